// Tests for the 3-D bevel-tip needle (needle_3d.h): exact arcs against closed forms and the
// planar model of dissertation 5.3, duty-cycled spinning's mean curvature and residual, the
// spin-rate limit (saturation), and the seeded 3-D noise model's statistics.
#include <gtest/gtest.h>

#include <cmath>
#include <vector>

#include "needle_guidance/math.h"
#include "needle_guidance/needle_model/needle_2d.h"
#include "needle_guidance/needle_model/needle_3d.h"

namespace needle_guidance::needle_model {
namespace {

constexpr double kDeg = kPi / 180.0;
constexpr double kExactPositionTol_m = 1e-12;  // closed forms in double over <= 0.3 m paths
constexpr double kExactAngleTol_rad = 1e-12;
/// Duty cycling bends once per cycle instead of continuously: the path is within
/// kappa_eff L^2 of the ideal arc laterally and lags it by at most one cycle L along it, so the
/// end points differ by at most about kappa_eff L * s over a path of length s (2 mm cycles).
constexpr double kDutyCycleCurvatureRelTol = 0.01;  // mean curvature over 40 mm [relative]
/// The duty cycle's residuals (heading drift, over-roll) against their first-order formulas in
/// kappa / rho (~ 6e-3 here), and the bevel's turn (its arc and the drift tilt it) [rad].
constexpr double kResidualRelTol = 0.1;
constexpr double kTurnTol_rad = 1e-3;
constexpr double kSpinRateTol = 1e-12;  // relative to spin_rate_max
/// Helix of a full spin: radius kappa / (kappa^2 + rho^2) = 2 um at rho = 2 pi / 2 mm [m].
constexpr double kHelixTol_m = 1e-5;
/// Sample standard deviation of N = 20000 normals: its standard error is sigma / sqrt(2N) =
/// 0.5 %; 3 % is six standard errors.
constexpr int kNoiseSamples = 20000;
constexpr double kSigmaRelTol = 0.03;
constexpr double kMeanTol_sigma = 0.05;  // sample mean within 7 standard errors (1/sqrt(N))

NeedleParams3 defaultParams() {
  NeedleParams3 p;
  p.kappa_max_per_m = 20.0;  // r = 5 cm
  p.insertion_speed_m_s = 2e-3;
  p.spin_rate_max_rad_s = 2.0 * kPi * 5.0;  // alpha_min = 0.2 at 2 mm cycles
  p.duty_cycle_length_m = 2e-3;
  return p;
}

TipPose3 alongX() {
  return makeTipPose(Vector3::Zero(), Vector3::UnitX(), Vector3::UnitY());
}

double angleBetween(const Vector3& a, const Vector3& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b));
}

TEST(Needle3d, ArcMatchesClosedFormCircle) {
  const double kappa = 20.0;
  for (double length : {0.0, 1e-7, 0.01, kPi / 2.0 / kappa, 0.2}) {
    const TipPose3 end = advanceArc(alongX(), kappa, length);
    const double phi = kappa * length;
    EXPECT_NEAR(
        (end.p_SceneTip - Vector3(std::sin(phi) / kappa, (1 - std::cos(phi)) / kappa, 0)).norm(),
        0.0, kExactPositionTol_m)
        << "length " << length;
    EXPECT_NEAR(angleBetween(end.tangent(), Vector3(std::cos(phi), std::sin(phi), 0.0)), 0.0,
                kExactAngleTol_rad);
    EXPECT_NEAR((end.R_SceneTip.transpose() * end.R_SceneTip - Matrix3::Identity()).norm(), 0.0,
                kExactAngleTol_rad);
  }
  const TipPose3 full = advanceArc(alongX(), kappa, 2.0 * kPi / kappa);
  EXPECT_NEAR(full.p_SceneTip.norm(), 0.0, kExactPositionTol_m);
}

TEST(Needle3d, PureRollIsStraightAndTurnsTheBevel) {
  const TipPose3 end = screwMotion(alongX(), 0.0, 100.0, 0.01);  // 1 rad of roll
  EXPECT_NEAR((end.p_SceneTip - Vector3(0.01, 0, 0)).norm(), 0.0, kExactPositionTol_m);
  EXPECT_NEAR(angleBetween(end.bevel(), Vector3(0, std::cos(1.0), std::sin(1.0))), 0.0,
              kExactAngleTol_rad);
}

