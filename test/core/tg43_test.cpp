// Tests for the TG-43 dose calculation (src/dose/tg43.cpp) against the shipped consensus data
// in config/sources/ (no other files needed).
#include "needle_guidance/dose/tg43.h"
#include "needle_guidance/math.h"

#include <gtest/gtest.h>
#include <stdlib.h>  // mkdtemp
#include <Eigen/Geometry>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

namespace fs = std::filesystem;
using needle_guidance::dose::availableSources;
using needle_guidance::dose::loadSource;
using needle_guidance::dose::Point3;
using needle_guidance::dose::SourceModel;
using needle_guidance::dose::Tg43Data;
using needle_guidance::dose::Tg43Source;

namespace {

using needle_guidance::kPi;
constexpr double kCm_m = 0.01;
constexpr double kDeg_rad = kPi / 180.0;
constexpr double kCGyPerH_GyPerS = 0.01 / 3600.0;  ///< 1 cGy h^-1 in Gy s^-1
constexpr double kRefRelTol = 1e-12;               ///< dose rate at (r0, theta0) vs Lambda
constexpr double kHandRelTol = 1e-9;               ///< hand-computed points (table values exact)
/// Along-away QA tables of the ESTRO sheets, points >= 0.5 cm from the centre. The data README
/// reports 0.05 % (GammaMed Plus), 0.11 % (Flexisource), < 0.001 % (VS2000) for this formalism.
constexpr double kAlongAwayRelTol = 0.005;
constexpr double kAlongAwayMinDistance_cm = 0.5;
constexpr double kPhiAnRelTol = 1e-4;  ///< phi_an (Simpson in the code) vs a fine trapezoid here

/// The shipped source data, config/sources/ of this source tree.
const fs::path& sourcesDir() {
  static const fs::path dir = fs::path(NG_SOURCE_DIR) / "config" / "sources";
  return dir;
}

/// Lambda [cGy h^-1 U^-1] -> Gy s^-1 U^-1.
double lambdaSi(const Tg43Source& s) {
  return s.data().dose_rate_constant_cGy_per_h_per_U * kCGyPerH_GyPerS;
}

/// Line-source geometry function G_L [cm^-2] written out as in TG-43U1 eq. (4), r in cm.
double geometryLineCm(double r_cm, double theta_rad, double length_cm) {
  if (theta_rad == 0.0 || theta_rad == kPi) {
    return 1.0 / (r_cm * r_cm - length_cm * length_cm / 4.0);
  }
  const double z = r_cm * std::cos(theta_rad);
  const double y = r_cm * std::sin(theta_rad);
  const double beta = std::atan((z + length_cm / 2.0) / y) - std::atan((z - length_cm / 2.0) / y);
  return beta / (length_cm * r_cm * std::sin(theta_rad));
}

/// A unique temporary directory, removed when the object goes out of scope.
class TempDir {
public:
  TempDir() {
    std::string pattern = (fs::temp_directory_path() / "tg43_test_XXXXXX").string();
    if (mkdtemp(pattern.data()) == nullptr) {
      throw std::runtime_error("mkdtemp failed");
    }
    path_ = pattern;
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  const fs::path& path() const { return path_; }

private:
  fs::path path_;
};

void writeFile(const fs::path& file, const std::string& text) {
  std::ofstream out(file);
  out << text;
}

/// Copies the shipped gammamed_plus_hdr data into dir.
void copyGammaMed(const fs::path& dir) {
  for (const char* f : {"source.yaml", "radial_dose_gL.csv", "anisotropy_F.csv"}) {
    fs::copy_file(sourcesDir() / "gammamed_plus_hdr" / f, dir / f);
  }
}

/// Message of the std::invalid_argument thrown by f (fails the test if none is thrown).
template <typename Fn>
std::string invalidArgumentMessage(Fn f) {
  try {
    f();
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  ADD_FAILURE() << "expected std::invalid_argument";
  return "";
}

}  // namespace

TEST(Tg43, ShipsTheFourConsensusSources) {
  const std::vector<std::string> names = availableSources();
  for (const char* expected :
       {"flexisource_hdr", "gammamed_plus_hdr", "microselectron_v2_hdr", "varisource_vs2000_hdr"}) {
    EXPECT_NE(std::find(names.begin(), names.end(), expected), names.end()) << expected;
  }
  for (const std::string& name : names) {
    const Tg43Source s = loadSource(name);
    EXPECT_EQ(s.name(), name);
    EXPECT_GT(s.data().active_length_m, 0.0);
  }
  const Tg43Source vs2000 = loadSource("varisource_vs2000_hdr");
  EXPECT_DOUBLE_EQ(vs2000.data().active_length_m, 0.5 * kCm_m);
  EXPECT_DOUBLE_EQ(vs2000.data().dose_rate_constant_cGy_per_h_per_U, 1.1);
}

TEST(Tg43, ReferencePointGivesLambda) {
  for (const std::string& name : availableSources()) {
    const Tg43Source s = loadSource(name);
    const double expected = lambdaSi(s);
    EXPECT_NEAR(s.doseRatePerU(1.0 * kCm_m, kPi / 2.0), expected, kRefRelTol * expected) << name;
    // Same through the 3-D overload: point 1 cm beside an arbitrary source position and axis.
    const Point3 centre(0.1, -0.2, 0.05);
    const Point3 axis = Point3(1.0, 2.0, -0.5).normalized();
    const Point3 side = axis.cross(Point3::UnitZ()).normalized();
    EXPECT_NEAR(s.doseRatePerU(centre + 1.0 * kCm_m * side, centre, axis), expected,
                kRefRelTol * expected)
        << name;
  }
}

TEST(Tg43, HandComputedPointsGammaMedPlus) {
  const Tg43Source s = loadSource("gammamed_plus_hdr");
  // Lambda = 1.1165 cGy/(h U) = 1.1165e-2 / 3600 Gy/(s U) = 3.101388889e-6; L = 0.35 cm.
  const double lambda = 1.1165e-2 / 3600.0;
  const double length_cm = 0.35;
  // G_L(1 cm, 90 deg) = 2 atan(L / 2) / L = 2 atan(0.175) / 0.35 = 0.989916 cm^-2.
  const double g_ref = 2.0 * std::atan(0.175) / 0.35;
  EXPECT_NEAR(geometryLineCm(1.0, kPi / 2.0, length_cm), g_ref, 1e-14);

  // (a) r = 2 cm, theta = 90 deg (table nodes): G_L = 2 atan(0.0875) / 0.7; gL(2) = 1.005820306;
  //     F(2, 90) = 1  ->  7.857558217e-7 Gy/(s U).
  const double a = lambda * (2.0 * std::atan(0.0875) / 0.7) / g_ref * 1.005820306 * 1.0;
  EXPECT_NEAR(a, 7.857558217e-7, 1e-15);
  EXPECT_NEAR(s.doseRatePerU(2.0 * kCm_m, 90.0 * kDeg_rad), a, kHandRelTol * a);

  // (b) r = 2.25 cm, theta = 12.5 deg: between theta rows 10/15 and r columns 2/2.5, weights 1/2:
  //     F = (F(10,2) + F(10,2.5) + F(15,2) + F(15,2.5)) / 4 = (0.7518 + 0.7548 + 0.8107 + 0.8131)/4
  //       = 0.7826;
  //     gL(2.25) = gL(2) + 0.25 (gL(3) - gL(2)) = 1.005820306 + 0.25 * 0.000188712 = 1.005867484;
  //     G_L(2.25, 12.5 deg) = beta / (L r sin theta), z = r cos theta, y = r sin theta,
  //       beta = atan((z + L/2)/y) - atan((z - L/2)/y)  = 0.198657 cm^-2  ->  4.899103825e-7.
  const double theta_b = 12.5 * kDeg_rad;
  const double b = lambda * geometryLineCm(2.25, theta_b, length_cm) / g_ref * 1.005867484 * 0.7826;
  EXPECT_NEAR(b, 4.899103825e-7, 1e-15);
  EXPECT_NEAR(s.doseRatePerU(2.25 * kCm_m, theta_b), b, kHandRelTol * b);

  // (c) r = 12 cm > last gL radius 10 cm, theta = 90 deg: linear extrapolation from r = 8, 10:
  //     gL(12) = gL(10) + (gL(10) - gL(8)) / 2 * 2 = 0.9351323971 - 0.0329552452 = 0.9021771519;
  //     F(12, 90) = F(10, 90) = 1 (nearest column); G_L = 2 atan(0.35 / 24) / (0.35 * 12)
  //     ->  1.962593890e-8.
  const double c = lambda * (2.0 * std::atan(0.35 / 24.0) / (0.35 * 12.0)) / g_ref * 0.9021771519;
  EXPECT_NEAR(c, 1.962593890e-8, 1e-17);
  EXPECT_NEAR(s.doseRatePerU(12.0 * kCm_m, 90.0 * kDeg_rad), c, kHandRelTol * c);

  // (d) on the axis beyond the tip, r = 3 cm, theta = 0: G_L = 1 / (r^2 - L^2/4) = 1 / 8.969375;
  //     gL(3) = 1.006009018; F(3, 0) = 0.6537  ->  2.296942229e-7.
  const double d =
      lambda * (1.0 / (9.0 - length_cm * length_cm / 4.0)) / g_ref * 1.006009018 * 0.6537;
  EXPECT_NEAR(d, 2.296942229e-7, 1e-15);
  EXPECT_NEAR(s.doseRatePerU(3.0 * kCm_m, 0.0), d, kHandRelTol * d);
  // The same point through the 3-D overload (axis +x, point at +3 cm on it).
  EXPECT_NEAR(s.doseRatePerU(Point3(0.03, 0.0, 0.0), Point3::Zero(), Point3::UnitX()), d,
              kHandRelTol * d);
}

TEST(Tg43, ReproducesAlongAwayQaTables) {
  int tables = 0;
  for (const std::string& name : availableSources()) {
    const fs::path file = sourcesDir() / name / "along_away_dose_rate.csv";
    if (!fs::exists(file)) {
      continue;
    }
    ++tables;
    const Tg43Source s = loadSource(name);
    std::ifstream in(file);
    ASSERT_TRUE(in) << file;
    std::string line;
    ASSERT_TRUE(std::getline(in, line));
    std::vector<double> y_cm;
    {
      std::istringstream header(line);
      std::string cell;
      std::getline(header, cell, ',');
      std::transform(cell.begin(), cell.end(), cell.begin(),
                     [](unsigned char ch) { return std::tolower(ch); });
      ASSERT_EQ(cell, "z_cm") << file;
      while (std::getline(header, cell, ',')) {
        y_cm.push_back(std::stod(cell));
      }
    }
    double max_rel = 0.0;
    int compared = 0;
    while (std::getline(in, line)) {
      if (line.empty()) {
        continue;
      }
      std::istringstream row(line);
      std::string cell;
      std::getline(row, cell, ',');
      const double z_cm = std::stod(cell);
      for (double y : y_cm) {
        ASSERT_TRUE(std::getline(row, cell, ',')) << file << ": short row z = " << z_cm;
        const double sheet_rate = std::strtod(cell.c_str(), nullptr);  // "nan" at the centre
        const double r_cm = std::hypot(z_cm, y);
        if (!std::isfinite(sheet_rate) || r_cm < kAlongAwayMinDistance_cm) {
          continue;
        }
        const double ours = s.doseRatePerU(r_cm * kCm_m, std::atan2(y, z_cm)) / kCGyPerH_GyPerS;
        const double rel = std::abs(ours / sheet_rate - 1.0);
        EXPECT_LT(rel, kAlongAwayRelTol) << name << " z = " << z_cm << " cm, y = " << y << " cm";
        // 3-D overload, source axis along +z of the frame, point in the x-z plane.
        const double ours_3d =
            s.doseRatePerU(Point3(y * kCm_m, 0.0, z_cm * kCm_m), Point3::Zero(), Point3::UnitZ()) /
            kCGyPerH_GyPerS;
        EXPECT_NEAR(ours_3d, ours, 1e-12 * ours);
        max_rel = std::max(max_rel, rel);
        ++compared;
      }
    }
    EXPECT_GT(compared, 200) << file;
    std::cout << "[          ] " << name << ": " << compared
              << " along-away points >= 0.5 cm, max relative difference " << 100.0 * max_rel
              << " %\n";
  }
  EXPECT_GE(tables, 3);
}

TEST(Tg43, HardCasesAreFiniteAndNonNegative) {
  for (const std::string& name : availableSources()) {
    const Tg43Source s = loadSource(name);
    const double length_m = s.data().active_length_m;
    const auto ok = [&](double v, const std::string& what) {
      EXPECT_TRUE(std::isfinite(v)) << name << ": " << what;
      EXPECT_GE(v, 0.0) << name << ": " << what;
    };
    for (SourceModel model : {SourceModel::kLine, SourceModel::kPoint}) {
      const std::string m = model == SourceModel::kLine ? "line " : "point ";
      for (double theta : {0.0, kPi / 4.0, kPi / 2.0, kPi}) {
        ok(s.doseRatePerU(0.0, theta, model), m + "r = 0");
        ok(s.doseRatePerU(0.25 * length_m, theta, model), m + "r = L/4");
        ok(s.doseRatePerU(0.5 * length_m, theta, model), m + "r = L/2");
        ok(s.doseRatePerU(0.5 * length_m * (1.0 + 1e-15), theta, model), m + "r = L/2 + eps");
        ok(s.doseRatePerU(1e-300, theta, model), m + "r = 1e-300");
        ok(s.doseRatePerU(1e3, theta, model), m + "r = 1 km");
      }
      // theta a round-off outside [0, pi] equals the end value.
      EXPECT_EQ(s.doseRatePerU(0.1 * length_m, -1e-12, model),
                s.doseRatePerU(0.1 * length_m, 0.0, model));
      EXPECT_EQ(s.doseRatePerU(0.02, kPi + 1e-12, model), s.doseRatePerU(0.02, kPi, model));
      // Source centre and a point on the axis inside the source via the 3-D overload.
      const Point3 c(0.01, 0.02, 0.03);
      const Point3 axis = Point3(0.0, 1.0, 1.0).normalized();
      ok(s.doseRatePerU(c, c, axis, model), m + "p = centre");
      ok(s.doseRatePerU(c + 0.3 * length_m * axis, c, axis, model), m + "p on axis inside source");
      ok(s.doseRatePerU(c - 0.5 * length_m * axis, c, axis, model), m + "p at cable-side end");
    }
    // A dense scan including the inside of the source: 0.125 mm steps to 1 cm, then 2.5 mm to 15
    // cm.
    for (int i = 0; i <= 136; ++i) {
      const double r_cm = i <= 80 ? 0.0125 * i : 1.0 + 0.25 * (i - 80);
      for (int k = 0; k <= 180; ++k) {
        ok(s.doseRatePerU(r_cm * kCm_m, k * kDeg_rad), "scan");
      }
    }
  }
}

TEST(Tg43, BadCoordinatesThrow) {
  const Tg43Source s = loadSource("gammamed_plus_hdr");
  const double nan = std::numeric_limits<double>::quiet_NaN();
  EXPECT_THROW(s.doseRatePerU(-0.01, 1.0), std::invalid_argument);
  EXPECT_THROW(s.doseRatePerU(nan, 1.0), std::invalid_argument);
  EXPECT_THROW(s.doseRatePerU(0.01, nan), std::invalid_argument);
  EXPECT_THROW(s.doseRatePerU(0.01, 4.0), std::invalid_argument);
  EXPECT_THROW(s.doseRatePerU(0.01, -0.1), std::invalid_argument);
  EXPECT_THROW(s.doseRatePerU(Point3(0.01, 0, 0), Point3::Zero(), Point3::Zero()),
               std::invalid_argument);
  EXPECT_THROW(s.doseRatePerU(Point3(nan, 0, 0), Point3::Zero(), Point3::UnitZ()),
               std::invalid_argument);
}

TEST(Tg43, PointModelUsesTg43PhiAn) {
  // 1-D formalism: Ddot(r) = S_K Lambda (r0/r)^2 g_P(r) phi_an(r), phi_an(r) = integral of
  // Ddot(r, theta) sin(theta) / 2 over theta divided by Ddot(r, theta0) (TG-43U1 eq. 10), so
  // Ddot_point(r) must equal the solid-angle average of the 2-D dose rate at r.
  const Tg43Source s = loadSource("gammamed_plus_hdr");
  for (double r_cm : {1.0, 2.0, 5.0}) {  // tabulated F radii, where phi_an is computed exactly
    const double r = r_cm * kCm_m;
    const int n = 20000;
    double sum = 0.0;
    for (int k = 0; k <= n; ++k) {
      const double theta = kPi * k / n;
      const double w = (k == 0 || k == n) ? 0.5 : 1.0;
      sum += w * s.doseRatePerU(r, theta) * std::sin(theta);
    }
    const double average = 0.5 * sum * kPi / n;
    const double point = s.doseRatePerU(r, kPi / 2.0, SourceModel::kPoint);
    EXPECT_NEAR(point, average, kPhiAnRelTol * average) << "r = " << r_cm << " cm";
    EXPECT_LT(point, s.doseRatePerU(r, kPi / 2.0));  // phi_an < 1 for these sources
  }
  // The point model ignores theta and is finite at r = 0.
  EXPECT_EQ(s.doseRatePerU(0.03, 0.1, SourceModel::kPoint),
            s.doseRatePerU(0.03, 2.0, SourceModel::kPoint));
  EXPECT_TRUE(std::isfinite(s.doseRatePerU(0.0, 0.0, SourceModel::kPoint)));
}

TEST(Tg43, ConstructorValidates) {
  const Tg43Data good = loadSource("gammamed_plus_hdr").data();
  const auto expect_throw_naming = [](Tg43Data d, const std::string& fragment) {
    const std::string msg = invalidArgumentMessage([&] { Tg43Source s(std::move(d)); });
    EXPECT_NE(msg.find("gammamed_plus_hdr"), std::string::npos) << msg;
    EXPECT_NE(msg.find(fragment), std::string::npos) << msg;
  };
  Tg43Data d = good;
  d.dose_rate_constant_cGy_per_h_per_U = 0.0;
  expect_throw_naming(d, "Lambda");
  d = good;
  d.active_length_m = -1.0;
  expect_throw_naming(d, "active length");
  d = good;
  std::swap(d.gL_r_m[3], d.gL_r_m[4]);
  expect_throw_naming(d, "strictly increasing");
  d = good;
  d.gL.pop_back();
  expect_throw_naming(d, "g_L values");
  d = good;
  d.F(2, 3) = std::numeric_limits<double>::quiet_NaN();
  expect_throw_naming(d, "not finite");
  d = good;
  d.F.conservativeResize(d.F.rows() - 1, Eigen::NoChange);
  expect_throw_naming(d, "expected");
  d = good;
  for (double& g : d.gL) {
    g *= 1.1;  // not normalised to g_L(r0) = 1 (e.g. a wrong column)
  }
  expect_throw_naming(d, "not normalised");
}

TEST(Tg43, MalformedFilesThrowNamingTheFile) {
  {
    TempDir tmp;
    copyGammaMed(tmp.path());
    // r column not increasing at data line 5 (file line 5, after the header).
    writeFile(tmp.path() / "radial_dose_gL.csv",
              "r_cm,gL\n0,0.998\n0.25,0.997\n1,1\n0.5,0.996\n2,1.005\n");
    const std::string msg = invalidArgumentMessage([&] { loadSource(tmp.path().string()); });
    EXPECT_NE(msg.find((tmp.path() / "radial_dose_gL.csv").string() + ":5:"), std::string::npos)
        << msg;
    EXPECT_NE(msg.find("increasing"), std::string::npos) << msg;
  }
  {
    TempDir tmp;
    copyGammaMed(tmp.path());
    fs::remove(tmp.path() / "anisotropy_F.csv");
    const std::string msg = invalidArgumentMessage([&] { loadSource(tmp.path().string()); });
    EXPECT_NE(msg.find((tmp.path() / "anisotropy_F.csv").string()), std::string::npos) << msg;
  }
  {
    TempDir tmp;
    copyGammaMed(tmp.path());
    fs::remove(tmp.path() / "source.yaml");
    const std::string msg = invalidArgumentMessage([&] { loadSource(tmp.path().string()); });
    EXPECT_NE(msg.find("source.yaml"), std::string::npos) << msg;
  }
  {
    TempDir tmp;
    copyGammaMed(tmp.path());
    writeFile(tmp.path() / "source.yaml", "name: x\nactive_length_L_cm: 0.35\n");
    const std::string msg = invalidArgumentMessage([&] { loadSource(tmp.path().string()); });
    EXPECT_NE(msg.find("source.yaml"), std::string::npos) << msg;
    EXPECT_NE(msg.find("dose_rate_constant_Lambda_cGy_per_h_per_U"), std::string::npos) << msg;
  }
  {
    TempDir tmp;
    copyGammaMed(tmp.path());
    writeFile(tmp.path() / "source.yaml",
              "dose_rate_constant_Lambda_cGy_per_h_per_U: 1.1\nactive_length_L_cm: abc\n");
    const std::string msg = invalidArgumentMessage([&] { loadSource(tmp.path().string()); });
    EXPECT_NE(msg.find("source.yaml:2:"), std::string::npos) << msg;
  }
  {
    TempDir tmp;
    copyGammaMed(tmp.path());
    // Row with a missing F value and a non-numeric one.
    writeFile(tmp.path() / "anisotropy_F.csv", "theta_deg,0.5,1\n0,0.7,0.6\n90,1\n180,0.5,0.5\n");
    std::string msg = invalidArgumentMessage([&] { loadSource(tmp.path().string()); });
    EXPECT_NE(msg.find("anisotropy_F.csv:3:"), std::string::npos) << msg;
    writeFile(tmp.path() / "anisotropy_F.csv", "theta_deg,0.5,1\n0,0.7,0.6\n90,1,x\n180,0.5,0.5\n");
    msg = invalidArgumentMessage([&] { loadSource(tmp.path().string()); });
    EXPECT_NE(msg.find("anisotropy_F.csv:3:"), std::string::npos) << msg;
  }
  {
    // A well-formed copy in a temp directory loads and gives the same numbers.
    TempDir tmp;
    copyGammaMed(tmp.path());
    const Tg43Source copy = loadSource(tmp.path().string());
    const Tg43Source shipped = loadSource("gammamed_plus_hdr");
    EXPECT_EQ(copy.doseRatePerU(0.013, 0.7), shipped.doseRatePerU(0.013, 0.7));
  }
}

TEST(Tg43, UnknownSourceNamesTheDirectorySearched) {
  const std::string msg = invalidArgumentMessage([] { loadSource("no_such_source"); });
  EXPECT_NE(msg.find("no_such_source"), std::string::npos) << msg;
  EXPECT_NE(msg.find(sourcesDir().string()), std::string::npos) << msg;
  EXPECT_THROW(loadSource(""), std::invalid_argument);
  EXPECT_THROW(loadSource("/no/such/dir/"), std::invalid_argument);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
