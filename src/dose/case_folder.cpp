#include "needle_guidance/dose/case_folder.h"

#include <yaml-cpp/yaml.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <stdexcept>
#include <vector>

namespace needle_guidance::dose {
namespace {

constexpr double kMm = 1e-3;

std::ofstream openOut(const std::string& path) {
  std::ofstream out(path);
  if (!out) {
    throw std::runtime_error("writeCaseFolder: cannot write '" + path + "'");
  }
  out.precision(10);
  return out;
}

const char* kindName(PointKind k) {
  return k == PointKind::kSurface ? "surface" : "volume";
}

/// Rows of a CSV with a header; every row must have the header's column count.
struct Csv {
  std::string path;
  std::vector<std::string> header;
  std::vector<std::vector<std::string>> rows;
  std::vector<int> lines;
  int column(const std::string& name) const {
    for (std::size_t i = 0; i < header.size(); ++i) {
      if (header[i] == name)
        return static_cast<int>(i);
    }
    throw std::invalid_argument(path + ": missing column '" + name + "'");
  }
  [[noreturn]] void fail(std::size_t row, const std::string& why) const {
    throw std::invalid_argument(path + ":" + std::to_string(lines[row]) + ": " + why);
  }
  double number(std::size_t row, const std::string& name) const {
    const std::string& text = rows[row][static_cast<std::size_t>(column(name))];
    try {
      std::size_t used = 0;
      const double v = std::stod(text, &used);
      if (used != text.size() || !std::isfinite(v))
        throw std::invalid_argument("");
      return v;
    } catch (const std::exception&) {
      fail(row, "column '" + name + "' value '" + text + "' is not a finite number");
    }
  }
  const std::string& text(std::size_t row, const std::string& name) const {
    return rows[row][static_cast<std::size_t>(column(name))];
  }
};

std::vector<std::string> split(const std::string& line) {
  std::vector<std::string> out;
  std::stringstream ss(line);
  std::string cell;
  while (std::getline(ss, cell, ','))
    out.push_back(cell);
  if (!line.empty() && line.back() == ',')
    out.emplace_back();
  return out;
}

Csv readCsv(const std::string& path) {
  std::ifstream in(path);
  if (!in) {
    throw std::invalid_argument(path + ": cannot be read");
  }
  Csv csv;
  csv.path = path;
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    if (!line.empty() && line.back() == '\r')
      line.pop_back();
    if (line.empty())
      continue;
    if (csv.header.empty()) {
      csv.header = split(line);
      continue;
    }
    auto cells = split(line);
    if (cells.size() != csv.header.size()) {
      throw std::invalid_argument(path + ":" + std::to_string(number) + ": " +
                                  std::to_string(cells.size()) + " columns, the header has " +
                                  std::to_string(csv.header.size()));
    }
    csv.rows.push_back(std::move(cells));
    csv.lines.push_back(number);
  }
  if (csv.header.empty()) {
    throw std::invalid_argument(path + ": empty file (a header is required)");
  }
  return csv;
}

PointKind parseKind(const Csv& csv, std::size_t row) {
  const std::string& k = csv.text(row, "kind");
  if (k == "surface")
    return PointKind::kSurface;
  if (k == "volume")
    return PointKind::kVolume;
  csv.fail(row, "kind '" + k + "' must be surface or volume");
}

}  // namespace

void writeCaseFolder(const HdrCase& c, const std::string& dir) {
  std::filesystem::create_directories(dir);
  {
    auto out = openOut(dir + "/case.yaml");
    out << "name: " << c.name << "\nsource: " << c.source
        << "\nair_kerma_strength_U: " << c.air_kerma_strength_U
        << "\nprescription_Gy: " << c.prescription_Gy << "\n";
  }
  {
    auto out = openOut(dir + "/structures.csv");
    out << "structure,role,contour,z_mm,x_mm,y_mm\n";
    for (const Structure& s : c.structures) {
      for (std::size_t k = 0; k < s.contours.size(); ++k) {
        for (const Point2d& p : s.contours[k].xy_m) {
          out << s.name << ',' << (s.role == StructureRole::kTarget ? "target" : "oar") << ',' << k
              << ',' << s.contours[k].z_m / kMm << ',' << p.x() / kMm << ',' << p.y() / kMm << '\n';
        }
      }
    }
  }
  {
    auto out = openOut(dir + "/catheters.csv");
    out << "catheter,point,x_mm,y_mm,z_mm\n";
    for (const Catheter& cat : c.catheters) {
      for (std::size_t k = 0; k < cat.points_m.size(); ++k) {
        const Point3& p = cat.points_m[k];
        out << cat.name << ',' << k << ',' << p.x() / kMm << ',' << p.y() / kMm << ','
            << p.z() / kMm << '\n';
      }
    }
  }
  {
    auto out = openOut(dir + "/dwells.csv");
    out << "catheter,index,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,time_s\n";
    for (std::size_t j = 0; j < c.dwells.size(); ++j) {
      const DwellPosition& d = c.dwells[j];
      out << c.catheters.at(static_cast<std::size_t>(d.catheter)).name << ',' << d.index << ','
          << d.position_m.x() / kMm << ',' << d.position_m.y() / kMm << ','
          << d.position_m.z() / kMm << ',' << d.axis.x() << ',' << d.axis.y() << ',' << d.axis.z()
          << ',' << (j < c.dwell_times_s.size() ? c.dwell_times_s[j] : 0.0) << '\n';
    }
  }
  {
    auto out = openOut(dir + "/points.csv");
    out << "structure,kind,x_mm,y_mm,z_mm\n";
    for (const DosePoint& p : c.points) {
      out << c.structures.at(static_cast<std::size_t>(p.structure)).name << ',' << kindName(p.kind)
          << ',' << p.position_m.x() / kMm << ',' << p.position_m.y() / kMm << ','
          << p.position_m.z() / kMm << '\n';
    }
  }
  {
    auto out = openOut(dir + "/criteria.csv");
    out << "structure,kind,min_Gy,max_Gy,weight_under,weight_over\n";
    for (const Criterion& cr : c.criteria) {
      out << cr.structure << ',' << kindName(cr.kind) << ',' << cr.min_Gy << ',' << cr.max_Gy << ','
          << cr.weight_under << ',' << cr.weight_over << '\n';
    }
  }
}

