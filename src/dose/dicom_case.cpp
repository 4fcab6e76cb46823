#include "needle_guidance/dose/dicom_case.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <limits>
#include <stdexcept>

#include "needle_guidance/format.h"

namespace needle_guidance::dose {
namespace {

/// An active clinical dwell this close to a candidate counts as on the candidate lattice [m].
constexpr double kOnLatticeTol_m = 0.5e-3;

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char ch) { return std::tolower(ch); });
  return s;
}

std::string trimmed(const std::string& s) {
  const auto b = s.find_first_not_of(" \t");
  const auto e = s.find_last_not_of(" \t");
  return b == std::string::npos ? "" : s.substr(b, e - b + 1);
}

/// Arc length along the polyline of the point on it nearest to p [m].
double arcOf(const std::vector<Point3>& line, const Point3& p) {
  double best = std::numeric_limits<double>::infinity(), best_arc = 0.0, along = 0.0;
  for (std::size_t i = 0; i + 1 < line.size(); ++i) {
    const Point3 d = line[i + 1] - line[i];
    const double len2 = d.squaredNorm();
    const double t = len2 > 0.0 ? std::clamp((p - line[i]).dot(d) / len2, 0.0, 1.0) : 0.0;
    const double dist = (line[i] + t * d - p).norm();
    if (dist < best) {
      best = dist;
      best_arc = along + t * std::sqrt(len2);
    }
    along += std::sqrt(len2);
  }
  return best_arc;
}

/// Point and unit direction towards the tip at arc length s along the polyline.
bool pointAt(const std::vector<Point3>& line, double s, Point3& p, Point3& towards_tip) {
  double along = 0.0;
  for (std::size_t i = 0; i + 1 < line.size(); ++i) {
    const double len = (line[i + 1] - line[i]).norm();
    if (len > 0.0 && s <= along + len + 1e-12) {
      p = line[i] + (s - along) / len * (line[i + 1] - line[i]);
      towards_tip = (line[i] - line[i + 1]) / len;
      return true;
    }
    along += len;
  }
  return false;
}

double polylineLength(const std::vector<Point3>& line) {
  double len = 0.0;
  for (std::size_t i = 0; i + 1 < line.size(); ++i)
    len += (line[i + 1] - line[i]).norm();
  return len;
}

/// Median spacing of consecutive dwells of one catheter (by index) [m]; 0 if none.
double planStep(const HdrCase& c) {
  std::vector<double> gaps;
  for (std::size_t i = 0; i + 1 < c.dwells.size(); ++i) {
    const DwellPosition& a = c.dwells[i];
    const DwellPosition& b = c.dwells[i + 1];
    const double gap = (a.position_m - b.position_m).norm();
    if (a.catheter == b.catheter && gap > 1e-4)
      gaps.push_back(gap);
  }
  if (gaps.empty())
    return 0.0;
  std::nth_element(gaps.begin(), gaps.begin() + gaps.size() / 2, gaps.end());
  return std::round(gaps[gaps.size() / 2] * 1e4) / 1e4;  // to 0.1 mm
}

PointKind parseKind(const std::string& text, const std::string& where) {
  if (text == "surface")
    return PointKind::kSurface;
  if (text == "volume")
    return PointKind::kVolume;
  throw std::invalid_argument(where + ": kind must be surface or volume, not '" + text + "'");
}

/// Maps the imported ROIs onto canonical names; returns the mapped structures in settings order.
std::vector<Structure> mapStructures(const HdrCase& imported, const DicomCaseSettings& s,
                                     const std::string& file, std::vector<std::string>& ignored) {
  std::vector<Structure> out;
  std::vector<bool> used(imported.structures.size(), false);
  for (std::size_t k = 0; k < s.structures.size(); ++k) {
    const auto& [canonical, aliases] = s.structures[k];
    int found = -1;
    for (std::size_t i = 0; i < imported.structures.size(); ++i) {
      const std::string name = lower(trimmed(imported.structures[i].name));
      for (const std::string& alias : aliases) {
        if (name == lower(trimmed(alias))) {
          if (found >= 0) {
            throw std::invalid_argument(
                "DICOM case: " + file + ": ROIs '" + imported.structures[found].name + "' and '" +
                imported.structures[i].name + "' both map to '" + canonical +
                "'; name one in the case file's structures: " + canonical);
          }
          found = static_cast<int>(i);
        }
      }
    }
    if (found < 0) {
      if (k == 0) {
        std::string names, tried;
        for (const Structure& st : imported.structures)
          names += (names.empty() ? "'" : ", '") + st.name + "'";
        for (const std::string& a : aliases)
          tried += (tried.empty() ? "" : ", ") + a;
        throw std::invalid_argument("DICOM case: " + file + ": no ROI maps to the target '" +
                                    canonical + "' (names tried: " + tried +
                                    "); ROIs found: " + (names.empty() ? "none" : names) +
                                    "; give a case file whose structures map these names");
      }
      continue;
    }
    used[static_cast<std::size_t>(found)] = true;
    Structure st = imported.structures[static_cast<std::size_t>(found)];
    st.name = canonical;
    st.role = k == 0 ? StructureRole::kTarget : StructureRole::kOrganAtRisk;
    out.push_back(st);
  }
  for (std::size_t i = 0; i < imported.structures.size(); ++i) {
    if (!used[i])
      ignored.push_back(imported.structures[i].name);
  }
  return out;
}

