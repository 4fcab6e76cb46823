// procedures::SteeringTrial3 (the ROS procedure's world): a noiseless entry plan
// followed step by step ends in the target; a straight push along the urethra is stopped by it;
// a trial without a plan ends where it is, as a failure; the summary's Wilson interval; a plan
// beyond the insertion joint's travel ends that trial (not the run) as a refusal naming the
// travel; the trial loop leaves the robot safe after the last trial and after a fault and the
// report says what it did.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <string>

#include "needle_guidance/procedures/steering_3d_trials.h"
#include "needle_guidance/steering_3d/planner_3d.h"

namespace {

namespace sd = needle_guidance::steering_3d;
namespace nm = needle_guidance::needle_model;
using needle_guidance::procedures::SteeringTrial3;

// [mm] a noiseless plan ends at the target centre up to the duty-cycling residual
// (0.38 mm median for the noiseless open loop); well inside the 2.5 mm target.
constexpr double kNoiselessErrorMm = 1.0;

nm::Scene3d prostate() {
  return nm::loadScene3d(std::string(NG_SOURCE_DIR) +
                         "/config/scenes/steering_3d/prostate_3d.yaml");
}

TEST(SteeringTrial3, NoiselessEntryPlanFollowedStepByStepReachesTheTarget) {
  const nm::Scene3d scene = prostate();
  const nm::CollisionWorld3 world = scene.collisionWorld();
  const sd::Planner3 planner(scene, world, sd::PlannerParams3{}, nm::NoiseParams3{});
  const auto plan = planner.planFromEntry(11);
  ASSERT_TRUE(plan) << plan.status().toString();
  SteeringTrial3 trial(scene, world, nm::NoiseParams3{}, 5, 200);
  trial.start(plan.value().start, plan.value().p_success, 0.0);
  trial.setPlan(plan.value().controls);
  int steps = 0;
  while (trial.step()) {
    ++steps;
  }
  const sd::TrialResult3& r = trial.result();
  EXPECT_TRUE(r.success) << r.message;
  EXPECT_EQ(r.contact, nm::Contact3::kFree);
  EXPECT_LT(r.target_error_m * 1e3, kNoiselessErrorMm);
  // whole steps of 5 mm, each segment's remainder one more step
  EXPECT_GE(r.steps, static_cast<int>(plan.value().length_m / scene.step_length_m));
  EXPECT_LE(r.steps, static_cast<int>(plan.value().length_m / scene.step_length_m) +
                         static_cast<int>(plan.value().controls.size()));
  EXPECT_EQ(steps + 1, r.steps);  // step() returned false on the last
}

TEST(SteeringTrial3, StraightPushAlongTheUrethraTouchesIt) {
  const nm::Scene3d scene = prostate();
  const nm::CollisionWorld3 world = scene.collisionWorld();
  SteeringTrial3 trial(scene, world, nm::NoiseParams3{}, 5, 200);
  trial.start(nm::makeTipPose(scene.entry.center_m, scene.entry.direction, nm::Vector3::UnitY()),
              0.0, 0.0);
  trial.setPlan({nm::Control3{0.0, 0.0, 0.08}});
  while (trial.step()) {
  }
  EXPECT_FALSE(trial.result().success);
  EXPECT_EQ(trial.result().contact, nm::Contact3::kObstacle);
  EXPECT_EQ(trial.result().obstacle, "urethra");
}

TEST(SteeringTrial3, WithoutAPlanTheTrialEndsAsAFailure) {
  const nm::Scene3d scene = prostate();
  const nm::CollisionWorld3 world = scene.collisionWorld();
  SteeringTrial3 trial(scene, world, nm::NoiseParams3{}, 5, 200);
  trial.start(nm::makeTipPose(scene.entry.center_m, scene.entry.direction, nm::Vector3::UnitY()),
              0.0, 0.0);
  EXPECT_FALSE(trial.step());
  EXPECT_TRUE(trial.done());
  EXPECT_FALSE(trial.result().success);
  EXPECT_EQ(trial.result().message, "no plan to follow");
  EXPECT_EQ(trial.result().steps, 0);
}

TEST(SteeringTrial3, SummaryCountsSuccessesAndFaultsWithAWilsonInterval) {
  std::vector<sd::TrialResult3> results(4);
  results[0].success = results[1].success = results[2].success = true;
  for (auto& r : results)
    r.target_error_m = 1e-3;
  const auto s = needle_guidance::procedures::summarize(results, {false, false, false, true});
  EXPECT_EQ(s.successes, 3);
  EXPECT_EQ(s.faults, 1);
  EXPECT_DOUBLE_EQ(s.success_rate, 0.75);
  // Wilson 95 % for 3/4: [0.3006, 0.9544] (closed form)
  EXPECT_NEAR(s.success_ci_low, 0.3006, 1e-4);
  EXPECT_NEAR(s.success_ci_high, 0.9544, 1e-4);
  EXPECT_FALSE(needle_guidance::procedures::runSucceeded(s));  // a fault
}

TEST(SteeringTrial3, AStepBeyondTheJointsTravelEndsTheTrialAsARefusalNamingIt) {
  const nm::Scene3d scene = prostate();
  const nm::CollisionWorld3 world = scene.collisionWorld();
  const sd::Planner3 planner(scene, world, sd::PlannerParams3{}, nm::NoiseParams3{});
  const auto plan = planner.planFromEntry(11);  // the noiseless plan that reaches the target
  ASSERT_TRUE(plan) << plan.status().toString();
  constexpr double kTravelM = 0.012;  // [m] far shorter than the plan
  ASSERT_GT(plan.value().length_m, 2.0 * kTravelM);
  SteeringTrial3 trial(scene, world, nm::NoiseParams3{}, 5, 200);
  trial.setTravel(kTravelM);
  trial.start(plan.value().start, plan.value().p_success, 0.0);
  trial.setPlan(plan.value().controls);
  while (trial.step()) {
  }
  const sd::TrialResult3& r = trial.result();
  EXPECT_TRUE(trial.done());
  EXPECT_FALSE(r.success);
  EXPECT_EQ(r.contact, nm::Contact3::kFree);
  EXPECT_LE(trial.insertedLength_m(), kTravelM);
  EXPECT_GT(trial.insertedLength_m(), kTravelM - scene.step_length_m);  // stopped at the last fit
  EXPECT_NE(r.message.find("beyond the insertion joint's travel of 0.012 m"), std::string::npos)
      << r.message;
  EXPECT_EQ(r.message.rfind("refused", 0), 0U) << r.message;
}

TEST(SteeringTrial3, PlannerAnswersReplaceKeepOrRefuse) {
  const nm::Scene3d scene = prostate();
  const nm::CollisionWorld3 world = scene.collisionWorld();
  const sd::Planner3 planner(scene, world, sd::PlannerParams3{}, nm::NoiseParams3{});
  const auto plan = planner.planFromEntry(11);
  ASSERT_TRUE(plan) << plan.status().toString();
  // A replan that found nothing keeps the plan being followed and counts its time.
  SteeringTrial3 kept(scene, world, nm::NoiseParams3{}, 5, 200);
  kept.start(plan.value().start, plan.value().p_success, 0.0);
  kept.setPlan(plan.value().controls);
  EXPECT_TRUE(kept.followAnswer("no_path_within_budget", "", 0.02, {}));
  EXPECT_EQ(kept.result().replan_s.size(), 1U);
  EXPECT_TRUE(kept.step()) << kept.result().message;
  // "ok" replaces the plan: from none to the planner's.
  SteeringTrial3 replaced(scene, world, nm::NoiseParams3{}, 5, 200);
  replaced.start(plan.value().start, plan.value().p_success, 0.0);
  EXPECT_TRUE(replaced.followAnswer("ok", "", 0.01, plan.value().controls));
  EXPECT_TRUE(replaced.step()) << replaced.result().message;
  // "bad_input" is a fault: the trial ends, naming the planner's reason.
  SteeringTrial3 refused(scene, world, nm::NoiseParams3{}, 5, 200);
  refused.start(plan.value().start, plan.value().p_success, 0.0);
  EXPECT_FALSE(refused.followAnswer("bad_input", "position not finite", 0.0, {}));
  EXPECT_TRUE(refused.done());
  EXPECT_FALSE(refused.result().success);
  EXPECT_EQ(refused.result().message, "the planner refused the tip: position not finite");
}

/// Fake devices: trial `fault_at` throws with a dead node; every other trial is refused at the
/// start (no plan), which is an outcome. Records leaveSafe calls.
class FakeDevices3 : public needle_guidance::procedures::SteeringDevices3 {
public:
  explicit FakeDevices3(int fault_at) : fault_at_(fault_at) {}
  bool runTrial(SteeringTrial3& trial, std::uint64_t) override {
    if (trials_run_++ == fault_at_) {
      dead_ = true;
      throw std::runtime_error("the robot's steer goal: no result within the timeout");
    }
    trial.refuseStart(sd::PlanCode::kNoPathWithinBudget, "no plan in the fake");
    return true;
  }
  std::optional<std::string> fault() override {
    return dead_ ? std::optional<std::string>("node /insertion_robot died") : std::nullopt;
  }
  std::string leaveSafe() override {
    ++safe_calls_;
    safe_after_trials_ = trials_run_;
    return "needle retracted";
  }
  void progress(const std::string&) override {}

