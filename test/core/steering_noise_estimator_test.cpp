// Tests for the online deflection-noise estimator: the deflection recovered from two
// poses of advanceTip, the chi-square quantile against tabulated values, and the coverage of the
// 95 % interval over seeded synthetic deflections with a known sigma.
#include <gtest/gtest.h>

#include <cmath>
#include <optional>
#include <random>
#include <stdexcept>

#include "needle_guidance/math.h"
#include "needle_guidance/steering/noise_estimator.h"

namespace needle_guidance::steering {
namespace {

constexpr double kDeg = kPi / 180.0;
constexpr double kAngleTol_rad = 1e-12;
constexpr double kQuantileRelTol = 0.01;  // Wilson-Hilferty, dof >= 3
constexpr int kCoverageSeeds = 2000;
/// Binomial slack on 95 % coverage over 2000 seeds: 3 standard errors (~0.015).
constexpr double kCoverageTol = 0.015;

TEST(NoiseEstimatorTest, DeflectionIsRecoveredFromTwoPoses) {
  const double delta = 2 * kPi * 0.05 / 40, r = 0.05;
  for (Bevel b : {Bevel::kLeft, Bevel::kRight}) {
    for (Control u : {Control::kInsert, Control::kFlip}) {
      for (double beta_deg : {-30.0, -3.0, 0.0, 7.5, 170.0}) {
        const TipPose start{Point2(0.01, 0.02), 175 * kDeg, b};
        const TipPose end = advanceTip(start, u, beta_deg * kDeg, delta, r);
        EXPECT_NEAR(NoiseEstimator::deflection(start, end, u, delta, r), beta_deg * kDeg,
                    kAngleTol_rad);
      }
    }
  }
  EXPECT_THROW(NoiseEstimator::deflection({}, {Point2::Zero(), NAN, Bevel::kLeft}, Control::kInsert,
                                          delta, r),
               std::invalid_argument);
}

TEST(NoiseEstimatorTest, DeflectionOfAStoppedStepIsRecoveredFromItsChord) {
  const double delta = 2 * kPi * 0.05 / 40, r = 0.05;
  for (Bevel b : {Bevel::kLeft, Bevel::kRight}) {
    for (Control u : {Control::kInsert, Control::kFlip}) {
      for (double fraction : {0.15, 0.5, 1.0}) {
        for (double beta_deg : {-30.0, -3.0, 0.0, 7.5, 120.0}) {
          const TipPose start{Point2(0.01, 0.02), -170 * kDeg, b};
          const TipPose end = advanceTip(start, u, beta_deg * kDeg, fraction * delta, r);
          const std::optional<double> beta =
              NoiseEstimator::deflectionOfStoppedStep(start, end, 0.1 * delta);
          ASSERT_TRUE(beta.has_value()) << fraction;
          EXPECT_NEAR(*beta, beta_deg * kDeg, 1e-9) << fraction << " of delta, " << beta_deg;
        }
      }
    }
  }
  // A chord shorter than asked for teaches nothing; a non-finite pose is refused.
  const TipPose start{Point2(0.01, 0.02), 0.0, Bevel::kLeft};
  const TipPose near = advanceTip(start, Control::kInsert, 0.1, 0.05 * delta, r);
  EXPECT_FALSE(NoiseEstimator::deflectionOfStoppedStep(start, near, 0.1 * delta).has_value());
  EXPECT_THROW(
      NoiseEstimator::deflectionOfStoppedStep(start, {Point2(NAN, 0), 0, Bevel::kLeft}, 0.0),
      std::invalid_argument);
}

TEST(NoiseEstimatorTest, ChiSquareQuantileMatchesTables) {
  // Tabulated chi-square quantiles (dof, p, value).
  const double table[][3] = {{10, 0.025, 3.247},
                             {10, 0.975, 20.483},
                             {30, 0.025, 16.791},
                             {30, 0.975, 46.979},
                             {100, 0.5, 99.334}};
  for (const auto& row : table) {
    EXPECT_NEAR(chiSquareQuantile(row[1], row[0]), row[2], kQuantileRelTol * row[2]);
  }
  EXPECT_THROW(chiSquareQuantile(1.0, 3), std::invalid_argument);
}

TEST(NoiseEstimatorTest, IntervalCoversTheTrueSigmaAtItsLevel) {
  for (int n : {10, 40, 200}) {
    int covered = 0;
    for (int seed = 0; seed < kCoverageSeeds; ++seed) {
      std::mt19937_64 rng(static_cast<std::uint64_t>(seed) * 7919u + static_cast<unsigned>(n));
      std::normal_distribution<double> normal(0.0, 10 * kDeg);
      NoiseEstimator est(0.95);
      for (int i = 0; i < n; ++i) {
        est.add(Control::kFlip, normal(rng));
      }
      covered += est.estimate(Control::kFlip).contains(10 * kDeg) ? 1 : 0;
    }
    EXPECT_NEAR(double(covered) / kCoverageSeeds, 0.95, kCoverageTol) << n << " samples";
  }
}

TEST(NoiseEstimatorTest, ControlsAreSeparateAndBadInputLeavesTheEstimate) {
  NoiseEstimator est;
  est.add(Control::kInsert, 0.1);
  EXPECT_THROW(est.add(Control::kInsert, NAN), std::invalid_argument);
  EXPECT_EQ(est.estimate(Control::kInsert).samples, 1);
  EXPECT_NEAR(est.estimate(Control::kInsert).sigma_rad, 0.1, kAngleTol_rad);
  EXPECT_EQ(est.estimate(Control::kFlip).samples, 0);
  EXPECT_TRUE(std::isinf(est.estimate(Control::kFlip).high_rad));
  EXPECT_THROW(NoiseEstimator(1.0), std::invalid_argument);
  EXPECT_THROW(est.estimate(Control::kInsert, 0.0), std::invalid_argument);
}

TEST(NoiseEstimatorTest, AHigherConfidenceGivesAWiderInterval) {
  NoiseEstimator est(0.95);
  std::mt19937_64 rng(3);
  std::normal_distribution<double> normal(0.0, 5 * kDeg);
  for (int i = 0; i < 50; ++i) {
    est.add(Control::kInsert, normal(rng));
  }
  const SigmaEstimate a = est.estimate(Control::kInsert);
  const SigmaEstimate b = est.estimate(Control::kInsert, 0.9999);
  EXPECT_DOUBLE_EQ(a.sigma_rad, b.sigma_rad);
  EXPECT_LT(b.low_rad, a.low_rad);
  EXPECT_GT(b.high_rad, a.high_rad);
}

}  // namespace
}  // namespace needle_guidance::steering

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