/// Notes structures lying (partly) outside the RTDOSE grid.
void checkDoseGrid(const DicomCase& dc, std::vector<std::string>& notes) {
  if (dc.files.dose.empty())
    return;
  const DoseGrid grid = readRtDose(dc.files.dose);
  const double z0 = grid.origin_m.z() + std::min(grid.z_offsets_m.front(), grid.z_offsets_m.back());
  const double z1 = grid.origin_m.z() + std::max(grid.z_offsets_m.front(), grid.z_offsets_m.back());
  const Point3 lo_g(grid.origin_m.x(), grid.origin_m.y(), z0);
  const Point3 hi_g(grid.origin_m.x() + (grid.sizes[0] - 1) * grid.spacing_m.x(),
                    grid.origin_m.y() + (grid.sizes[1] - 1) * grid.spacing_m.y(), z1);
  for (const Structure& s : dc.planning.structures) {
    Point3 lo, hi;
    s.bounds(lo, hi);
    if ((lo.array() < lo_g.array() - 1e-6).any() || (hi.array() > hi_g.array() + 1e-6).any()) {
      notes.push_back(
          "structure '" + s.name + "' extends outside the RTDOSE grid of " + dc.files.dose +
          ": a DVH from that RTDOSE would be incomplete (our indices use our own dose grid)");
    }
  }
}

void relateClinical(DicomCase& dc) {
  const auto& clinical = dc.clinical.dwells;
  for (std::size_t j = 0; j < clinical.size(); ++j) {
    if (!(dc.clinical.dwell_times_s[j] > 0.0))
      continue;
    ++dc.clinical_active;
    double best = std::numeric_limits<double>::infinity();
    for (const DwellPosition& d : dc.planning.dwells) {
      if (d.catheter == clinical[j].catheter)
        best = std::min(best, (d.position_m - clinical[j].position_m).norm());
    }
    if (best <= kOnLatticeTol_m)
      ++dc.clinical_active_on_candidates;
    if (std::isfinite(best))
      dc.clinical_max_offset_m = std::max(dc.clinical_max_offset_m, best);
  }
}

}  // namespace

DicomCaseSettings readDicomCaseSettings(const std::string& path) {
  YAML::Node root;
  try {
    root = YAML::LoadFile(path);
  } catch (const YAML::Exception& e) {
    throw std::invalid_argument("DICOM case file " + path + ": " + e.what());
  }
  DicomCaseSettings s;
  const std::string where = "DICOM case file " + path;
  try {
    if (root["structures"]) {
      s.structures.clear();
      for (const auto& entry : root["structures"]) {
        std::vector<std::string> names;
        for (const auto& n : entry.second)
          names.push_back(n.as<std::string>());
        s.structures.emplace_back(lower(entry.first.as<std::string>()), names);
      }
      if (s.structures.empty())
        throw std::invalid_argument(where + ": structures: needs a target entry");
    }
    if (root["margin_mm"])
      s.margin_m = root["margin_mm"].as<double>() * 1e-3;
    if (root["surface_spacing_mm"])
      s.points.surface_spacing_m = root["surface_spacing_mm"].as<double>() * 1e-3;
    if (root["volume_points"])
      s.points.volume_points = root["volume_points"].as<int>();
    if (root["min_points_per_structure"])
      s.points.min_per_structure = root["min_points_per_structure"].as<int>();
    if (root["seed"])
      s.points.seed = root["seed"].as<unsigned>();
    if (root["source"])
      s.source = root["source"].as<std::string>();
    for (const auto& c : root["criteria"]) {
      Criterion k;
      k.structure = lower(c["structure"].as<std::string>());
      k.kind = parseKind(c["kind"].as<std::string>(), where + ": criteria");
      k.min_Gy = c["min_Gy"].as<double>();
      k.max_Gy = c["max_Gy"].as<double>();
      k.weight_under = c["weight_under"].as<double>();
      k.weight_over = c["weight_over"].as<double>();
      s.criteria.push_back(k);
    }
    for (const auto& c : root["dvh_criteria"]) {
      s.dvh_criteria.push_back(c.as<std::string>());
      try {
        parseDvhCriterion(s.dvh_criteria.back(), 1.0);
      } catch (const std::invalid_argument& e) {
        throw std::invalid_argument(where + ": dvh_criteria: " + e.what());
      }
    }
  } catch (const YAML::Exception& e) {
    throw std::invalid_argument(where + ": " + e.what());
  }
  if (!(s.margin_m >= 0.0) || !(s.points.surface_spacing_m > 0.0) || s.points.volume_points < 0) {
    throw std::invalid_argument(
        where + ": margin_mm >= 0, surface_spacing_mm > 0, volume_points >= 0 required");
  }
  return s;
}