  int trials_run_ = 0, safe_calls_ = 0, safe_after_trials_ = -1;

private:
  int fault_at_;
  bool dead_ = false;
};

TEST(SteeringTrials3, TheRobotIsLeftSafeAfterTheLastTrial) {
  const nm::Scene3d scene = prostate();
  const nm::CollisionWorld3 world = scene.collisionWorld();
  FakeDevices3 devices(-1);
  const auto run =
      needle_guidance::procedures::runSteeringTrials3(scene, world, devices, 3, 7, 200, 0.12);
  EXPECT_EQ(run.results.size(), 3U);
  EXPECT_TRUE(run.completed(3));
  EXPECT_EQ(devices.safe_calls_, 1);
  EXPECT_EQ(devices.safe_after_trials_, 3);  // after the last trial, not only before each
  EXPECT_EQ(run.safe_stop, "needle retracted");
}

TEST(SteeringTrials3, AFaultStopsTheRunLeavesTheRobotSafeAndTheReportSaysSo) {
  const nm::Scene3d scene = prostate();
  const nm::CollisionWorld3 world = scene.collisionWorld();
  FakeDevices3 devices(1);
  const auto run =
      needle_guidance::procedures::runSteeringTrials3(scene, world, devices, 5, 7, 200, 0.12);
  ASSERT_EQ(run.results.size(), 2U);  // stopped at the fault
  EXPECT_FALSE(run.completed(5));
  EXPECT_FALSE(run.faulted[0]);
  EXPECT_TRUE(run.faulted[1]);
  EXPECT_EQ(run.results[1].message, "node /insertion_robot died");  // the cause, not the symptom
  EXPECT_EQ(devices.safe_calls_, 1);
  EXPECT_EQ(devices.safe_after_trials_, 2);
  const std::string dir = testing::TempDir() + "/steering_3d_trials_safe_stop";
  std::filesystem::create_directories(dir);
  needle_guidance::procedures::writeSteeringReport3(dir, scene, run, {}, 7,
                                                    {"/insertion_robot", "died", 1.0});
  std::stringstream json;
  json << std::ifstream(dir + "/summary.json").rdbuf();
  EXPECT_NE(json.str().find("\"safe_stop\": \"needle retracted\""), std::string::npos)
      << json.str();
  EXPECT_NE(json.str().find("\"status\": \"node_died\""), std::string::npos) << json.str();
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