TEST(Needle3d, PlanarArcsAgreeWithTheModelOf53) {
  // Bevel left in 5.3 bends counter-clockwise in x-y: d = t rotated +90 degrees about +z.
  const double radius = 0.05;
  for (double theta : {-1.0, 0.0, 0.3, 2.0}) {
    TipPose planar;
    planar.p_SceneTip = geometry::Point2(0.01, 0.02);
    planar.theta_rad = theta;
    for (auto control : {Control::kInsert, Control::kFlip}) {
      const TipPose expected = advanceTip(planar, control, 0.0, 0.03, radius);
      TipPose3 pose =
          makeTipPose(Vector3(0.01, 0.02, 0.0), Vector3(std::cos(theta), std::sin(theta), 0.0),
                      Vector3(-std::sin(theta), std::cos(theta), 0.0));
      if (control == Control::kFlip) {
        pose = rotateBevel(pose, kPi);
      }
      const TipPose3 end = advanceArc(pose, 1.0 / radius, 0.03);
      EXPECT_NEAR(end.p_SceneTip.x(), expected.p_SceneTip.x(), kExactPositionTol_m);
      EXPECT_NEAR(end.p_SceneTip.y(), expected.p_SceneTip.y(), kExactPositionTol_m);
      EXPECT_NEAR(end.p_SceneTip.z(), 0.0, kExactPositionTol_m);
      EXPECT_NEAR(std::atan2(end.tangent().y(), end.tangent().x()),
                  std::remainder(expected.theta_rad, 2.0 * kPi), kExactAngleTol_rad);
    }
  }
}

TEST(Needle3d, MakeTipPoseRefusesDegenerateInput) {
  EXPECT_THROW(makeTipPose(Vector3::Zero(), Vector3::Zero(), Vector3::UnitY()),
               std::invalid_argument);
  EXPECT_THROW(makeTipPose(Vector3::Zero(), Vector3::UnitX(), Vector3::UnitX() * 3.0),
               std::invalid_argument);
}

TEST(Needle3d, DutyCycleMeanCurvatureMatchesRequest) {
  const NeedleParams3 params = defaultParams();
  const double length = 0.04;  // 20 cycles of 2 mm
  const double cycle_length = cycleLength(length, params);
  for (double fraction : {0.0, 0.2, 0.5, 0.7, 0.8, 1.0}) {
    const double kappa = fraction * params.kappa_max_per_m;
    const DutyCycle cycle = dutyCycleFor(kappa, params, cycle_length);
    ASSERT_FALSE(cycle.saturated) << "fraction " << fraction;
    EXPECT_NEAR(cycle.kappa_per_m, kappa, 1e-9);
    const TipPose3 end = insertDutyCycled(alongX(), cycle, length, params);
    const double turn = angleBetween(alongX().tangent(), end.tangent());
    EXPECT_NEAR(turn / length, kappa, kDutyCycleCurvatureRelTol * params.kappa_max_per_m)
        << "fraction " << fraction;
    // Out of the bevel's plane (z) the path drifts by the residual heading times the length.
    const double drift = residualHeadingRad(cycle, params, cycle_length) * length;
    EXPECT_NEAR(std::abs(end.p_SceneTip.z()), drift, kResidualRelTol * drift + kHelixTol_m)
        << "fraction " << fraction;
    const TipPose3 ideal = advanceArc(alongX(), kappa, length);
    const double bound = kappa * params.duty_cycle_length_m * length + drift + kHelixTol_m;
    EXPECT_LE((end.p_SceneTip - ideal.p_SceneTip).norm(), bound) << "fraction " << fraction;
    // The bevel ends where it started up to the screws' over-roll, pi (kappa / rho)^2 a turn.
    const double rho = cycle.spin_fraction > 0 ? 2 * kPi / (cycle.spin_fraction * cycle_length) : 1;
    const double over_roll =
        cycle.spin_fraction > 0 ? 20.0 * kPi * std::pow(params.kappa_max_per_m / rho, 2) : 0.0;
    EXPECT_NEAR(angleBetween(end.bevel(), ideal.bevel()), over_roll,
                kResidualRelTol * over_roll + kTurnTol_rad)
        << "fraction " << fraction;
  }
}