std::vector<DvhCriterion> dvhCriteria(const DicomCaseSettings& settings, double rx) {
  if (settings.dvh_criteria.empty())
    return defaultDvhCriteria(rx);
  std::vector<DvhCriterion> out;
  for (const std::string& text : settings.dvh_criteria)
    out.push_back(parseDvhCriterion(text, rx));
  return out;
}

std::vector<DwellPosition> candidateDwells(const HdrCase& c,
                                           const std::vector<DwellPosition>& clinical,
                                           double step_m, double margin_m) {
  if (!(step_m > 0.0))
    throw std::invalid_argument("candidateDwells: step must be > 0");
  const Structure* target = nullptr;
  for (const Structure& s : c.structures) {
    if (s.role == StructureRole::kTarget) {
      target = &s;
      break;
    }
  }
  if (!target)
    throw std::invalid_argument("candidateDwells: case '" + c.name + "' has no target structure");
  std::vector<DwellPosition> out;
  for (std::size_t k = 0; k < c.catheters.size(); ++k) {
    const auto& line = c.catheters[k].points_m;
    if (line.size() < 2)
      continue;
    double anchor =
        0.0;  // arc of the catheter's first clinical dwell: the lattice passes through it
    for (const DwellPosition& d : clinical) {
      if (d.catheter == static_cast<int>(k)) {
        anchor = arcOf(line, d.position_m);
        break;
      }
    }
    const double first = anchor - std::floor(anchor / step_m + 1e-9) * step_m;
    const double length = polylineLength(line);
    int index = 0;
    for (double s = first; s <= length + 1e-9; s += step_m, ++index) {
      Point3 p, axis;
      if (!pointAt(line, std::min(s, length), p, axis))
        continue;
      if (target->contains(p) || target->contains(p + margin_m * axis) ||
          target->contains(p - margin_m * axis)) {
        out.push_back({static_cast<int>(k), index, p, axis});
      }
    }
  }
  return out;
}

DicomCase loadDicomCase(const std::string& dir, const DicomCaseSettings& settings) {
  DicomCase dc;
  dc.files = findDicomRtFiles(dir);
  if (dc.files.structure_set.empty()) {
    throw std::invalid_argument("DICOM case: " + dir +
                                ": no RTSTRUCT: structures are needed to plan");
  }
  DicomRtImportOptions io;
  io.source_name = settings.source;
  HdrCase imported = importDicomRt(dc.files.plan, dc.files.structure_set, &dc.import_report, io);
  dc.notes = dc.import_report.warnings;
  HdrCase& c = dc.planning;
  c.name = imported.name.empty() ? std::filesystem::path(dir).filename().string() : imported.name;
  c.source = imported.source;
  c.air_kerma_strength_U = imported.air_kerma_strength_U;
  c.prescription_Gy = imported.prescription_Gy;
  c.catheters = imported.catheters;
  c.structures = mapStructures(imported, settings, dc.files.structure_set, dc.ignored_rois);
  for (const std::string& name : dc.ignored_rois) {
    dc.notes.push_back("ROI '" + name + "' is not in the structure mapping: ignored");
  }
  dc.step_m = planStep(imported);
  if (!(dc.step_m > 0.0)) {
    dc.step_m = 5e-3;
    dc.notes.push_back("the plan has no two dwells in one catheter: dwell step 5 mm assumed");
  }
  c.dwells = candidateDwells(c, imported.dwells, dc.step_m, settings.margin_m);
  for (std::size_t k = 0; k < c.catheters.size(); ++k) {
    const bool any = std::any_of(c.dwells.begin(), c.dwells.end(), [&](const DwellPosition& d) {
      return d.catheter == static_cast<int>(k);
    });
    if (!any) {
      dc.notes.push_back("catheter '" + c.catheters[k].name + "' does not pass within " +
                         formatNumber(settings.margin_m * 1e3) +
                         " mm of the target: no candidate dwells on it");
    }
  }
  if (c.dwells.empty()) {
    throw std::invalid_argument("DICOM case: " + dc.files.plan +
                                ": no catheter passes through the target");
  }
  const std::vector<Criterion> criteria =
      settings.criteria.empty() ? table61Criteria(c.prescription_Gy) : settings.criteria;
  for (const Criterion& k : criteria) {
    if (c.structureIndex(k.structure) >= 0) {
      c.criteria.push_back(k);
    } else if (!settings.criteria.empty()) {
      throw std::invalid_argument("DICOM case: criterion on '" + k.structure +
                                  "', a structure the case lacks");
    }
  }
  DosePointOptions po = settings.points;
  c.points = makeDosePoints(c, po);
  dc.clinical = c;
  dc.clinical.dwells = imported.dwells;
  dc.clinical.dwell_times_s = imported.dwell_times_s;
  relateClinical(dc);
  checkDoseGrid(dc, dc.notes);
  return dc;
}

