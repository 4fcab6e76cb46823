// The steerable trial loop (procedures/steerable_trials, dissertation 5.5) on in-process devices:
// the closed loop reaches the target as often as the core Monte Carlo of the same policy says;
// a stopped step is classified by the world and the robot's reason; a policy answer without a
// control, a failed device and a dead node end the trial as an error counted apart from the
// misses; the report writes every file, figures included.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "needle_guidance/math.h"
#include "needle_guidance/procedures/guided_trial.h"
#include "needle_guidance/procedures/steerable_trials.h"
#include "needle_guidance/robot/steerable_needle.h"
#include "needle_guidance/steering/value_iteration.h"

#include "../steering_shapes.h"

namespace needle_guidance::procedures {
namespace {

constexpr double kDeg = kPi / 180.0;
constexpr double kStandardErrors = 4.0;  // closed loop vs Monte Carlo, in binomial SEs
constexpr int kTrials = 300;

/// The open workspace with a wall between entry and target, sigma_i 5 deg, sigma_r 10 deg.
steering::SteeringProblem wallProblem() {
  steering::SteeringProblem p =
      steering::test_shapes::openProblem(1e-3, 5 * kDeg, 10 * kDeg, 0.085);
  p.obstacles.push_back(steering::test_shapes::obstacle(
      "wall", steering::test_shapes::rect(0.04, 0.0, 0.05, 0.045), 0.001));
  return p;
}

robot::SteerableNeedleConfig needleConfig(const steering::SteeringProblem& p) {
  robot::SteerableNeedleConfig c;
  c.min_height_m = 0.0;
  c.max_height_m = 0.1;
  c.sigma_insert_rad = p.params.sigma_insert_rad;
  c.sigma_flip_rad = p.params.sigma_flip_rad;
  return c;
}

struct Fixture {
  steering::SteeringProblem problem = wallProblem();
  steering::PolicyTable table = steering::solveValueIteration(steering::SteeringModel(problem));
  steering::StartOptions starts = steering::test_shapes::entryLine();
  robot::SteerableNeedle needle{steering::planarWorkspace(problem), needleConfig(problem),
                                robot::EntryPose{0.05, 0.0}};
  std::uint64_t frame_index = 0;
  SteerableStart start() const {
    const steering::BestStart best = table.bestStart(starts);
    return {best.best.pose, best.best.probability_of_success};
  }
  SteerableTrials trials(int n) const {
    SteerableSettings s;
    s.trials = n;
    return SteerableTrials("wall", problem, table, starts, s);
  }
};

/// In-process devices with faults injected: the robot's step ends as `end` from step
/// `fail_at_step` on, the policy answers `status` without a control, or a node dies after
/// `die_after_controls` answers.
class FaultyDevices : public InProcessSteerableDevices {
public:
  using InProcessSteerableDevices::InProcessSteerableDevices;
  StepEnd end = StepEnd::kMoved;
  int fail_at_step = -1;
  std::string status;  ///< non-empty: the policy's answer has no control
  int die_after_controls = -1;