TEST(Needle3d, DutyCycleResidualIsNonZeroButSmall) {
  // The screw of a spin is not an exact full turn about the tangent: the model has a residual.
  const NeedleParams3 params = defaultParams();
  const DutyCycle cycle = dutyCycleFor(0.5 * params.kappa_max_per_m, params, 2e-3);
  const TipPose3 end = insertDutyCycled(alongX(), cycle, 2e-3, params);
  const TipPose3 ideal = advanceArc(alongX(), cycle.kappa_per_m, 2e-3);
  const double residual = (end.p_SceneTip - ideal.p_SceneTip).norm();
  EXPECT_GT(residual, 1e-9);
  EXPECT_LT(residual, 1e-4);
}

TEST(Needle3d, SpinRateLimitSaturatesToTheNearestAchievableCurvature) {
  const NeedleParams3 params = defaultParams();
  const double kmax = params.kappa_max_per_m;
  EXPECT_NEAR(minSpinFraction(params, 2e-3), 0.2, 1e-12);
  // In the gap (0.8 kmax, kmax): nearer kmax -> kmax, nearer 0.8 kmax -> 0.8 kmax.
  DutyCycle high = dutyCycleFor(0.95 * kmax, params, 2e-3);
  EXPECT_TRUE(high.saturated);
  EXPECT_DOUBLE_EQ(high.kappa_per_m, kmax);
  EXPECT_DOUBLE_EQ(high.spin_fraction, 0.0);
  DutyCycle low = dutyCycleFor(0.85 * kmax, params, 2e-3);
  EXPECT_TRUE(low.saturated);
  EXPECT_NEAR(low.kappa_per_m, 0.8 * kmax, 1e-9);
  // Out of range requests are clamped and flagged.
  EXPECT_TRUE(dutyCycleFor(-1.0, params, 2e-3).saturated);
  EXPECT_DOUBLE_EQ(dutyCycleFor(-1.0, params, 2e-3).kappa_per_m, 0.0);
  EXPECT_TRUE(dutyCycleFor(2.0 * kmax, params, 2e-3).saturated);
  EXPECT_DOUBLE_EQ(dutyCycleFor(2.0 * kmax, params, 2e-3).kappa_per_m, kmax);
  // No request and no step length makes the stage spin faster than its limit.
  for (double step : {2e-4, 1e-3, 2e-3, 3e-3, 5e-3, 1e-2}) {
    for (int i = 0; i <= 100; ++i) {
      const double request = kmax * (i / 100.0);
      const DutyCycle c = dutyCycleFor(request, params, cycleLength(step, params));
      EXPECT_LE(c.spin_rate_rad_s, params.spin_rate_max_rad_s * (1.0 + kSpinRateTol))
          << "step " << step << " request " << request;
      EXPECT_EQ(c.saturated, std::abs(c.kappa_per_m - request) > 1e-9 * kmax);
    }
  }
  // A cycle too short for one turn at the limit allows only the held bevel.
  const DutyCycle short_cycle = dutyCycleFor(0.0, params, 2e-4);
  EXPECT_TRUE(short_cycle.saturated);
  EXPECT_DOUBLE_EQ(short_cycle.kappa_per_m, kmax);
}

TEST(Needle3d, ParamsValidationNamesTheField) {
  NeedleParams3 params = defaultParams();
  params.spin_rate_max_rad_s = 1.0;  // cannot turn once per 2 mm cycle at 2 mm/s
  try {
    params.validate();
    FAIL() << "accepted a spin rate too low for one turn per cycle";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("spin_rate_max_rad_s"), std::string::npos) << e.what();
  }
  params = defaultParams();
  params.kappa_max_per_m = std::nan("");
  EXPECT_THROW(params.validate(), std::invalid_argument);
  NoiseParams3 noise;
  noise.sigma_spin_rad = -1.0;
  EXPECT_THROW(NoisyNeedle3(defaultParams(), noise, 1), std::invalid_argument);
}

struct Stats {
  double mean = 0.0;
  double sd = 0.0;
};

Stats stats(const std::vector<double>& v) {
  Stats s;
  for (double x : v) {
    s.mean += x;
  }
  s.mean /= static_cast<double>(v.size());
  for (double x : v) {
    s.sd += (x - s.mean) * (x - s.mean);
  }
  s.sd = std::sqrt(s.sd / static_cast<double>(v.size() - 1));
  return s;
}

