// Tests for the isodose lines and the dose slice (src/dose/isodose.cpp) and the structure doses
// with extra source stops (src/dose/dose_indices.cpp).
#include "needle_guidance/dose/isodose.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <vector>

#include "needle_guidance/dose/dose_indices.h"
#include "needle_guidance/dose/prostate_case.h"

namespace dose = needle_guidance::dose;

namespace {

constexpr double kSpacing_m = 1e-3;
/// Radially symmetric fields: vertices on the true circle within this (interpolation on a 1 mm
/// grid).
constexpr double kRadiusTol_m = 0.25 * kSpacing_m;
constexpr double kDoseRelTol = 1e-12;  ///< the same sums in another order

/// f(r) on a grid of n x n nodes centred at (cx, cy), spacing kSpacing_m, origin (x0, y0).
template <typename F>
Eigen::MatrixXd radialField(int n, double x0, double y0, double cx, double cy, F f) {
  Eigen::MatrixXd grid(n, n);
  for (int i = 0; i < n; ++i) {
    for (int j = 0; j < n; ++j) {
      grid(i, j) = f(std::hypot(x0 + j * kSpacing_m - cx, y0 + i * kSpacing_m - cy));
    }
  }
  return grid;
}

TEST(Isodose, LinearConeGivesCircleOfKnownRadius) {
  const double x0 = -0.03, y0 = 0.01, cx = -0.0053, cy = 0.0342;  // centre off the grid nodes
  const double radius_m = 0.0117;
  const Eigen::MatrixXd grid =
      radialField(51, x0, y0, cx, cy, [](double r) { return 20.0 - 1000.0 * r; });
  const double level = 20.0 - 1000.0 * radius_m;
  const auto lines = dose::isodoseLines(grid, x0, y0, kSpacing_m, level);
  ASSERT_EQ(lines.size(), 1u);
  ASSERT_GT(lines[0].size(), 40u);
  for (const auto& p : lines[0]) {
    EXPECT_NEAR(std::hypot(p.x() - cx, p.y() - cy), radius_m, kRadiusTol_m) << p.transpose();
  }
}

TEST(Isodose, InverseSquareFieldWithinOneSpacing) {
  // A point source's 1/r^2 fall-off: strongly curved, the interpolation is biased but bounded.
  const double x0 = -0.025, y0 = -0.025;
  const Eigen::MatrixXd grid =
      radialField(51, x0, y0, 0.0004, -0.0007, [](double r) { return 1e-4 / (r * r + 1e-6); });
  for (const double radius_m : {0.004, 0.008, 0.015}) {
    const auto lines =
        dose::isodoseLines(grid, x0, y0, kSpacing_m, 1e-4 / (radius_m * radius_m + 1e-6));
    ASSERT_EQ(lines.size(), 1u) << radius_m;
    for (const auto& p : lines[0]) {
      EXPECT_NEAR(std::hypot(p.x() - 0.0004, p.y() + 0.0007), radius_m, kSpacing_m) << radius_m;
    }
  }
}

TEST(Isodose, RingGivesOuterLineAndHole) {
  // dose >= level for 5 mm <= r <= 12 mm: two closed lines, one per radius.
  const double x0 = -0.02, y0 = -0.02;
  const Eigen::MatrixXd grid = radialField(
      41, x0, y0, 0.0, 0.0, [](double r) { return 1.0 - std::abs(r - 0.0085) * 100.0; });
  const double level = 1.0 - 0.0035 * 100.0;
  const auto lines = dose::isodoseLines(grid, x0, y0, kSpacing_m, level);
  ASSERT_EQ(lines.size(), 2u);
  std::vector<double> mean_radius;
  for (const auto& line : lines) {
    double sum = 0.0;
    for (const auto& p : line)
      sum += p.norm();
    mean_radius.push_back(sum / static_cast<double>(line.size()));
  }
  std::sort(mean_radius.begin(), mean_radius.end());
  EXPECT_NEAR(mean_radius[0], 0.005, kRadiusTol_m);
  EXPECT_NEAR(mean_radius[1], 0.012, kRadiusTol_m);
}

TEST(Isodose, LevelAboveAndBelowEverything) {
  const Eigen::MatrixXd grid =
      radialField(11, 0.0, 0.0, 0.005, 0.005, [](double r) { return 1.0 - r; });
  EXPECT_TRUE(dose::isodoseLines(grid, 0.0, 0.0, kSpacing_m, 2.0).empty());
  // Everything above: one line around the whole grid along its border nodes.
  const auto all = dose::isodoseLines(grid, 0.0, 0.0, kSpacing_m, -1.0);
  ASSERT_EQ(all.size(), 1u);
  for (const auto& p : all[0]) {
    const bool on_border = std::abs(p.x()) < 1e-12 || std::abs(p.y()) < 1e-12 ||
                           std::abs(p.x() - 0.01) < 1e-12 || std::abs(p.y() - 0.01) < 1e-12;
    EXPECT_TRUE(on_border) << p.transpose();
  }
}

TEST(Isodose, RefusesBadInput) {
  Eigen::MatrixXd grid = Eigen::MatrixXd::Ones(5, 5);
  EXPECT_THROW(dose::isodoseLines(Eigen::MatrixXd(), 0.0, 0.0, kSpacing_m, 0.5),
               std::invalid_argument);
  EXPECT_THROW(dose::isodoseLines(grid, 0.0, 0.0, 0.0, 0.5), std::invalid_argument);
  EXPECT_THROW(dose::isodoseLines(grid, 0.0, 0.0, kSpacing_m, std::nan("")), std::invalid_argument);
  grid(2, 2) = std::numeric_limits<double>::quiet_NaN();
  EXPECT_THROW(dose::isodoseLines(grid, 0.0, 0.0, kSpacing_m, 0.5), std::invalid_argument);
}

class SyntheticCase : public ::testing::Test {
protected:
  static void SetUpTestSuite() {
    dose::SyntheticCaseOptions options;
    options.seed = 1;
    case_ = new dose::HdrCase(dose::syntheticProstateCase(options));
    source_ = new dose::Tg43Source(dose::loadSource(case_->source));
  }
  static void TearDownTestSuite() {
    delete case_;
    delete source_;
  }
  static const dose::HdrCase* case_;
  static const dose::Tg43Source* source_;
};
const dose::HdrCase* SyntheticCase::case_ = nullptr;
const dose::Tg43Source* SyntheticCase::source_ = nullptr;

TEST_F(SyntheticCase, MidSliceIsAContourNearTheMiddle) {
  const dose::Structure& prostate = case_->structures.front();
  const double z = dose::midSliceZ(prostate);
  const double middle = 0.5 * (prostate.contours.front().z_m + prostate.contours.back().z_m);
  EXPECT_LE(std::abs(z - middle), 0.5 * prostate.sliceSpacing() + 1e-12);
  bool found = false;
  for (const auto& contour : prostate.contours)
    found = found || contour.z_m == z;
  EXPECT_TRUE(found);
  EXPECT_THROW(dose::midSliceZ(dose::Structure{}), std::invalid_argument);
}

TEST_F(SyntheticCase, DoseSliceMatchesDoseAt) {
  std::vector<double> times(case_->dwells.size(), 0.0);
  for (std::size_t j = 0; j < times.size(); j += 3)
    times[j] = 2.0 + 0.01 * static_cast<double>(j);
  const dose::DoseSlice slice =
      dose::doseSlice(*case_, *source_, times, 0.001, -0.02, -0.015, 0.02, 0.0155, 2e-3);
  EXPECT_EQ(slice.dose_Gy.cols(), 21);
  EXPECT_EQ(slice.dose_Gy.rows(), 17);  // 30.5 mm / 2 mm = 15.25 steps, rounded up to 16
  const dose::Point3 p(-0.02 + 7 * 2e-3, -0.015 + 5 * 2e-3, 0.001);
  EXPECT_NEAR(slice.dose_Gy(5, 7), dose::doseAt(*case_, *source_, times, p),
              1e-12 * slice.dose_Gy(5, 7));
  EXPECT_THROW(dose::doseSlice(*case_, *source_, {}, 0.0, 0, 0, 0.01, 0.01), std::invalid_argument);
  EXPECT_THROW(dose::doseSlice(*case_, *source_, times, 0.0, 0.01, 0, 0.0, 0.01),
               std::invalid_argument);
}

TEST_F(SyntheticCase, ExtraStopsAddUpPointByPoint) {
  // The dose of dwell times split between the dwell list and extra stops at the same positions
  // equals that of the dwell list alone; the grids line up, so extras alone add point by point.
  std::vector<double> times(case_->dwells.size(), 0.0), first(times.size(), 0.0);
  std::vector<dose::ExtraDwell> extra;
  for (std::size_t j = 0; j < times.size(); j += 4) {
    times[j] = 3.0;
    first[j] = 1.0;
    extra.push_back({case_->dwells[j], 2.0});
  }
  const std::vector<double> none(times.size(), 0.0);
  const auto whole = dose::structureDoses(*case_, *source_, times, 4e-3);
  const auto split = dose::structureDoses(*case_, *source_, first, extra, 4e-3);
  const auto extra_only = dose::structureDoses(*case_, *source_, none, extra, 4e-3);
  const auto first_only = dose::structureDoses(*case_, *source_, first, 4e-3);
  ASSERT_EQ(whole.size(), split.size());
  for (std::size_t s = 0; s < whole.size(); ++s) {
    ASSERT_EQ(whole[s].dose_Gy.size(), split[s].dose_Gy.size());
    ASSERT_EQ(whole[s].dose_Gy.size(), extra_only[s].dose_Gy.size());
    for (std::size_t k = 0; k < whole[s].dose_Gy.size(); ++k) {
      EXPECT_NEAR(split[s].dose_Gy[k], whole[s].dose_Gy[k], kDoseRelTol * whole[s].dose_Gy[k]);
      EXPECT_NEAR(first_only[s].dose_Gy[k] + extra_only[s].dose_Gy[k], whole[s].dose_Gy[k],
                  kDoseRelTol * whole[s].dose_Gy[k]);
    }
  }
  extra.front().time_s = -1.0;
  EXPECT_THROW(dose::structureDoses(*case_, *source_, first, extra, 4e-3), std::invalid_argument);
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