  std::optional<PolicyAnswer> control(std::string& why_not) override {
    ++controls_;
    if (die_after_controls >= 0 && controls_ > die_after_controls) {
      dead_ = Fault{"/steering_policy", 1.0, "not registered with the master", 0.0};
      why_not = "no control";
      return std::nullopt;
    }
    std::optional<PolicyAnswer> a = InProcessSteerableDevices::control(why_not);
    if (!status.empty()) {
      a->usable = false;
      a->status = status;
    }
    return a;
  }
  StepEnd insertTo(double length_m, std::string& message) override {
    if (fail_at_step >= 0 && ++steps_ > fail_at_step) {
      message = "refused: the robot says so";
      return end;
    }
    return InProcessSteerableDevices::insertTo(length_m, message);
  }
  std::optional<Fault> fault() override { return dead_; }

private:
  int controls_ = 0;
  int steps_ = 0;
  std::optional<Fault> dead_;
};

TEST(SteerableTrials, ClosedLoopSucceedsAsOftenAsTheMonteCarloOfItsPolicy) {
  Fixture f;
  InProcessSteerableDevices devices(f.needle, f.table, nullptr, nullptr, f.frame_index);
  const SteerableReport rep = f.trials(kTrials).run(devices, f.start());
  ASSERT_EQ(rep.counted(), kTrials);
  EXPECT_EQ(rep.errored(), 0);
  EXPECT_FALSE(rep.fault);
  const double p = rep.monte_carlo.rate();
  ASSERT_GT(p, 0.05);  // the wall makes the task uncertain, not hopeless
  ASSERT_LT(p, 0.98);
  const double rate = double(rep.successes()) / kTrials;
  EXPECT_NEAR(rate, p, kStandardErrors * std::sqrt(p * (1.0 - p) / kTrials));
  for (const SteerableTrialRecord& r : rep.records) {
    EXPECT_NE(r.outcome, SteerableOutcome::kError) << r.message;
    EXPECT_GE(r.steps, 1);
    // Ground truth: the policy saw the true tip at every decision.
    for (const SteerableDecision& d : r.decisions) {
      EXPECT_EQ(d.tipError_m(), 0.0);
    }
  }
  EXPECT_TRUE(rep.success());
}

TEST(SteerableTrials, AStoppedStepIsClassifiedByTheWorldAndTheRobot) {
  Fixture f;
  const std::pair<StepEnd, SteerableOutcome> cases[] = {
      {StepEnd::kObstacle, SteerableOutcome::kHitObstacle},
      {StepEnd::kJointLimit, SteerableOutcome::kNeedleLength},
      {StepEnd::kFailed, SteerableOutcome::kError},
  };
  for (const auto& [end, outcome] : cases) {
    FaultyDevices devices(f.needle, f.table, nullptr, nullptr, f.frame_index);
    devices.end = end;
    devices.fail_at_step = 2;
    const double delta_m = 2.0 * kPi * f.problem.params.radius_m / f.problem.params.orientations;
    const SteerableTrialRecord r = runSteerableTrial(
        devices, steering::ContinuousWorkspace(f.problem), delta_m, f.start().pose, 7, true, 40);
    EXPECT_EQ(r.outcome, outcome) << toString(outcome);
    EXPECT_EQ(r.steps, 3);
    EXPECT_EQ(r.message, "refused: the robot says so");
    ASSERT_FALSE(r.decisions.empty());
    EXPECT_FALSE(r.decisions.back().answered);  // the tip where it stopped
  }
}

TEST(SteerableTrials, AnAnswerWithoutAControlEndsTheTrialAsAnError) {
  Fixture f;
  FaultyDevices devices(f.needle, f.table, nullptr, nullptr, f.frame_index);
  devices.status = "invalid_tip";
  const SteerableReport rep = f.trials(3).run(devices, f.start());
  ASSERT_EQ(rep.records.size(), 3u);
  EXPECT_EQ(rep.errored(), 3);
  EXPECT_EQ(rep.counted(), 0);
  EXPECT_EQ(rep.records[0].steps, 0);  // no motion on an answer without a control
  EXPECT_NE(rep.records[0].message.find("invalid_tip"), std::string::npos);
  EXPECT_FALSE(rep.success());
}

TEST(SteerableTrials, ADeadNodeStopsTheRunAndTheReportNamesIt) {
  Fixture f;
  FaultyDevices devices(f.needle, f.table, nullptr, nullptr, f.frame_index);
  devices.die_after_controls = 12;  // dies in the second or a later trial
  const SteerableReport rep = f.trials(20).run(devices, f.start());
  ASSERT_TRUE(rep.fault);
  EXPECT_LT(rep.records.size(), 20u);
  EXPECT_EQ(rep.records.back().outcome, SteerableOutcome::kError);
  EXPECT_EQ(rep.errored(), 1);  // the trials before it are counted as they ended
  EXPECT_EQ(rep.counted(), static_cast<int>(rep.records.size()) - 1);
  EXPECT_FALSE(rep.success());
  EXPECT_EQ(f.needle.insertedLength_m(), 0.0);  // leaveSafe retracted the needle
  EXPECT_NE(rep.summaryJson().find("\"dead_node\": \"/steering_policy\""), std::string::npos);
  EXPECT_NE(rep.summaryJson().find("\"errored_trials\": 1"), std::string::npos);
}

TEST(SteerableTrials, TheReportWritesItsTablesAndFigures) {
  Fixture f;
  InProcessSteerableDevices devices(f.needle, f.table, nullptr, nullptr, f.frame_index);
  const SteerableReport rep = f.trials(4).run(devices, f.start());
  const std::filesystem::path dir =
      std::filesystem::temp_directory_path() / "ng_steerable_report_test";
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  rep.write(dir.string());
  for (const char* name :
       {"trials.csv", "paths.csv", "decisions.csv", "ps_map.csv", "obstacles.csv", "summary.json",
        "summary.md", "paths.png", "ps_map.png"}) {
    EXPECT_GT(std::filesystem::file_size(dir / name), 100u) << name;
  }
  std::ifstream trials(dir / "trials.csv");
  std::string line;
  int rows = -1;  // header
  while (std::getline(trials, line)) {
    ++rows;
  }
  EXPECT_EQ(rows, 4);
}

TEST(SteerableTrials, EachTableThatAnsweredPredictsItsOwnTrials) {
  Fixture f;
  InProcessSteerableDevices devices(f.needle, f.table, nullptr, nullptr, f.frame_index);
  SteerableReport rep = f.trials(4).run(devices, f.start());
  // In-process answers do not name a noise: no trial has one.
  std::vector<int> index;
  EXPECT_TRUE(rep.trialNoises(index).empty());
  const steering::TrialNoise scene_noise{f.problem.params.sigma_insert_rad,
                                         f.problem.params.sigma_flip_rad};
  rep.records[1].noise = scene_noise;
  rep.records[3].noise = scene_noise;
  ASSERT_EQ(rep.trialNoises(index).size(), 2u);
  EXPECT_EQ(index, (std::vector<int>{1, 3}));
  auto source = std::make_shared<steering::PolicySource>();
  source->model = std::make_unique<const steering::SteeringModel>(f.problem);
  source->table = std::make_unique<const steering::PolicyTable>(f.table);
  rep.addTablesUsed({steering::TableUsed{scene_noise, {0, 1}, source}}, index);
  ASSERT_EQ(rep.tables.size(), 1u);
  EXPECT_EQ(rep.tables[0].trials, (std::vector<int>{1, 3}));  // mapped back to the records
  EXPECT_EQ(rep.tables[0].predicted_ps, f.start().predicted_ps);
  // The scene's own table in the scene's world: the same seeded Monte Carlo as the headline.
  EXPECT_EQ(rep.tables[0].monte_carlo.successes, rep.monte_carlo.successes);
  EXPECT_NE(rep.summaryJson().find("\"tables_used\": [{\"sigma_insert_deg\": 5"), std::string::npos)
      << rep.summaryJson();
}

TEST(SteerableTrials, TheReportsMonteCarloResolvesTheTolerance) {
  // 1.96 SE <= tolerance / 2 at the P_s: n = ceil(1.96^2 p (1 - p) / (tolerance / 2)^2).
  EXPECT_EQ(SteerableTrials::monteCarloTrials(0.5, 0.01), 38415);
  EXPECT_EQ(SteerableTrials::monteCarloTrials(0.58, 0.005), 149725);
  // Never fewer than the minimum (a P_s near 1 needs few), never more than the limit.
  EXPECT_EQ(SteerableTrials::monteCarloTrials(0.999, 0.01), SteerableTrials::kMinMonteCarloTrials);
  EXPECT_EQ(SteerableTrials::monteCarloTrials(0.5, 0.001), SteerableTrials::kMaxMonteCarloTrials);
}

TEST(SteerableTrials, BadSettingsAreRefused) {
  Fixture f;
  SteerableSettings s;
  s.trials = 0;
  EXPECT_THROW(SteerableTrials("wall", f.problem, f.table, f.starts, s), std::invalid_argument);
  s.trials = 1;
  s.max_steps = 0;
  EXPECT_THROW(SteerableTrials("wall", f.problem, f.table, f.starts, s), std::invalid_argument);
}

}  // namespace
}  // namespace needle_guidance::procedures

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
