// TG-43 dose calculation (dissertation 6.2): AAPM TG-43U1 (Rivard et al., Med. Phys. 31 (2004)
// 633-674) with the AAPM/ESTRO high-energy consensus data (Perez-Calatayud et al., Med. Phys. 39
// (2012) 2904-2929). See include/needle_guidance/dose/tg43.h and config/sources/README.md.
//
// Choices outside the tabulated data (all documented here, none returns NaN/inf):
//  * Points inside the source. The line-source geometry function is singular on the active
//    segment (r sin(theta) = 0, |r cos(theta)| <= L/2) and the tables have no meaning inside the
//    capsule. A point closer than kMinCoreDistance_m (0.5 mm, at least the outer capsule radius
//    of the HDR Ir-192 sources shipped) to the active segment is moved along the direction away
//    from its nearest segment point onto that distance (a point on the segment itself moves
//    perpendicular to the axis); the dose there is returned. Points farther away, i.e. every
//    point in water, are evaluated unchanged. For r -> 0 this gives the dose at 0.5 mm beside the
//    source centre; for on-axis points at r <= L/2 + 0.5 mm it gives the dose at 0.5 mm beside
//    the nearest point of the active segment (or at r = L/2 + 0.5 mm on the axis beyond the tip).
//  * g_L(r): linear interpolation; below the first tabulated r the first value is held,
//    beyond the last one linear extrapolation from the last two points, clamped at >= 0
//    (TG-43U1 section II.A.3 and appendix C: nearest neighbour at short distances, linear
//    extrapolation from the last two points at large distances).
//  * F(r, theta): bilinear in (theta, r); outside the tabulated r range the nearest r column
//    (TG-43U1 appendix C), outside the tabulated theta range the nearest row.
//  * 1-D formalism: phi_an(r) is the TG-43U1 eq. (10) definition, the solid-angle average of the
//    2-D dose rate at r relative to the transverse-axis dose rate, i.e. of
//    F(r, theta) G_L(r, theta) / G_L(r, theta0) (for r >> L this is the average of F alone).
//    It is integrated once at the tabulated F radii and interpolated linearly in r (nearest
//    column outside). The radial distance is clamped at kMinCoreDistance_m like the 2-D model.
#include "needle_guidance/dose/tg43.h"
#include "needle_guidance/math.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "needle_guidance/format.h"
#include "needle_guidance/package_paths.h"