std::map<std::string, std::vector<std::string>> comparisonIndexSpecs() {
  return {{"prostate", {"V100", "V150", "V200", "D90"}},
          {"urethra", {"D10", "D0.1cc", "V125"}},
          {"rectum", {"D2cc", "D0.1cc", "V75"}},
          {"bladder", {"D2cc", "D0.1cc", "V75"}}};
}

std::map<std::string, DoseVolumeIndex> comparisonIndexSet(const std::vector<StructureDose>& doses,
                                                          double rx) {
  return indexSet(doses, comparisonIndexSpecs(), rx);
}

std::map<std::string, double> comparisonIndices(const std::vector<StructureDose>& doses,
                                                double rx) {
  return definedValues(comparisonIndexSet(doses, rx));
}

void exportDicomRtPlan(const HdrCase& plan, const Tg43Source& source, const DoseGrid* dose_geometry,
                       const std::string& dir, const std::string& clinical_structure_set) {
  std::filesystem::create_directories(dir);
  DicomExportContext ctx = clinical_structure_set.empty()
                               ? newExportContext()
                               : exportContextFrom(clinical_structure_set);
  const std::string rs = (std::filesystem::path(dir) / "RS.dcm").string();
  const std::string rp = (std::filesystem::path(dir) / "RP.dcm").string();
  ctx.sop_instance_uid = "";
  DicomExportContext rs_ctx = ctx;
  rs_ctx.sop_instance_uid = newExportContext().study_uid;  // a fresh UID
  writeRtStruct(plan, rs, rs_ctx);
  DicomExportContext rp_ctx = ctx;
  rp_ctx.sop_instance_uid = newExportContext().study_uid;
  rp_ctx.structure_set_uid = rs_ctx.sop_instance_uid;
  rp_ctx.series_number = 2;
  writeRtPlan(plan, rp, DwellTimeEncoding::kStandardCumulative, rp_ctx);
  if (dose_geometry) {
    DoseGrid grid = computeDoseOnGrid(plan, source, *dose_geometry);
    grid.summation_type = "PLAN";
    DicomExportContext rd_ctx = ctx;
    rd_ctx.plan_uid = rp_ctx.sop_instance_uid;
    rd_ctx.series_number = 3;
    writeRtDose(grid, (std::filesystem::path(dir) / "RD.dcm").string(), rd_ctx);
  }
}

/// The planning case with the clinical plan's dwell times on the candidate dwells (an active
/// clinical dwell within 1 mm of a candidate on its catheter adds its time there), so that the
/// planner scores the clinical plan on its own model.
HdrCase planningWithClinicalTimes(const DicomCase& dc) {
  HdrCase c = dc.planning;
  c.dwell_times_s.assign(c.dwells.size(), 0.0);
  for (std::size_t j = 0; j < dc.clinical.dwells.size(); ++j) {
    double best = 1e-3;
    int at = -1;
    for (std::size_t i = 0; i < c.dwells.size(); ++i) {
      const double dist = (c.dwells[i].position_m - dc.clinical.dwells[j].position_m).norm();
      if (c.dwells[i].catheter == dc.clinical.dwells[j].catheter && dist < best) {
        best = dist;
        at = static_cast<int>(i);
      }
    }
    if (at >= 0)
      c.dwell_times_s[static_cast<std::size_t>(at)] += dc.clinical.dwell_times_s[j];
  }
  return c;
}

}  // namespace needle_guidance::dose