HdrCase readCaseFolder(const std::string& dir) {
  HdrCase c;
  const std::string yaml_path = dir + "/case.yaml";
  try {
    const YAML::Node root = YAML::LoadFile(yaml_path);
    c.name = root["name"].as<std::string>();
    c.source = root["source"].as<std::string>();
    c.air_kerma_strength_U = root["air_kerma_strength_U"].as<double>();
    c.prescription_Gy = root["prescription_Gy"].as<double>();
  } catch (const YAML::Exception& e) {
    throw std::invalid_argument(yaml_path + ": " + e.what());
  }
  if (!(c.air_kerma_strength_U > 0.0) || !(c.prescription_Gy > 0.0) ||
      !std::isfinite(c.air_kerma_strength_U) || !std::isfinite(c.prescription_Gy)) {
    throw std::invalid_argument(
        yaml_path + ": air_kerma_strength_U and prescription_Gy must be finite and > 0");
  }
  // Structures: contours keyed by (structure, contour index).
  const Csv s = readCsv(dir + "/structures.csv");
  std::map<std::string, std::size_t> structure_of;
  std::map<std::pair<std::size_t, int>, std::size_t> contour_of;
  for (std::size_t r = 0; r < s.rows.size(); ++r) {
    const std::string& name = s.text(r, "structure");
    auto it = structure_of.find(name);
    if (it == structure_of.end()) {
      const std::string& role = s.text(r, "role");
      if (role != "target" && role != "oar")
        s.fail(r, "role '" + role + "' must be target or oar");
      it = structure_of.emplace(name, c.structures.size()).first;
      c.structures.push_back(
          {name, role == "target" ? StructureRole::kTarget : StructureRole::kOrganAtRisk, {}});
    }
    Structure& st = c.structures[it->second];
    const int k = static_cast<int>(s.number(r, "contour"));
    auto ct = contour_of.find({it->second, k});
    if (ct == contour_of.end()) {
      ct = contour_of.emplace(std::make_pair(it->second, k), st.contours.size()).first;
      st.contours.push_back({s.number(r, "z_mm") * kMm, {}});
    }
    st.contours[ct->second].xy_m.emplace_back(s.number(r, "x_mm") * kMm, s.number(r, "y_mm") * kMm);
  }
  for (Structure& st : c.structures) {
    st.normalise();
  }
  const Csv k = readCsv(dir + "/catheters.csv");
  std::map<std::string, int> catheter_of;
  for (std::size_t r = 0; r < k.rows.size(); ++r) {
    const std::string& name = k.text(r, "catheter");
    auto it = catheter_of.find(name);
    if (it == catheter_of.end()) {
      it = catheter_of.emplace(name, static_cast<int>(c.catheters.size())).first;
      c.catheters.push_back({name, {}});
    }
    c.catheters[static_cast<std::size_t>(it->second)].points_m.emplace_back(
        k.number(r, "x_mm") * kMm, k.number(r, "y_mm") * kMm, k.number(r, "z_mm") * kMm);
  }
  const Csv d = readCsv(dir + "/dwells.csv");
  for (std::size_t r = 0; r < d.rows.size(); ++r) {
    const auto it = catheter_of.find(d.text(r, "catheter"));
    if (it == catheter_of.end())
      d.fail(r, "unknown catheter '" + d.text(r, "catheter") + "'");
    Point3 axis(d.number(r, "axis_x"), d.number(r, "axis_y"), d.number(r, "axis_z"));
    if (!(axis.norm() > 0.0))
      d.fail(r, "zero source axis");
    const double t = d.number(r, "time_s");
    if (t < 0.0)
      d.fail(r, "negative dwell time");
    c.dwells.push_back({it->second, static_cast<int>(d.number(r, "index")),
                        Point3(d.number(r, "x_mm"), d.number(r, "y_mm"), d.number(r, "z_mm")) * kMm,
                        axis.normalized()});
    c.dwell_times_s.push_back(t);
  }
  const Csv p = readCsv(dir + "/points.csv");
  for (std::size_t r = 0; r < p.rows.size(); ++r) {
    const auto it = structure_of.find(p.text(r, "structure"));
    if (it == structure_of.end())
      p.fail(r, "unknown structure '" + p.text(r, "structure") + "'");
    c.points.push_back(
        {static_cast<int>(it->second), parseKind(p, r),
         Point3(p.number(r, "x_mm"), p.number(r, "y_mm"), p.number(r, "z_mm")) * kMm});
  }
  const Csv cr = readCsv(dir + "/criteria.csv");
  for (std::size_t r = 0; r < cr.rows.size(); ++r) {
    c.criteria.push_back({cr.text(r, "structure"), parseKind(cr, r), cr.number(r, "min_Gy"),
                          cr.number(r, "max_Gy"), cr.number(r, "weight_under"),
                          cr.number(r, "weight_over")});
  }
  return c;
}

}  // namespace needle_guidance::dose
