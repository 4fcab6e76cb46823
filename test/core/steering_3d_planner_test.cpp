// Tests for the 3-D RRT planner (planner_3d.h) and the closed loop (closed_loop_3d.h): plans
// re-checked independently, the hard cases' clear "no plan" (target in an obstacle, target
// unreachable under kappa_max, start in an obstacle), a start on the tissue boundary, the
// success-probability estimate's limits, and closed-loop outcomes on the prostate-like scene.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <string>

#include "needle_guidance/needle_model/scene_3d.h"
#include "needle_guidance/steering_3d/closed_loop_3d.h"
#include "needle_guidance/steering_3d/planner_3d.h"

namespace needle_guidance::steering_3d {

using namespace needle_model;  // the needle, meshes and scenes the planner works on
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

TEST(Planner3d, NoiselessApproachIsCertainAndEndsAtTheCentre) {
  // With sigma = 0 every free approach candidate succeeds: the tie goes to the smallest final
  // error, so the plan ends at the target centre with an estimate of 1.
  const Scene3d s = prostate();
  const CollisionWorld3 world = s.collisionWorld();
  PlannerParams3 aware = testParams();
  aware.time_budget_s = 5.0;
  const TipPose3 tip = makeTipPose(Vector3(20, 2, 1) * kMm, Vector3::UnitX(), Vector3::UnitY());
  const auto a = Planner3(s, world, aware, s.noise.scaled(0.0)).planFromTip(tip, kSeed);
  ASSERT_TRUE(a) << a.status().toString();
  EXPECT_GE(a.value().approach, 0);  // the direct approach is free from here
  EXPECT_DOUBLE_EQ(a.value().p_success, 1.0);
  TipPose3 pose = a.value().start;
  for (const Control3& c : a.value().controls) {
    EXPECT_LE(c.curvature_per_m, s.needle.kappa_max_per_m * (1 + 1e-12));
    pose = advanceArc(rotateBevel(pose, c.rotate_rad), c.curvature_per_m, c.length_m);
  }
  // The first step spreads the turn over the whole step: its end is off the exact turn by
  // ~kappa l^2 / 8 (< 0.1 mm at 20 /m over 5 mm); the straight part keeps the heading.
  constexpr double kSpreadTurnTol_m = 0.15 * kMm;
  EXPECT_LE((pose.p_SceneTip - s.target.center_m).norm(), kSpreadTurnTol_m);
  EXPECT_TRUE(world.checkPolyline(a.value().points()).free());
}

/// Successes of the replanning loop from `tip` over `trials` seeded needles (seed 500 + i).
int successesFromTip(const Scene3d& s, const CollisionWorld3& world, const PlannerParams3& params,
                     const NoiseParams3& noise, const TipPose3& start, int trials) {
  const Planner3 planner(s, world, params, noise);
  int successes = 0;
  for (int i = 0; i < trials; ++i) {
    NoisyNeedle3 needle(s.needle, noise, 500 + i);
    TrialResult3 r;
    TipPose3 tip = start;
    auto plan = planner.planFromTip(tip, callSeed(500 + i, 0));
    while (plan && r.steps < 40) {
      Control3 c = plan.value().controls.front();
      const bool last =
          plan.value().controls.size() == 1 && c.length_m <= s.step_length_m * 1.000001;
      c.length_m = std::min(c.length_m, s.step_length_m);
      if (!executeStep3(needle, world, c, tip, r, TrialOptions3{}) || last) {
        break;
      }
      plan = planner.planFromTip(tip, callSeed(500 + i, static_cast<std::uint64_t>(r.steps)));
    }
    finishTrial3(s, tip, r);
    successes += r.success ? 1 : 0;
  }
  return successes;
}

TEST(ClosedLoop3d, AwareChoiceBeatsTheFirstFoundPlanAtTwiceSigma) {
  // Past the arch, 4 cm from the target and heading off it: the baseline's single arc needs
  // ~14 /m and a spin-deflected step can push it past kappa_max; the aware choice scores the
  // approaches by rollouts and straightens early or holds the bevel plane. Same needles for both.
  const Scene3d s = prostate();
  const CollisionWorld3 world = s.collisionWorld();
  PlannerParams3 aware = testParams();
  // Whole rollout rounds (~5 ms of CPU) fit the budget even under load: the outcome is tested;
  // the node limit bounds the trees of the replans that find no plan.
  aware.time_budget_s = 0.2;
  aware.max_nodes = 3000;
  PlannerParams3 first = aware;
  first.choice = PlanChoice::kFirstFound;
  const NoiseParams3 noise = s.noise.scaled(2.0);
  const TipPose3 tip =
      makeTipPose(Vector3(22, 4, 0) * kMm, Vector3(1, 0.05, 0.1), Vector3::UnitY());
  constexpr int kTrials = 60;
  const int ours = successesFromTip(s, world, aware, noise, tip, kTrials);
  const int base = successesFromTip(s, world, first, noise, tip, kTrials);
  std::cout << "[ info ] aware " << ours << " vs first found " << base << " of " << kTrials << "\n";
  EXPECT_GT(ours, base);
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