namespace needle_guidance::dose {
namespace {

namespace fs = std::filesystem;

constexpr double kCm_m = 0.01;                     ///< 1 cm in m
constexpr double kDeg_rad = kPi / 180.0;           ///< 1 deg in rad
constexpr double kR0_m = 1.0 * kCm_m;              ///< TG-43 reference distance r0 = 1 cm
constexpr double kTheta0_rad = kPi / 2.0;          ///< TG-43 reference angle theta0 = 90 deg
constexpr double kCGyPerH_GyPerS = 0.01 / 3600.0;  ///< 1 cGy h^-1 in Gy s^-1
/// Minimum distance from the active segment at which the dose is evaluated (see file header).
constexpr double kMinCoreDistance_m = 0.5e-3;
/// theta outside [0, pi] by at most this much is round-off and is clamped; more is an error.
constexpr double kThetaRoundOff_rad = 1e-6;
/// g_L(r0) and F(r0, theta0) must be 1 (TG-43 normalisation) within this; catches unit mix-ups.
constexpr double kNormalisationTol = 0.01;
/// Below this ratio L y / (r^2 - L^2/4) the on-axis form of G_L is used (error ~ ratio^2 / 3).
constexpr double kOnAxisRatio = 1e-9;
/// Simpson sub-intervals per tabulated theta interval for phi_an (F is linear in between).
constexpr int kPhiAnSubintervals = 16;

std::string label(const std::string& name) {
  return "Tg43Source '" + (name.empty() ? std::string("<unnamed>") : name) + "'";
}

std::string fmt(double v) {
  return formatNumber(v, 10);
}

/// Throws unless v is non-empty, finite and strictly increasing.
void checkAbscissae(const std::vector<double>& v, const std::string& what, const std::string& name,
                    std::size_t min_size) {
  if (v.size() < min_size) {
    throw std::invalid_argument(label(name) + ": " + what + " has " + std::to_string(v.size()) +
                                " entries, at least " + std::to_string(min_size) + " needed");
  }
  for (std::size_t i = 0; i < v.size(); ++i) {
    if (!std::isfinite(v[i])) {
      throw std::invalid_argument(label(name) + ": " + what + "[" + std::to_string(i) +
                                  "] is not finite");
    }
    if (i > 0 && !(v[i] > v[i - 1])) {
      throw std::invalid_argument(label(name) + ": " + what +
                                  " is not strictly increasing at index " + std::to_string(i) +
                                  " (" + fmt(v[i - 1]) + " then " + fmt(v[i]) + ")");
    }
  }
}

/// Interval index i (x[i] <= v <= x[i+1]) and weight t in [0, 1]; v outside the range gives the
/// end interval with t = 0 or 1 (nearest value). x has >= 2 strictly increasing entries.
std::pair<std::size_t, double> bracket(const std::vector<double>& x, double v) {
  const std::size_t n = x.size();
  if (!(v > x.front())) {
    return {0, 0.0};
  }
  if (!(v < x.back())) {
    return {n - 2, 1.0};
  }
  const std::size_t i =
      static_cast<std::size_t>(std::upper_bound(x.begin(), x.end(), v) - x.begin()) - 1;
  return {i, (v - x[i]) / (x[i + 1] - x[i])};
}

/// Line-source geometry function G_L [m^-2] (TG-43U1 eq. 4) at axial coordinate z and distance
/// y >= 0 from the axis, source centred at 0 with active length L. beta = atan2(L y, r^2 - L^2/4)
/// is the angle the segment subtends at the point (from the cross and dot products of the vectors
/// to its ends), stable on both sides of the source; on the axis G_L = 1 / (r^2 - L^2/4).
/// The caller keeps the point off the segment (clampOutsideCore), so the result is finite.
double geometryLine(double z, double y, double length_m) {
  const double c = z * z + y * y - 0.25 * length_m * length_m;
  const double a = length_m * y;
  if (a <= kOnAxisRatio * c) {
    return 1.0 / c;
  }
  return std::atan2(a, c) / a;
}

/// Moves (z, y) onto distance kMinCoreDistance_m from the active segment [-L/2, L/2] x {0} if it
/// is closer (see file header); unchanged otherwise.
std::pair<double, double> clampOutsideCore(double z, double y, double length_m) {
  const double zc = std::clamp(z, -0.5 * length_m, 0.5 * length_m);
  const double dz = z - zc;
  const double d = std::hypot(dz, y);
  if (d >= kMinCoreDistance_m) {
    return {z, y};
  }
  if (d > 0.0) {
    return {zc + kMinCoreDistance_m * dz / d, kMinCoreDistance_m * y / d};
  }
  return {zc, kMinCoreDistance_m};
}

/// g_L(r) with the extrapolation rules of the file header.
double radialDose(const Tg43Data& d, double r) {
  const auto& x = d.gL_r_m;
  const auto& g = d.gL;
  const std::size_t n = x.size();
  if (!(r > x.front())) {
    return g.front();
  }
  if (r >= x.back()) {
    const double slope = (g[n - 1] - g[n - 2]) / (x[n - 1] - x[n - 2]);
    return std::max(0.0, g[n - 1] + slope * (r - x[n - 1]));
  }
  const auto [i, t] = bracket(x, r);
  return g[i] + t * (g[i + 1] - g[i]);
}

/// F(r, theta), bilinear in (theta, r), nearest row / column outside the table.
double anisotropy(const Tg43Data& d, double r, double theta) {
  const auto [i, ti] = bracket(d.F_theta_rad, theta);
  const auto [j, tj] = bracket(d.F_r_m, r);
  const Eigen::MatrixXd& f = d.F;
  const double f0 = f(i, j) + tj * (f(i, j + 1) - f(i, j));
  const double f1 = f(i + 1, j) + tj * (f(i + 1, j + 1) - f(i + 1, j));
  return f0 + ti * (f1 - f0);
}

/// 2-D dose rate per U divided by Lambda (dimensionless) at (z, y), y >= 0.
double lineRatio(const Tg43Data& d, double g_ref, double z, double y) {
  const double length_m = d.active_length_m;
  const auto [zc, yc] = clampOutsideCore(z, y, length_m);
  const double r = std::hypot(zc, yc);
  const double theta = std::atan2(yc, zc);  // in [0, pi] because yc >= 0
  return geometryLine(zc, yc, length_m) / g_ref * radialDose(d, r) * anisotropy(d, r, theta);
}

/// phi_an(r) of TG-43U1 eq. (10): integral over theta of Ddot(r, theta) sin(theta) / 2, divided by
/// Ddot(r, theta0); composite Simpson on every tabulated theta interval (F is linear there).
double phiAn(const Tg43Data& d, double g_ref, double r) {
  std::vector<double> knots{0.0};
  for (double t : d.F_theta_rad) {
    if (t > knots.back() && t < kPi) {
      knots.push_back(t);
    }
  }
  knots.push_back(kPi);
  const auto f = [&](double theta) {
    return lineRatio(d, g_ref, r * std::cos(theta), r * std::sin(theta)) * std::sin(theta);
  };
  double integral = 0.0;
  for (std::size_t k = 0; k + 1 < knots.size(); ++k) {
    const double a = knots[k];
    const double h = (knots[k + 1] - a) / kPhiAnSubintervals;
    double s = f(a) + f(knots[k + 1]);
    for (int m = 1; m < kPhiAnSubintervals; ++m) {
      s += (m % 2 == 1 ? 4.0 : 2.0) * f(a + m * h);
    }
    integral += s * h / 3.0;
  }
  return 0.5 * integral / lineRatio(d, g_ref, 0.0, r);
}

// ---- file reading ------------------------------------------------------------------------------

struct CsvRow {
  int line = 0;
  std::vector<std::string> cells;
};

std::string trim(const std::string& s) {
  const auto first = s.find_first_not_of(" \t\r\n");
  if (first == std::string::npos) {
    return "";
  }
  const auto last = s.find_last_not_of(" \t\r\n");
  return s.substr(first, last - first + 1);
}

std::string lower(std::string s) {
  for (char& c : s) {
    c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  }
  return s;
}

std::string where(const fs::path& file, int line) {
  return file.string() + ":" + std::to_string(line);
}

/// Non-blank, non-comment ('#') lines split at commas, cells trimmed.
std::vector<CsvRow> readCsv(const fs::path& file) {
  std::ifstream in(file);
  if (!in) {
    throw std::invalid_argument(file.string() + ": cannot open (" + std::strerror(errno) + ")");
  }
  std::vector<CsvRow> rows;
  std::string text;
  int line = 0;
  while (std::getline(in, text)) {
    ++line;
    text = trim(text);
    if (text.empty() || text[0] == '#') {
      continue;
    }
    CsvRow row;
    row.line = line;
    std::size_t start = 0;
    while (true) {
      const std::size_t comma = text.find(',', start);
      row.cells.push_back(
          trim(text.substr(start, comma == std::string::npos ? std::string::npos : comma - start)));
      if (comma == std::string::npos) {
        break;
      }
      start = comma + 1;
    }
    rows.push_back(std::move(row));
  }
  if (in.bad()) {
    throw std::invalid_argument(file.string() + ": read error");
  }
  return rows;
}

double parseNumber(const std::string& cell, const fs::path& file, int line,
                   const std::string& what) {
  const char* begin = cell.c_str();
  char* end = nullptr;
  errno = 0;
  const double v = std::strtod(begin, &end);
  if (cell.empty() || end == begin || *end != '\0' || errno == ERANGE || !std::isfinite(v)) {
    throw std::invalid_argument(where(file, line) + ": " + what + " '" + cell +
                                "' is not a finite number");
  }
  return v;
}

/// radial_dose_gL.csv: header "r_cm,gL", then r [cm] strictly increasing >= 0, gL >= 0.
void readRadialDose(const fs::path& file, Tg43Data& d) {
  const std::vector<CsvRow> rows = readCsv(file);
  if (rows.empty()) {
    throw std::invalid_argument(file.string() + ": empty file (expected header 'r_cm,gL')");
  }
  const CsvRow& header = rows.front();
  if (header.cells.size() != 2 || lower(header.cells[0]) != "r_cm" ||
      lower(header.cells[1]) != "gl") {
    throw std::invalid_argument(where(file, header.line) + ": expected header 'r_cm,gL'");
  }
  for (std::size_t k = 1; k < rows.size(); ++k) {
    const CsvRow& row = rows[k];
    if (row.cells.size() != 2) {
      throw std::invalid_argument(where(file, row.line) + ": expected 2 values (r_cm,gL), got " +
                                  std::to_string(row.cells.size()));
    }
    const double r_cm = parseNumber(row.cells[0], file, row.line, "r_cm");
    const double g = parseNumber(row.cells[1], file, row.line, "gL");
    if (r_cm < 0.0) {
      throw std::invalid_argument(where(file, row.line) + ": r_cm = " + fmt(r_cm) + " is negative");
    }
    if (g < 0.0) {
      throw std::invalid_argument(where(file, row.line) + ": gL = " + fmt(g) + " is negative");
    }
    const double r_m = r_cm * kCm_m;
    if (!d.gL_r_m.empty() && !(r_m > d.gL_r_m.back())) {
      throw std::invalid_argument(
          where(file, row.line) + ": r_cm = " + fmt(r_cm) + " does not increase (previous r_cm = " +
          fmt(d.gL_r_m.back() / kCm_m) + "); r must be strictly increasing");
    }
    d.gL_r_m.push_back(r_m);
    d.gL.push_back(g);
  }
  if (d.gL.size() < 2) {
    throw std::invalid_argument(file.string() + ": " + std::to_string(d.gL.size()) +
                                " data rows, at least 2 needed");
  }
}

/// anisotropy_F.csv: header "theta_deg,<r_cm>,...", then one row per theta [deg] in [0, 180].
void readAnisotropy(const fs::path& file, Tg43Data& d) {
  const std::vector<CsvRow> rows = readCsv(file);
  if (rows.empty()) {
    throw std::invalid_argument(file.string() +
                                ": empty file (expected header 'theta_deg,<r_cm>,...')");
  }
  const CsvRow& header = rows.front();
  if (header.cells.size() < 3 || lower(header.cells[0]) != "theta_deg") {
    throw std::invalid_argument(
        where(file, header.line) +
        ": expected header 'theta_deg,<r_cm>,<r_cm>,...' with at least 2 r columns");
  }
  for (std::size_t c = 1; c < header.cells.size(); ++c) {
    const double r_cm = parseNumber(header.cells[c], file, header.line, "header r_cm");
    if (r_cm < 0.0) {
      throw std::invalid_argument(where(file, header.line) + ": r_cm = " + fmt(r_cm) +
                                  " is negative");
    }
    const double r_m = r_cm * kCm_m;
    if (!d.F_r_m.empty() && !(r_m > d.F_r_m.back())) {
      throw std::invalid_argument(where(file, header.line) + ": header r_cm = " + fmt(r_cm) +
                                  " does not increase (previous " + fmt(d.F_r_m.back() / kCm_m) +
                                  "); r columns must be strictly increasing");
    }
    d.F_r_m.push_back(r_m);
  }
  const std::size_t ncol = d.F_r_m.size();
  std::vector<std::vector<double>> values;
  for (std::size_t k = 1; k < rows.size(); ++k) {
    const CsvRow& row = rows[k];
    if (row.cells.size() != ncol + 1) {
      throw std::invalid_argument(where(file, row.line) + ": expected " + std::to_string(ncol + 1) +
                                  " values (theta_deg and one F per r column), got " +
                                  std::to_string(row.cells.size()));
    }
    const double theta_deg = parseNumber(row.cells[0], file, row.line, "theta_deg");
    if (theta_deg < 0.0 || theta_deg > 180.0) {
      throw std::invalid_argument(where(file, row.line) + ": theta_deg = " + fmt(theta_deg) +
                                  " is outside [0, 180]");
    }
    const double theta_rad = theta_deg * kDeg_rad;
    if (!d.F_theta_rad.empty() && !(theta_rad > d.F_theta_rad.back())) {
      throw std::invalid_argument(where(file, row.line) + ": theta_deg = " + fmt(theta_deg) +
                                  " does not increase (previous " +
                                  fmt(d.F_theta_rad.back() / kDeg_rad) +
                                  "); theta rows must be strictly increasing");
    }
    d.F_theta_rad.push_back(theta_rad);
    std::vector<double> f(ncol);
    for (std::size_t c = 0; c < ncol; ++c) {
      f[c] = parseNumber(row.cells[c + 1], file, row.line, "F");
      if (f[c] < 0.0) {
        throw std::invalid_argument(where(file, row.line) + ": F = " + fmt(f[c]) + " (column " +
                                    std::to_string(c + 2) + ") is negative");
      }
    }
    values.push_back(std::move(f));
  }
  if (values.size() < 2) {
    throw std::invalid_argument(file.string() + ": " + std::to_string(values.size()) +
                                " theta rows, at least 2 needed");
  }
  d.F.resize(static_cast<Eigen::Index>(values.size()), static_cast<Eigen::Index>(ncol));
  for (std::size_t i = 0; i < values.size(); ++i) {
    for (std::size_t c = 0; c < ncol; ++c) {
      d.F(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(c)) = values[i][c];
    }
  }
}

/// A positive finite number under `key` in source.yaml.
double readYamlPositive(const YAML::Node& root, const std::string& key, const fs::path& file) {
  const YAML::Node node = root[key];
  if (!node) {
    throw std::invalid_argument(file.string() + ": missing key '" + key + "'");
  }
  const std::string at = where(file, node.Mark().line + 1);
  double v = 0.0;
  try {
    v = node.as<double>();
  } catch (const YAML::Exception&) {
    throw std::invalid_argument(at + ": '" + key + "' is not a number");
  }
  if (!std::isfinite(v) || v <= 0.0) {
    throw std::invalid_argument(at + ": '" + key + "' = " + fmt(v) +
                                " must be positive and finite");
  }
  return v;
}

void readSourceYaml(const fs::path& file, Tg43Data& d) {
  if (!fs::is_regular_file(file)) {
    throw std::invalid_argument(file.string() + ": cannot open (no such file)");
  }
  YAML::Node root;
  try {
    root = YAML::LoadFile(file.string());
  } catch (const YAML::ParserException& e) {
    throw std::invalid_argument(where(file, e.mark.line + 1) + ": YAML syntax error: " + e.msg);
  } catch (const YAML::Exception& e) {
    throw std::invalid_argument(file.string() + ": cannot read: " + e.what());
  }
  if (!root.IsMap()) {
    throw std::invalid_argument(where(file, 1) + ": expected a YAML mapping");
  }
  d.dose_rate_constant_cGy_per_h_per_U =
      readYamlPositive(root, "dose_rate_constant_Lambda_cGy_per_h_per_U", file);
  d.active_length_m = readYamlPositive(root, "active_length_L_cm", file) * kCm_m;
}

fs::path sourcesDir() {
  return configDir() / "sources";
}

}  // namespace

// ---- Tg43Source --------------------------------------------------------------------------------

Tg43Source::Tg43Source(Tg43Data data) : data_(std::move(data)) {
  const std::string& name = data_.name;
  const double lambda = data_.dose_rate_constant_cGy_per_h_per_U;
  const double length_m = data_.active_length_m;
  if (!std::isfinite(lambda) || lambda <= 0.0) {
    throw std::invalid_argument(label(name) + ": dose-rate constant Lambda = " + fmt(lambda) +
                                " cGy/(h U) must be positive and finite");
  }
  if (!std::isfinite(length_m) || length_m <= 0.0) {
    throw std::invalid_argument(label(name) + ": active length L = " + fmt(length_m) +
                                " m must be positive and finite");
  }
  checkAbscissae(data_.gL_r_m, "g_L radii gL_r_m", name, 2);
  if (data_.gL.size() != data_.gL_r_m.size()) {
    throw std::invalid_argument(label(name) + ": " + std::to_string(data_.gL.size()) +
                                " g_L values for " + std::to_string(data_.gL_r_m.size()) +
                                " radii");
  }
  if (data_.gL_r_m.front() < 0.0) {
    throw std::invalid_argument(label(name) + ": negative g_L radius");
  }
  for (std::size_t i = 0; i < data_.gL.size(); ++i) {
    if (!std::isfinite(data_.gL[i]) || data_.gL[i] < 0.0) {
      throw std::invalid_argument(label(name) + ": g_L[" + std::to_string(i) +
                                  "] = " + fmt(data_.gL[i]) + " is not finite and non-negative");
    }
  }
  checkAbscissae(data_.F_theta_rad, "anisotropy angles F_theta_rad", name, 2);
  if (data_.F_theta_rad.front() < -kThetaRoundOff_rad ||
      data_.F_theta_rad.back() > kPi + kThetaRoundOff_rad) {
    throw std::invalid_argument(label(name) + ": anisotropy angles must lie in [0, pi] rad");
  }
  checkAbscissae(data_.F_r_m, "anisotropy radii F_r_m", name, 2);
  if (data_.F_r_m.front() < 0.0) {
    throw std::invalid_argument(label(name) + ": negative anisotropy radius");
  }
  if (data_.F.rows() != static_cast<Eigen::Index>(data_.F_theta_rad.size()) ||
      data_.F.cols() != static_cast<Eigen::Index>(data_.F_r_m.size())) {
    throw std::invalid_argument(label(name) + ": F is " + std::to_string(data_.F.rows()) + " x " +
                                std::to_string(data_.F.cols()) + ", expected " +
                                std::to_string(data_.F_theta_rad.size()) + " (theta) x " +
                                std::to_string(data_.F_r_m.size()) + " (r)");
  }
  for (Eigen::Index i = 0; i < data_.F.rows(); ++i) {
    for (Eigen::Index j = 0; j < data_.F.cols(); ++j) {
      if (!std::isfinite(data_.F(i, j)) || data_.F(i, j) < 0.0) {
        throw std::invalid_argument(label(name) + ": F(theta index " + std::to_string(i) +
                                    ", r index " + std::to_string(j) + ") = " + fmt(data_.F(i, j)) +
                                    " is not finite and non-negative");
      }
    }
  }
  // TG-43 normalisation g_L(r0) = F(r0, theta0) = 1; a large mismatch means wrong units or columns.
  const double g0 = radialDose(data_, kR0_m);
  const double f0 = anisotropy(data_, kR0_m, kTheta0_rad);
  if (std::abs(g0 - 1.0) > kNormalisationTol || std::abs(f0 - 1.0) > kNormalisationTol) {
    throw std::invalid_argument(
        label(name) + ": not normalised at r0 = 1 cm, theta0 = 90 deg: g_L(r0) = " + fmt(g0) +
        ", F(r0, theta0) = " + fmt(f0) + " (expected 1; units cm / deg?)");
  }
  g_ref_ = geometryLine(0.0, kR0_m, length_m);
  phi_an_.resize(data_.F_r_m.size());
  for (std::size_t j = 0; j < phi_an_.size(); ++j) {
    phi_an_[j] = phiAn(data_, g_ref_, std::max(data_.F_r_m[j], kMinCoreDistance_m));
  }
}

double Tg43Source::doseRatePerU(double r_m, double theta_rad, SourceModel model) const {
  if (!std::isfinite(r_m) || r_m < 0.0) {
    throw std::invalid_argument(label(data_.name) + ": doseRatePerU: r_m = " + fmt(r_m) +
                                " must be finite and non-negative");
  }
  if (!std::isfinite(theta_rad) || theta_rad < -kThetaRoundOff_rad ||
      theta_rad > kPi + kThetaRoundOff_rad) {
    throw std::invalid_argument(label(data_.name) + ": doseRatePerU: theta_rad = " +
                                fmt(theta_rad) + " is outside [0, pi]");
  }
  const double lambda_SI = data_.dose_rate_constant_cGy_per_h_per_U * kCGyPerH_GyPerS;
  if (model == SourceModel::kPoint) {
    // TG-43U1 eq. (11) with X = P: (r0/r)^2 g_P(r) phi_an(r), where
    // g_P(r) = g_L(r) G_L(r, theta0) G_P(r0) / (G_P(r) G_L(r0, theta0)) and G_P(r) = r^-2 (eq. 6),
    // so (r0/r)^2 g_P(r) = g_L(r) G_L(r, theta0) / G_L(r0, theta0). r is clamped like the 2-D
    // model.
    const double r = std::max(r_m, kMinCoreDistance_m);
    const auto [j, t] = bracket(data_.F_r_m, r);
    const double phi = phi_an_[j] + t * (phi_an_[j + 1] - phi_an_[j]);
    return lambda_SI * geometryLine(0.0, r, data_.active_length_m) / g_ref_ * radialDose(data_, r) *
           phi;
  }
  const double theta = std::clamp(theta_rad, 0.0, kPi);
  return lambda_SI * lineRatio(data_, g_ref_, r_m * std::cos(theta), r_m * std::sin(theta));
}

double Tg43Source::doseRatePerU(const Point3& p, const Point3& centre, const Point3& axis,
                                SourceModel model) const {
  if (!p.allFinite() || !centre.allFinite() || !axis.allFinite()) {
    throw std::invalid_argument(label(data_.name) +
                                ": doseRatePerU: point, centre or axis is not finite");
  }
  const double axis_norm = axis.norm();
  if (!(axis_norm > 1e-12)) {
    throw std::invalid_argument(label(data_.name) + ": doseRatePerU: source axis has zero length");
  }
  const Point3 d = p - centre;
  const Point3 n = axis / axis_norm;
  const double z = d.dot(n);
  const double y = (d - z * n).norm();
  if (model == SourceModel::kPoint) {
    return doseRatePerU(d.norm(), kTheta0_rad, model);
  }
  return data_.dose_rate_constant_cGy_per_h_per_U * kCGyPerH_GyPerS *
         lineRatio(data_, g_ref_, z, y);
}

// ---- loading -----------------------------------------------------------------------------------

Tg43Source loadSource(const std::string& name_or_dir) {
  if (name_or_dir.empty()) {
    throw std::invalid_argument("loadSource: empty source name");
  }
  // A name without '/' is looked up in the package's config/sources/ (pass "./dir" for a local
  // directory), so the result does not depend on the working directory.
  const bool is_path =
      name_or_dir.find('/') != std::string::npos || name_or_dir == "." || name_or_dir == "..";
  fs::path dir;
  std::string name;
  if (is_path) {
    dir = name_or_dir;
    if (!fs::is_directory(dir)) {
      throw std::invalid_argument("loadSource: '" + name_or_dir + "' is not a directory");
    }
    name = fs::weakly_canonical(dir).filename().string();
  } else {
    dir = sourcesDir() / name_or_dir;
    name = name_or_dir;
    if (!fs::is_directory(dir)) {
      std::string known;
      for (const std::string& s : availableSources()) {
        known += (known.empty() ? "" : ", ") + s;
      }
      throw std::invalid_argument("loadSource: unknown TG-43 source '" + name_or_dir +
                                  "': no directory '" + dir.string() +
                                  "' (available: " + (known.empty() ? "none" : known) + ")");
    }
  }
  Tg43Data data;
  data.name = name;
  readSourceYaml(dir / "source.yaml", data);
  readRadialDose(dir / "radial_dose_gL.csv", data);
  readAnisotropy(dir / "anisotropy_F.csv", data);
  return Tg43Source(std::move(data));
}

std::vector<std::string> availableSources() {
  std::vector<std::string> names;
  std::error_code ec;
  const fs::path root = sourcesDir();
  if (!fs::is_directory(root, ec)) {
    return names;
  }
  for (const fs::directory_entry& entry : fs::directory_iterator(root, ec)) {
    if (entry.is_directory(ec) && fs::is_regular_file(entry.path() / "source.yaml", ec)) {
      names.push_back(entry.path().filename().string());
    }
  }
  std::sort(names.begin(), names.end());
  return names;
}

}  // namespace needle_guidance::dose