TEST(Needle3d, NoiseHasTheModelsStatistics) {
  NoiseParams3 noise;
  noise.sigma_insert_rad = 2.0 * kDeg;
  noise.sigma_spin_rad = 10.0 * kDeg;
  noise.sigma_roll_rad = 5.0 * kDeg;
  NoisyNeedle3 needle(defaultParams(), noise, 42);
  std::vector<double> insert_d, insert_n, spin_d, spin_n, roll, tangent_angle;
  for (int i = 0; i < kNoiseSamples; ++i) {
    const StepRecord plain = needle.step(alongX(), {0.0, 20.0, 0.0});
    insert_d.push_back(plain.deflection_rad.x());
    insert_n.push_back(plain.deflection_rad.y());
    // A zero-length step: the tangent turned by exactly the drawn deflection.
    tangent_angle.push_back(angleBetween(plain.pose.tangent(), Vector3::UnitX()) -
                            plain.deflection_rad.norm());
    const StepRecord spun = needle.step(alongX(), {kPi / 2.0, 20.0, 0.0});
    spin_d.push_back(spun.deflection_rad.x());
    spin_n.push_back(spun.deflection_rad.y());
    // Bevel after a commanded quarter turn and the deflection: undo the deflection to read
    // the roll error about the original tangent.
    const TipPose3 undone = deflect(spun.pose, -spun.deflection_rad);
    roll.push_back(std::atan2(undone.bevel().z(), undone.bevel().y()) - kPi / 2.0);
  }
  const auto check = [](const std::vector<double>& v, double sigma, const char* what) {
    const Stats s = stats(v);
    EXPECT_NEAR(s.sd, sigma, kSigmaRelTol * sigma) << what;
    EXPECT_NEAR(s.mean, 0.0, kMeanTol_sigma * sigma) << what;
  };
  check(insert_d, noise.sigma_insert_rad, "insert about d");
  check(insert_n, noise.sigma_insert_rad, "insert about n");
  check(spin_d, noise.sigma_spin_rad, "spin about d");
  check(spin_n, noise.sigma_spin_rad, "spin about n");
  check(roll, noise.sigma_roll_rad, "roll");
  for (double residual : tangent_angle) {
    ASSERT_NEAR(residual, 0.0, 1e-12);
  }
}

TEST(Needle3d, InPlaneNoiseStaysInThePlaneAndSeedsRepeat) {
  NoiseParams3 noise;
  noise.sigma_insert_rad = 3.0 * kDeg;
  noise.sigma_spin_rad = 10.0 * kDeg;
  noise.in_plane_only = true;
  NoisyNeedle3 a(defaultParams(), noise, 7);
  NoisyNeedle3 b(defaultParams(), noise, 7);
  NoisyNeedle3 c(defaultParams(), noise, 8);
  TipPose3 pa = alongX(), pb = alongX(), pc = alongX();
  for (int i = 0; i < 20; ++i) {
    const Control3 u{i % 3 == 0 ? kPi : 0.0, 20.0, 5e-3};  // flips only: bevel stays in x-y
    pa = a.step(pa, u).pose;
    pb = b.step(pb, u).pose;
    pc = c.step(pc, u).pose;
  }
  EXPECT_EQ((pa.p_SceneTip - pb.p_SceneTip).norm(), 0.0);
  EXPECT_GT((pa.p_SceneTip - pc.p_SceneTip).norm(), 1e-6);
  EXPECT_NEAR(pa.p_SceneTip.z(), 0.0, kExactPositionTol_m);
  EXPECT_NEAR(pa.tangent().z(), 0.0, kExactAngleTol_rad);
}

TEST(Needle3d, StepRefusesBadControls) {
  NoisyNeedle3 needle(defaultParams(), NoiseParams3{}, 1);
  EXPECT_THROW(needle.step(alongX(), {0.0, -1.0, 1e-3}), std::invalid_argument);
  EXPECT_THROW(needle.step(alongX(), {0.0, 1.0, -1e-3}), std::invalid_argument);
  EXPECT_THROW(needle.step(alongX(), {std::nan(""), 1.0, 1e-3}), std::invalid_argument);
}

}  // namespace
}  // namespace needle_guidance::needle_model

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
