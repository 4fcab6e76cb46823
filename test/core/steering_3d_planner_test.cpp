// Tests for the 3-D RRT planner (planner_3d.h) and the closed loop (closed_loop_3d.h): plans
// re-checked independently, the hard cases' clear "no plan" (target in an obstacle, target
// unreachable under kappa_max, start in an obstacle), a start on the tissue boundary, the
// success-probability estimate's limits, and closed-loop outcomes on the prostate-like scene.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "needle_guidance/steering_3d/closed_loop_3d.h"
#include "needle_guidance/steering_3d/planner_3d.h"
#include "needle_guidance/steering_3d/scene_3d.h"

namespace needle_guidance::steering_3d {
namespace {

constexpr double kMm = 1e-3;
constexpr std::uint64_t kSeed = 7;
/// A goal arc must end within this fraction of the target radius of its centre (planner_3d.cpp).
constexpr double kGoalEndFraction = 0.25;
/// A plan's end is recomputed by chaining exact arcs: double rounding only [m].
constexpr double kChainTol_m = 1e-9;

Scene3d prostate() {
  return loadScene3d(std::string(NG_SOURCE_DIR) + "/config/scenes/steering_3d/prostate_3d.yaml");
}

PlannerParams3 testParams() {
  PlannerParams3 p;
  p.entry_time_budget_s = 2.0;  // generous: the tests check outcomes, the bench speed
  p.time_budget_s = 0.2;
  p.entry_estimate_budget_s = 0.1;  // the rollouts' budget: outcomes, not the estimate's spread
  p.estimate_budget_s = 0.01;
  return p;
}

TEST(Planner3d, PlanFromEntryIsFeasibleAndEndsAtTheTarget) {
  const Scene3d s = prostate();
  const CollisionWorld3 world = s.collisionWorld();
  const Planner3 planner(s, world, testParams(), s.noise);
  PlanReport report;
  const auto plan = planner.planFromEntry(kSeed, &report);
  ASSERT_TRUE(plan) << plan.status().toString();
  EXPECT_TRUE(s.entry.allows(plan.value().start.p_SceneTip, plan.value().start.tangent(), 1e-9));
  TipPose3 pose = plan.value().start;
  double length = 0.0;
  for (const Control3& c : plan.value().controls) {
    EXPECT_LE(c.curvature_per_m, s.needle.kappa_max_per_m * (1 + 1e-12));
    pose = advanceArc(rotateBevel(pose, c.rotate_rad), c.curvature_per_m, c.length_m);
    length += c.length_m;
  }
  EXPECT_NEAR(length, plan.value().length_m, kChainTol_m);
  EXPECT_LE((pose.p_SceneTip - s.target.center_m).norm(), kGoalEndFraction * s.target.radius_m);
  // Independent re-check of the whole plan as a 1 mm polyline.
  EXPECT_TRUE(world.checkPolyline(plan.value().points()).free());
  EXPECT_GT(plan.value().p_success, 0.0);
  EXPECT_LE(plan.value().p_success, 1.0);
  EXPECT_GE(report.plans_found, 1);
}

TEST(Planner3d, TargetInsideAnObstacleIsAClearNoPlan) {
  Scene3d s = prostate();
  s.target.center_m = Vector3(40, -3, 0) * kMm;  // on the urethra's axis
  const CollisionWorld3 world = s.collisionWorld();
  const Planner3 planner(s, world, testParams(), s.noise);
  const auto plan = planner.planFromEntry(kSeed);
  ASSERT_FALSE(plan);
  EXPECT_EQ(plan.status().code(), PlanCode::kTargetInObstacle);
  EXPECT_NE(plan.status().toString().find("urethra"), std::string::npos)
      << plan.status().toString();
}

TEST(Planner3d, TargetUnreachableUnderKappaMaxIsAClearNoPlan) {
  // No obstacles; a 4 cm block; the target 15 mm off-axis only 8 mm deep: from the 10 mm disc
  // within 10 degrees a needle of r = 5 cm rises at most ~12 mm there, and the block is too
  // small to loop back.
  Scene3d s = prostate();
  s.obstacles.clear();
  s.tissue = boxMesh(Vector3(0, -20, -20) * kMm, Vector3(40, 20, 20) * kMm);
  s.target.center_m = Vector3(8, 15, 0) * kMm;
  s.target.radius_m = 1 * kMm;
  const CollisionWorld3 world = s.collisionWorld();
  PlannerParams3 params = testParams();
  params.entry_time_budget_s = 0.3;
  const Planner3 planner(s, world, params, s.noise);
  PlanReport report;
  const auto plan = planner.planFromEntry(kSeed, &report);
  ASSERT_FALSE(plan);
  EXPECT_EQ(plan.status().code(), PlanCode::kNoPathWithinBudget);
  EXPECT_NE(plan.status().toString().find("no plan"), std::string::npos);
  EXPECT_GT(report.nodes, 100);  // it searched
}

TEST(Planner3d, StartOnTheTissueBoundaryPlansAndStartInAnObstacleIsRefused) {
  const Scene3d s = prostate();
  const CollisionWorld3 world = s.collisionWorld();
  const Planner3 planner(s, world, testParams(), s.noise);
  // On the perineal face x = 0, 6 mm above the urethra's axis, heading +x.
  const TipPose3 on_boundary =
      makeTipPose(Vector3(0, 6, 3) * kMm, Vector3::UnitX(), Vector3::UnitY());
  const auto plan = planner.planFromTip(on_boundary, kSeed);
  EXPECT_TRUE(plan) << plan.status().toString();
  const TipPose3 in_arch =
      makeTipPose(Vector3(30, 16, 0) * kMm, Vector3::UnitX(), Vector3::UnitY());
  const auto refused = planner.planFromTip(in_arch, kSeed);
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.status().code(), PlanCode::kStartInObstacle);
  EXPECT_NE(refused.status().toString().find("pubic_arch"), std::string::npos);
  const TipPose3 outside = makeTipPose(Vector3(-5, 0, 0) * kMm, Vector3::UnitX(), Vector3::UnitY());
  EXPECT_EQ(planner.planFromTip(outside, kSeed).status().code(), PlanCode::kStartOutsideTissue);
}

TEST(Planner3d, SuccessProbabilityLimits) {
  const Scene3d s = prostate();
  const CollisionWorld3 world = s.collisionWorld();
  const Planner3 planner(s, world, testParams(), s.noise);
  const auto plan = planner.planFromEntry(kSeed);
  ASSERT_TRUE(plan);
  const double kmax = s.needle.kappa_max_per_m;
  double previous = 2.0;
  for (double scale : {0.0, 0.5, 1.0, 2.0, 4.0, 50.0}) {
    const double p = successProbability(plan.value(), world, s.target, s.noise.scaled(scale),
                                        s.step_length_m, kmax);
    EXPECT_LE(p, previous) << "scale " << scale;  // more noise, no higher estimate
    previous = p;
    if (scale == 0.0) {
      EXPECT_DOUBLE_EQ(p, 1.0);
    }
  }
  EXPECT_LT(previous, 0.01);  // 50x: the target cannot be hit
}

TEST(Planner3d, MonteCarloEstimateLimitsAndCommonRandomNumbers) {
  const Scene3d s = prostate();
  const CollisionWorld3 world = s.collisionWorld();
  const PlannerParams3 params = testParams();
  const auto plan = Planner3(s, world, params, s.noise).planFromEntry(kSeed);
  ASSERT_TRUE(plan);
  constexpr int kRollouts = 40;
  // Without noise every rollout follows the plan into the target.
  EXPECT_EQ(monteCarloSuccesses(plan.value(), s, world, s.noise.scaled(0.0), params, kRollouts, 3),
            kRollouts);
  // At 20x sigma (10 degrees per step, 30 after a spin) the target is hit by chance only: 2.5 mm
  // behind the arch after a dozen such steps (< 10 % here; 0 of 40 in practice).
  EXPECT_LE(monteCarloSuccesses(plan.value(), s, world, s.noise.scaled(20.0), params, kRollouts, 3),
            kRollouts / 10);
  // Seeded: the same seed gives the same outcomes (the candidates' paired comparison).
  const int a = monteCarloSuccesses(plan.value(), s, world, s.noise, params, kRollouts, 11);
  EXPECT_EQ(a, monteCarloSuccesses(plan.value(), s, world, s.noise, params, kRollouts, 11));
}

TEST(Planner3d, NoiselessChoiceKeepsTheFirstFoundPlan) {
  // With sigma = 0 every candidate that reaches the target scores 1: a tie keeps the baseline's
  // plan, so the aware choice differs from it only on evidence.
  const Scene3d s = prostate();
  const CollisionWorld3 world = s.collisionWorld();
  PlannerParams3 aware = testParams();
  aware.max_nodes = 4000;  // trees bounded by size, not time: the same candidates in both runs
  aware.time_budget_s = 5.0;
  aware.estimate_budget_s = 5.0;
  PlannerParams3 first = aware;
  first.choice = PlanChoice::kFirstFound;
  const TipPose3 tip = makeTipPose(Vector3(20, 2, 1) * kMm, Vector3::UnitX(), Vector3::UnitY());
  const auto a = Planner3(s, world, aware, s.noise.scaled(0.0)).planFromTip(tip, kSeed);
  const auto b = Planner3(s, world, first, s.noise.scaled(0.0)).planFromTip(tip, kSeed);
  ASSERT_TRUE(a && b);
  ASSERT_EQ(a.value().controls.size(), b.value().controls.size());
  EXPECT_DOUBLE_EQ(a.value().length_m, b.value().length_m);
  EXPECT_DOUBLE_EQ(a.value().p_success, 1.0);
}

TEST(ClosedLoop3d, ReplanningReachesTheTargetBehindTheArchAndStraightDoesNot) {
  const Scene3d s = prostate();
  const CollisionWorld3 world = s.collisionWorld();
  PlannerParams3 params = testParams();
  params.time_budget_s = 0.03;
  int ours = 0, straight = 0;
  constexpr int kTrials = 12;
  for (int i = 0; i < kTrials; ++i) {
    ours += runTrial3(s, world, Strategy3::kReplanUncertainty, s.noise, params, 100 + i).success;
    const TrialResult3 st = runTrial3(s, world, Strategy3::kStraight, s.noise, params, 100 + i);
    straight += st.success;
    EXPECT_NE(st.contact, Contact3::kFree) << "the straight needle should hit the arch";
  }
  // The bench measures the rate over >= 200 trials; here 10 of 12 keeps the test meaningful
  // (P(<= 9 of 12) < 2 % at a true rate of 95 %).
  EXPECT_GE(ours, 10);
  EXPECT_EQ(straight, 0);
}

TEST(ClosedLoop3d, ReplanningThroughBiplaneImagingReachesTheTarget) {
  const Scene3d s = prostate();
  const CollisionWorld3 world = s.collisionWorld();
  PlannerParams3 params = testParams();
  params.time_budget_s = 0.03;
  TrialOptions3 options;
  options.biplane = true;  // default imaging: 0.2 mm per view, 5 % dropout, 2 % outliers
  int successes = 0, fused = 0, missing = 0;
  constexpr int kTrials = 6;
  // A view's 0.2 mm noise, a 5 mm outlier passed by the 1-dof gate and dead reckoning between
  // fused pairs: the estimate stays within this of the true tip [m].
  constexpr double kEstimateTol_m = 6e-3;
  for (int i = 0; i < kTrials; ++i) {
    const TrialResult3 r =
        runTrial3(s, world, Strategy3::kReplanFirstFound, s.noise, params, 300 + i, options);
    successes += r.success;
    fused += r.views_fused;
    missing += r.views_dropped + r.views_gated;
    EXPECT_LT(r.estimate_error_m_max, kEstimateTol_m) << "seed " << 300 + i;
  }
  EXPECT_GE(successes, kTrials - 1);
  // About 13 % of pairs are lost at the default rates (1 - 0.95^2 dropped, a few outliers gated).
  EXPECT_GT(fused, 3 * missing);
}

TEST(ClosedLoop3d, NoiselessOpenLoopHitsTheCentre) {
  const Scene3d s = prostate();
  const CollisionWorld3 world = s.collisionWorld();
  const TrialResult3 r =
      runTrial3(s, world, Strategy3::kOpenLoop, s.noise.scaled(0.0), testParams(), kSeed);
  ASSERT_TRUE(r.success) << r.message;
  // Without noise only the duty cycle's residual and the goal arc's tolerance remain.
  EXPECT_LE(r.target_error_m, kGoalEndFraction * s.target.radius_m + 0.5 * kMm);
}

}  // namespace
}  // namespace needle_guidance::steering_3d

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
