// The shortest-path baseline (dissertation 5.1, 5.5): the OMPL plan in the
// continuous world and the breadth-first steps-to-go table on the MDP's grid.
//
// Two independent references check the OMPL plan:
//   - an exhaustive search in this file (iterative deepening over the 2^n control sequences,
//     pruned by the chord lower bound): the exact fewest steps in the continuous world, cheap
//     here because the bound prunes almost everything;
//   - the BFS table (shortest_path.h), which works on the grid of 5.4.2. Its step count may
//     differ from the continuous one by one step: the grid rounds the start and every control-
//     circle point to the nearest grid point, so its tip drifts from the true arc by up to
//     Delta sqrt(2) per direction change (5.4.2, E_h), enough to gain or lose the last step into
//     a 5 mm target. In narrow gaps the drift can also open or close a passage altogether.
//
// OMPL runs under an iteration budget (with a generous time limit as a safety net), so every plan
// here depends on the seed only, not on the speed of the machine.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/math.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/shortest_path.h"
#include "needle_guidance/steering/steering_model.h"
#include "needle_guidance/steering/value_iteration.h"

#include "../steering_shapes.h"

namespace needle_guidance::steering {
namespace {

constexpr double kDeg = kPi / 180.0;
/// End pose of a plan inside the target disc [m].
constexpr double kInTargetTol_m = 1e-9;
/// A re-traced pose against the plan's own (same arithmetic) [m] / [rad].
constexpr double kReplayTol_m = 1e-12;
constexpr double kReplayTol_rad = 1e-12;
/// |continuous steps - grid steps| allowed: grid rounding of the start and of the arcs (5.4.2).
constexpr int kGridRoundingSteps = 1;
/// Planner budget: SST matched the exhaustive optimum on all 70 entry-line starts of the open
/// workspace with 50,000 iterations (with 20,000, three were one step long).
constexpr std::uint64_t kIterations = 50000;
/// Safety net only: the iteration budget ends every solvable plan first (~0.2 s) [s].
constexpr double kSafetyTimeLimit_s = 20.0;
/// Budget for problems with no solution, and the slack allowed beyond it (set-up, tear-down) [s].
constexpr double kUnreachableTimeLimit_s = 0.5;
constexpr double kTimeSlack_s = 0.5;
/// A refused start must not start the planner at all [s].
constexpr double kRefuseTime_s = 0.05;
/// Monte Carlo trials per policy on the real scene (10,000) and the seed.
constexpr std::int64_t kSceneTrials = 10000;
constexpr std::uint64_t kMonteCarloSeed = 20070501;
/// Deepest exhaustive search [steps].
constexpr int kExhaustiveDepth = 20;

using test_shapes::obstacle;
using test_shapes::openProblem;  // Delta = 1 mm, sigma = 0
using test_shapes::rect;

/// A wall at x = 40..50 mm over the full height with a gap at y = 47..53 mm: 4 mm wide after the
/// 1 mm clearance, like the channel of the real scene.
SteeringProblem gapProblem() {
  SteeringProblem p = openProblem();
  p.obstacles.push_back(obstacle("wall_low", rect(0.04, -0.01, 0.05, 0.047), 1e-3));
  p.obstacles.push_back(obstacle("wall_high", rect(0.04, 0.053, 0.05, 0.11), 1e-3));
  return p;
}

TipPose pose(double x_m, double y_m, double theta_rad, Bevel bevel = Bevel::kLeft) {
  TipPose t;
  t.p_SceneTip = Point2(x_m, y_m);
  t.theta_rad = theta_rad;
  t.bevel = bevel;
  return t;
}

ShortestPathOptions budget(std::uint32_t seed = 1) {
  ShortestPathOptions o;
  o.time_limit_s = kSafetyTimeLimit_s;
  o.max_iterations = kIterations;
  o.seed = seed;
  return o;
}

double deltaOf(const SteeringProblem& p) {
  return 2.0 * kPi * p.params.radius_m / p.params.orientations;
}

/// The exact fewest steps from `start` into the target disc in the continuous world (-1 if none
/// within max_depth): iterative deepening over both controls, cut where even straight chords of
/// 2 r sin(pi / N_c) could not reach the disc in the steps left.
class ExhaustiveSearch {
public:
  explicit ExhaustiveSearch(const ContinuousWorkspace& world)
      : world_(world),
        delta_m_(deltaOf(world.problem())),
        chord_m_(2.0 * world.problem().params.radius_m *
                 std::sin(kPi / world.problem().params.orientations)) {}

  int fewestSteps(const TipPose& start, int max_depth) {
    for (int depth = 0; depth <= max_depth; ++depth) {
      if (reaches(start, depth)) {
        return depth;
      }
    }
    return -1;
  }

private:
  bool reaches(const TipPose& p, int steps_left) {
    if (world_.inTarget(p.p_SceneTip)) {
      return true;
    }
    const scene::Target& t = world_.problem().target;
    if (steps_left == 0 ||
        (p.p_SceneTip - t.position).norm() - t.radius_m > steps_left * chord_m_ + 1e-12) {
      return false;
    }
    for (Control u : {Control::kInsert, Control::kFlip}) {
      if (world_.traceArc(p, u, 0.0, delta_m_).outcome == ArcOutcome::kFree &&
          reaches(advanceTip(p, u, 0.0, delta_m_, world_.problem().params.radius_m),
                  steps_left - 1)) {
        return true;
      }
    }
    return false;
  }

  const ContinuousWorkspace& world_;
  double delta_m_;
  double chord_m_;
};

/// Checks a found plan against the world: pose count, start, every arc free and ending at the
/// next pose, the last pose in the disc, the length, nothing NaN.
void expectConsistentPlan(const ContinuousWorkspace& world, const TipPose& start,
                          const ShortestPath& plan) {
  const SteeringProblem& p = world.problem();
  const double delta_m = deltaOf(p);
  ASSERT_TRUE(plan.found) << plan.message;
  EXPECT_TRUE(plan.message.empty());
  ASSERT_EQ(plan.steps, static_cast<int>(plan.controls.size()));
  ASSERT_EQ(plan.poses.size(), plan.controls.size() + 1);
  EXPECT_NEAR((plan.poses.front().p_SceneTip - start.p_SceneTip).norm(), 0.0, kReplayTol_m);
  EXPECT_EQ(plan.poses.front().bevel, start.bevel);
  EXPECT_NEAR(plan.length_m, plan.steps * delta_m, kReplayTol_m);
  EXPECT_GE(plan.steps, plan.lower_bound_steps);
  EXPECT_EQ(plan.proven_shortest, plan.steps == plan.lower_bound_steps);
  for (std::size_t i = 0; i < plan.controls.size(); ++i) {
    const TipPose& from = plan.poses[i];
    ASSERT_TRUE(from.p_SceneTip.allFinite() && std::isfinite(from.theta_rad)) << "pose " << i;
    const ArcTrace arc = world.traceArc(from, plan.controls[i], 0.0, delta_m);
    EXPECT_EQ(arc.outcome, ArcOutcome::kFree) << "step " << i << ": " << toString(arc.outcome);
    const TipPose& to = plan.poses[i + 1];
    EXPECT_NEAR((arc.end.p_SceneTip - to.p_SceneTip).norm(), 0.0, kReplayTol_m) << "step " << i;
    EXPECT_NEAR(std::remainder(arc.end.theta_rad - to.theta_rad, 2.0 * kPi), 0.0, kReplayTol_rad);
    EXPECT_EQ(to.bevel, plan.controls[i] == Control::kFlip ? flipped(from.bevel) : from.bevel);
    EXPECT_GT(to.theta_rad, -kPi);
    EXPECT_LE(to.theta_rad, kPi);
  }
  const Point2 end = plan.poses.back().p_SceneTip;
  EXPECT_LE((end - p.target.position).norm(), p.target.radius_m + kInTargetTol_m);
}

// ---- the OMPL plan ---------------------------------------------------------------------------

TEST(ShortestPathPlanTest, OpenWorkspaceReachesTheTargetAndAgreesWithTwoReferences) {
  const SteeringProblem problem = openProblem();
  const ContinuousWorkspace world(problem);
  const TipPose start = pose(0.0, 0.05, 0.0);
  const ShortestPath plan = planShortestPath(world, start, budget());
  expectConsistentPlan(world, start, plan);
  std::printf("[ open       ] %s\n", plan.toString().c_str());

  ExhaustiveSearch exact(world);
  EXPECT_EQ(plan.steps, exact.fewestSteps(start, kExhaustiveDepth));

  const ShortestPathTable table = ShortestPathTable::fromProblem(problem);
  const ShortestPathLookup grid = table.lookup(start);  // the start is a grid point, theta = 0
  ASSERT_TRUE(grid) << grid.toString();
  EXPECT_NEAR(plan.steps, grid.steps_to_go, kGridRoundingSteps)
      << "OMPL " << plan.steps << " steps, grid BFS " << grid.steps_to_go;
}

TEST(ShortestPathPlanTest, MatchesTheExhaustiveOptimumAlongTheEntryLine) {
  const SteeringProblem problem = openProblem();
  const ContinuousWorkspace world(problem);
  const ShortestPathTable table = ShortestPathTable::fromProblem(problem);
  ExhaustiveSearch exact(world);
  int planned = 0, off_grid_by_one = 0, unreachable = 0, grid_unreachable = 0;
  for (int y_mm = 10; y_mm <= 90; y_mm += 10) {
    for (int k : {-8, -4, 0, 4, 8}) {  // theta = k alpha, within +-72 degrees
      const TipPose start = pose(0.0, y_mm * 1e-3, k * 2.0 * kPi / 40.0);
      SCOPED_TRACE("start y = " + std::to_string(y_mm) + " mm, k = " + std::to_string(k));
      const int optimum = exact.fewestSteps(start, kExhaustiveDepth);
      if (optimum < 0) {
        ++unreachable;  // steep towards a near edge: no turn of r = 5 cm fits (SST would spend
        continue;       // its whole budget; the enclosed-target test covers that case)
      }
      const ShortestPath plan = planShortestPath(world, start, budget());
      expectConsistentPlan(world, start, plan);
      EXPECT_EQ(plan.steps, optimum) << plan.toString();
      ++planned;
      const ShortestPathLookup grid = table.lookup(start);
      if (!grid) {
        ++grid_unreachable;  // the grid's drift closes a marginal path (see the top of the file)
        continue;
      }
      EXPECT_NEAR(plan.steps, grid.steps_to_go, kGridRoundingSteps);
      off_grid_by_one += plan.steps != grid.steps_to_go ? 1 : 0;
    }
  }
  EXPECT_GE(planned, 30);
  EXPECT_LE(grid_unreachable, planned / 10);
  std::printf(
      "[ entry line ] %d starts (%d unreachable skipped): OMPL = exhaustive optimum; grid "
      "BFS one step off on %d, no grid path on %d\n",
      planned, unreachable, off_grid_by_one, grid_unreachable);
}

TEST(ShortestPathPlanTest, NarrowGapIsThreadedAndTheOpenLoopPlanSucceedsWithoutNoise) {
  const SteeringProblem problem = gapProblem();
  const ContinuousWorkspace world(problem);
  const TipPose start = pose(0.0, 0.05, 0.0);
  const ShortestPath plan = planShortestPath(world, start, budget());
  expectConsistentPlan(world, start, plan);
  std::printf("[ gap        ] %s\n", plan.toString().c_str());
  ExhaustiveSearch exact(world);
  EXPECT_EQ(plan.steps, exact.fewestSteps(start, kExhaustiveDepth));
  // The wall spans the whole height, so the path must cross x = 40..50 mm inside the cleared gap.
  const double delta_m = deltaOf(problem);
  int samples_in_wall_range = 0;
  for (std::size_t i = 0; i < plan.controls.size(); ++i) {
    for (int j = 0; j <= 20; ++j) {
      const Point2 q = advanceTip(plan.poses[i], plan.controls[i], 0.0, delta_m * j / 20.0,
                                  problem.params.radius_m)
                           .p_SceneTip;
      if (q.x() >= 0.039 && q.x() <= 0.051) {
        ++samples_in_wall_range;
        EXPECT_GT(q.y(), 0.048);
        EXPECT_LT(q.y(), 0.052);
      }
    }
  }
  EXPECT_GT(samples_in_wall_range, 0);

  // Executed open-loop by the Monte Carlo simulator at sigma = 0: always the same success.
  const MonteCarloResult noiseless =
      runMonteCarlo(world, start, openLoopPolicy(plan.controls), 20, kMonteCarloSeed);
  EXPECT_EQ(noiseless.rate(), 1.0);
  TrialOptions record;
  record.record_path = true;
  const Trial trial = simulateTrial(world, start, openLoopPolicy(plan.controls), 1, record);
  ASSERT_TRUE(trial.success()) << toString(trial.outcome);
  ASSERT_EQ(trial.path.size(), plan.poses.size());
  for (std::size_t i = 0; i < trial.path.size(); ++i) {
    EXPECT_NEAR((trial.path[i].p_SceneTip - plan.poses[i].p_SceneTip).norm(), 0.0, kReplayTol_m);
  }

  // With the real scene's noise (sigma_i = 5, sigma_r = 10 degrees) the same plan often fails:
  // the reason for the MDP (5.1).
  SteeringProblem noisy = problem;
  noisy.params.sigma_insert_rad = 5 * kDeg;
  noisy.params.sigma_flip_rad = 10 * kDeg;
  const MonteCarloResult mc = runMonteCarlo(ContinuousWorkspace(noisy), start,
                                            openLoopPolicy(plan.controls), 2000, kMonteCarloSeed);
  std::printf("[ gap        ] open loop under sigma = 5/10 deg: P_s = %.3f [%.3f, %.3f]\n",
              mc.rate(), mc.interval().low, mc.interval().high);
  EXPECT_LT(mc.interval().high, 1.0);

  // The grid's view of the same start, for the record: its rounding may close the 4 mm gap.
  std::printf("[ gap        ] grid BFS from the same start: %s\n",
              ShortestPathTable::fromProblem(problem).lookup(start).toString().c_str());
}

TEST(ShortestPathPlanTest, EnclosedTargetIsNotFoundWithinTheTimeLimit) {
  // Four walls box the target in (0.5 mm clearance); nothing outside the box can get in.
  SteeringProblem problem = openProblem();
  problem.obstacles.push_back(obstacle("box_left", rect(0.072, 0.035, 0.074, 0.065), 5e-4));
  problem.obstacles.push_back(obstacle("box_right", rect(0.096, 0.035, 0.098, 0.065), 5e-4));
  problem.obstacles.push_back(obstacle("box_bottom", rect(0.072, 0.035, 0.098, 0.037), 5e-4));
  problem.obstacles.push_back(obstacle("box_top", rect(0.072, 0.063, 0.098, 0.065), 5e-4));
  const ContinuousWorkspace world(problem);
  const TipPose start = pose(0.0, 0.05, 0.0);
  ShortestPathOptions options;
  options.time_limit_s = kUnreachableTimeLimit_s;
  const ShortestPath plan = planShortestPath(world, start, options);
  EXPECT_FALSE(plan.found);
  EXPECT_NE(plan.message.find("no path"), std::string::npos) << plan.message;
  EXPECT_TRUE(plan.controls.empty());
  EXPECT_TRUE(plan.poses.empty());
  EXPECT_EQ(plan.steps, 0);
  EXPECT_LE(plan.seconds, kUnreachableTimeLimit_s + kTimeSlack_s);
  EXPECT_GT(plan.iterations, 0u);
  std::printf("[ enclosed   ] %s\n", plan.message.c_str());

  const ShortestPathTable table = ShortestPathTable::fromProblem(problem);
  const GridSpec& g = table.grid();
  for (int ix = 0; ix < g.nx; ++ix) {
    for (int iy = 0; iy < g.ny; ++iy) {
      const Point2 q = g.point(ix, iy);
      if (q.x() > 0.0715 && q.x() < 0.0985 && q.y() > 0.0345 && q.y() < 0.0655) {
        continue;  // inside the box (walls included)
      }
      for (StateId s = g.position(ix, iy) * 2 * g.nc; s < (g.position(ix, iy) + 1) * 2 * g.nc;
           ++s) {
        ASSERT_EQ(table.stepsToGo(s), -1) << "state " << s;
        ASSERT_EQ(table.control(s), Control::kInsert);
      }
    }
  }
  const ShortestPathLookup l = table.lookup(start);
  EXPECT_EQ(l.status, ShortestPathLookup::Status::kUnreachable);
  EXPECT_EQ(l.steps_to_go, -1);
  EXPECT_EQ(l.control, Control::kInsert);
  EXPECT_EQ(shortestPathPolicy(table)(start, 0), Control::kInsert);
}

TEST(ShortestPathPlanTest, TargetInsideAnObstacleIsUnreachableEverywhere) {
  SteeringProblem problem = openProblem();
  problem.obstacles.push_back(obstacle("tumour_wall", rect(0.075, 0.04, 0.095, 0.06), 1e-3));
  const ContinuousWorkspace world(problem);
  ShortestPathOptions options;
  options.time_limit_s = kUnreachableTimeLimit_s;
  const ShortestPath plan = planShortestPath(world, pose(0.0, 0.05, 0.0), options);
  EXPECT_FALSE(plan.found);
  EXPECT_FALSE(plan.message.empty());
  EXPECT_LE(plan.seconds, kUnreachableTimeLimit_s + kTimeSlack_s);

  const ShortestPathTable table = ShortestPathTable::fromProblem(problem);
  EXPECT_EQ(table.reachableStates(), 0);
  EXPECT_EQ(table.maxStepsToGo(), 0);
  for (StateId s = 0; s < table.grid().numStates(); ++s) {
    ASSERT_EQ(table.stepsToGo(s), -1) << s;  // not even a target cell: all lie in the obstacle
  }
}

TEST(ShortestPathPlanTest, BadStartsAreRefusedWithAMessage) {
  SteeringProblem problem = openProblem();
  problem.obstacles.push_back(obstacle("entry_block", rect(-0.01, -0.01, 0.01, 0.03), 1e-3));
  const ContinuousWorkspace world(problem);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  struct Case {
    TipPose start;
    std::string expected;  // in the message
  };
  const std::vector<Case> cases = {
      {pose(0.0, 0.02, 0.0), "entry_block"},      // inside the expanded obstacle
      {pose(0.005, 0.0305, 0.0), "entry_block"},  // in its 1 mm clearance only
      {pose(-0.01, 0.05, 0.0), "outside the workspace"},
      {pose(0.02, 0.2, 0.0), "outside the workspace"},
      {pose(nan, 0.05, 0.0), "not finite"},
      {pose(0.0, inf, 0.0), "not finite"},
      {pose(0.0, 0.05, nan), "not finite"},
  };
  for (const Case& c : cases) {
    const ShortestPath plan = planShortestPath(world, c.start, budget());
    EXPECT_FALSE(plan.found) << c.expected;
    EXPECT_FALSE(static_cast<bool>(plan));
    EXPECT_NE(plan.message.find(c.expected), std::string::npos) << plan.message;
    EXPECT_EQ(plan.toString(), plan.message);
    EXPECT_TRUE(plan.controls.empty());
    EXPECT_TRUE(plan.poses.empty());
    EXPECT_EQ(plan.iterations, 0u);  // refused before planning
    EXPECT_LT(plan.seconds, kRefuseTime_s);
    EXPECT_TRUE(std::isfinite(plan.length_m));
  }
}

TEST(ShortestPathPlanTest, StartInTheTargetIsZeroSteps) {
  const ContinuousWorkspace world(openProblem());
  const TipPose start = pose(0.087, 0.051, 1.0, Bevel::kRight);
  const ShortestPath plan = planShortestPath(world, start, budget());
  ASSERT_TRUE(plan.found) << plan.message;
  EXPECT_EQ(plan.steps, 0);
  EXPECT_TRUE(plan.controls.empty());
  ASSERT_EQ(plan.poses.size(), 1u);
  EXPECT_EQ(plan.poses.front().bevel, Bevel::kRight);
  EXPECT_TRUE(plan.proven_shortest);
  EXPECT_EQ(plan.length_m, 0.0);
}

TEST(ShortestPathPlanTest, NonsenseOptionsThrowAndATooShortStepLimitIsAStatus) {
  const ContinuousWorkspace world(openProblem());
  const TipPose start = pose(0.0, 0.05, 0.0);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (double t : {0.0, -1.0, nan, std::numeric_limits<double>::infinity()}) {
    ShortestPathOptions o;
    o.time_limit_s = t;
    EXPECT_THROW(planShortestPath(world, start, o), std::invalid_argument) << t;
  }
  ShortestPathOptions o;
  o.seed = 0;
  EXPECT_THROW(planShortestPath(world, start, o), std::invalid_argument);
  o = {};
  o.max_steps = 0;
  EXPECT_THROW(planShortestPath(world, start, o), std::invalid_argument);
  o = {};
  o.pruning_radius_m = -1e-3;
  EXPECT_THROW(planShortestPath(world, start, o), std::invalid_argument);
  o = {};
  o.selection_radius_m = nan;
  EXPECT_THROW(planShortestPath(world, start, o), std::invalid_argument);
  o = {};
  o.goal_bias = 1.5;
  EXPECT_THROW(planShortestPath(world, start, o), std::invalid_argument);
  // The target is 80 mm = at least 11 chords of 7.85 mm away: a limit of 10 steps cannot be met.
  o = budget();
  o.max_steps = 10;
  const ShortestPath plan = planShortestPath(world, start, o);
  EXPECT_FALSE(plan.found);
  EXPECT_NE(plan.message.find("max_steps"), std::string::npos) << plan.message;
}

TEST(ShortestPathPlanTest, SameSeedAndIterationBudgetGiveTheSamePlan) {
  const ContinuousWorkspace world(openProblem());
  // Facing 54 degrees up: the shortest path (12 steps) is longer than the bound (11), so SST
  // uses its whole budget rather than stopping at a proven optimum.
  const TipPose start = pose(0.0, 0.05, 54 * kDeg);
  ShortestPathOptions o = budget(7);
  o.max_iterations = 20000;
  const ShortestPath a = planShortestPath(world, start, o);
  const ShortestPath b = planShortestPath(world, start, o);
  ASSERT_TRUE(a.found) << a.message;
  ASSERT_TRUE(b.found) << b.message;
  EXPECT_FALSE(a.proven_shortest);
  EXPECT_EQ(a.iterations, o.max_iterations);
  EXPECT_EQ(a.controls, b.controls);
  EXPECT_EQ(a.iterations, b.iterations);
}

// ---- the steps-to-go table -------------------------------------------------------------------

TEST(ShortestPathTableTest, AgreesWithValueIterationAndTheBellmanEquationAtSigmaZero) {
  SteeringProblem problem =
      test_shapes::dissertation(problemFromScene(scene::loadSceneSpec("steering_workspace")));
  problem.params.grid_spacing_m = 2e-3;
  problem.params.sigma_insert_rad = 0.0;
  problem.params.sigma_flip_rad = 0.0;
  const SteeringModel model(problem);
  const ShortestPathTable table(model);
  const PolicyTable vi = solveValueIteration(model);
  const GridSpec& g = model.grid();
  ASSERT_GT(table.reachableStates(), 0);
  std::int64_t reachable = 0;
  for (StateId s = 0; s < model.numStates(); ++s) {
    const std::int64_t position = s / (2 * std::int64_t{g.nc});
    const int steps = table.stepsToGo(s);
    // Two methods, one answer: reachable by BFS <=> P_s = 1 by value iteration at sigma = 0.
    ASSERT_EQ(steps >= 0, vi.value(s) == 1.0f) << "state " << s;
    if (model.cell(position) == Cell::kTarget) {
      ASSERT_EQ(steps, 0);
      continue;
    }
    // At sigma = 0 both bevels of a pose have the same two successors (insert with one is flip
    // with the other), so the same steps-to-go, and mirrored controls unless both tie.
    int ix = 0, iy = 0, k = 0;
    Bevel b = Bevel::kLeft;
    g.decode(s, ix, iy, k, b);
    const StateId twin = g.state(ix, iy, k, flipped(b));
    ASSERT_EQ(steps, table.stepsToGo(twin)) << "state " << s;
    if (steps <= 0) {
      ASSERT_EQ(table.control(s), Control::kInsert);
      continue;
    }
    ++reachable;
    // Bellman: steps = 1 + min over controls of the successor's steps, the stored control
    // attains it, and a tie keeps insert.
    int to_go[2];
    for (int u = 0; u < 2; ++u) {
      const auto next = model.successors(s, static_cast<Control>(u));
      ASSERT_EQ(next.size(), 1u);
      const int t = next.front().next == kFailState ? -1 : table.stepsToGo(next.front().next);
      to_go[u] = t < 0 ? std::numeric_limits<int>::max() : t;
    }
    ASSERT_EQ(steps, 1 + std::min(to_go[0], to_go[1])) << "state " << s;
    ASSERT_EQ(table.control(s), to_go[1] < to_go[0] ? Control::kFlip : Control::kInsert);
    if (to_go[0] != to_go[1]) {
      ASSERT_NE(table.control(s), table.control(twin));
    }
  }
  EXPECT_EQ(reachable, table.reachableStates());
  std::printf("[ table 2 mm ] %lld of %lld states reach the target, at most %d steps; BFS %.3f s\n",
              static_cast<long long>(table.reachableStates()),
              static_cast<long long>(model.numStates()), table.maxStepsToGo(),
              table.buildSeconds());
}

TEST(ShortestPathTableTest, RefusesANoisyModelAndLooksUpEveryStatus) {
  SteeringProblem noisy = openProblem();
  noisy.params.grid_spacing_m = 2e-3;
  noisy.params.sigma_insert_rad = 5 * kDeg;
  noisy.params.sigma_flip_rad = 10 * kDeg;
  EXPECT_THROW(ShortestPathTable{SteeringModel(noisy)}, std::invalid_argument);

  SteeringProblem problem = noisy;  // fromProblem zeroes the sigmas
  problem.obstacles.push_back(obstacle("block", rect(0.04, 0.07, 0.05, 0.08), 1e-3));
  const ShortestPathTable table = ShortestPathTable::fromProblem(problem);
  using Status = ShortestPathLookup::Status;
  const double nan = std::numeric_limits<double>::quiet_NaN();

  const ShortestPathLookup off = table.lookup(pose(-0.01, 0.05, 0.0));
  EXPECT_EQ(off.status, Status::kOutsideGrid);
  EXPECT_EQ(off.state, -1);
  EXPECT_FALSE(off);
  EXPECT_EQ(table.lookup(pose(nan, 0.05, 0.0)).status, Status::kOutsideGrid);
  EXPECT_EQ(table.lookup(pose(0.01, 0.05, nan)).status, Status::kOutsideGrid);

  const ShortestPathLookup in_target = table.lookup(pose(0.085, 0.05, 0.3));
  EXPECT_EQ(in_target.status, Status::kInTarget);
  EXPECT_EQ(in_target.steps_to_go, 0);
  EXPECT_EQ(in_target.toString(), "in target");

  const ShortestPathLookup in_obstacle = table.lookup(pose(0.045, 0.075, 0.0));
  EXPECT_EQ(in_obstacle.status, Status::kInObstacle);
  EXPECT_EQ(in_obstacle.steps_to_go, -1);

  // At the right edge facing +x every arc leaves the workspace.
  const ShortestPathLookup stuck = table.lookup(pose(0.098, 0.05, 0.0));
  EXPECT_EQ(stuck.status, Status::kUnreachable);
  EXPECT_EQ(stuck.control, Control::kInsert);
  EXPECT_EQ(stuck.toString(), "unreachable");

  // 6 mm above the floor heading 18 degrees down: bevel right (clockwise) would turn further
  // down and leave the workspace, so it must flip; bevel left just inserts.
  const TipPose low_right = pose(0.02, 0.006, -18 * kDeg, Bevel::kRight);
  const TipPose low_left = pose(0.02, 0.006, -18 * kDeg, Bevel::kLeft);
  const ShortestPathLookup ok = table.lookup(low_right);
  ASSERT_TRUE(ok) << ok.toString();
  EXPECT_GT(ok.steps_to_go, 0);
  EXPECT_EQ(ok.steps_to_go, table.stepsToGo(ok.state));
  EXPECT_EQ(ok.control, Control::kFlip);
  EXPECT_NE(ok.toString().find("flip"), std::string::npos) << ok.toString();

  const SteeringPolicy policy = shortestPathPolicy(table);
  EXPECT_EQ(table.lookup(low_left).steps_to_go, ok.steps_to_go);
  EXPECT_EQ(policy(low_right, 3), Control::kFlip);
  EXPECT_EQ(policy(low_left, 3), Control::kInsert);
  EXPECT_EQ(policy(pose(-0.01, 0.05, 0.0), 0), Control::kInsert);
  EXPECT_EQ(policy(pose(0.045, 0.075, 0.0), 0), Control::kInsert);
}

// The closed-loop table policy in the continuous world without noise. It is exact on the grid,
// but the true tip drifts from the grid path (5.4.2: up to Delta / sqrt 2 from rounding the imaged
// tip, Delta sqrt 2 per direction change), so now and then a path that the grid sees ending on a
// target cell at the disc's edge, or skimming the workspace edge, misses in the continuous world
// (most of the misses measured pass within a millimetre of the disc), and the needle, unable to
// turn back within r = 5 cm, leaves the workspace. Measured: 494 of 528 entry-line states
// succeed. The MDP's tablePolicy shares the grid and this effect.
TEST(ShortestPathTableTest, ClosedLoopPolicyReachesTheTargetWithoutNoise) {
  const SteeringProblem problem = openProblem();
  const ContinuousWorkspace world(problem);
  const ShortestPathTable table = ShortestPathTable::fromProblem(problem);
  const SteeringPolicy policy = shortestPathPolicy(table);
  constexpr double kMinSuccessFraction = 0.9;
  int starts = 0, successes = 0;
  for (int y_mm = 5; y_mm <= 95; y_mm += 5) {
    for (int k = -8; k <= 8; ++k) {
      for (Bevel b : {Bevel::kLeft, Bevel::kRight}) {
        const TipPose start = pose(0.0, y_mm * 1e-3, k * 2.0 * kPi / 40.0, b);
        const ShortestPathLookup l = table.lookup(start);
        if (!l) {
          continue;
        }
        ++starts;
        const Trial trial = simulateTrial(world, start, policy, 1);
        if (trial.success()) {
          ++successes;
          EXPECT_NEAR(trial.steps, l.steps_to_go, kGridRoundingSteps)
              << "y = " << y_mm << " mm, k = " << k << ", bevel " << toString(b);
        } else {
          EXPECT_EQ(trial.outcome, TrialOutcome::kLeftWorkspace);  // there are no obstacles
        }
      }
    }
  }
  ASSERT_GT(starts, 400);
  std::printf("[ closed loop] sigma = 0: %d of %d entry-line states reach the target\n", successes,
              starts);
  EXPECT_GE(successes, kMinSuccessFraction * starts);
  // The straight-ahead start is one that works, in exactly the grid's step count or one more.
  const Trial straight = simulateTrial(world, pose(0.0, 0.05, 0.0), policy, 1);
  EXPECT_TRUE(straight.success()) << toString(straight.outcome);
}

// ---- the real scene --------------------------------------------------------------------------

TEST(ShortestPathSceneTest, BaselinesAgainstTheMdpOnTheSteeringWorkspace) {
  const scene::Scene scene = scene::loadSceneSpec("steering_workspace");
  const SteeringProblem problem = test_shapes::dissertation(problemFromScene(scene));
  const SteeringModel model(problem);
  ASSERT_EQ(model.numStates(), 800000);  // 5.5: N = 800,000
  const PolicyTable mdp = solveValueIteration(model);
  const BestStart best = mdp.bestStart(startOptionsFromScene(scene));
  ASSERT_TRUE(best) << best.toString();
  const TipPose start = best.best.pose;
  std::printf("[ scene      ] MDP %s\n", best.toString().c_str());

  const ContinuousWorkspace world(problem);
  ShortestPathOptions options = budget();
  options.max_iterations = 2 * kIterations;
  const ShortestPath plan = planShortestPath(world, start, options);
  expectConsistentPlan(world, start, plan);
  std::printf("[ scene      ] OMPL SST: %s\n", plan.toString().c_str());
  ExhaustiveSearch exact(world);
  EXPECT_EQ(plan.steps, exact.fewestSteps(start, kExhaustiveDepth));

  const ShortestPathTable table = ShortestPathTable::fromProblem(problem);
  const ShortestPathLookup grid = table.lookup(start);
  std::printf("[ scene      ] BFS table over %lld states: %.3f s; at the start: %s\n",
              static_cast<long long>(table.grid().numStates()), table.buildSeconds(),
              grid.toString().c_str());
  if (grid) {
    EXPECT_NEAR(plan.steps, grid.steps_to_go, kGridRoundingSteps);
  }

  // The same uncertainty for all three (sigma_i = 5, sigma_r = 10 degrees, tip imaged every
  // delta): the MDP policy, the shortest path re-planned from every image (closed loop), and the
  // shortest path executed blind (open loop).
  const MonteCarloResult mdp_mc =
      runMonteCarlo(world, start, tablePolicy(mdp), kSceneTrials, kMonteCarloSeed);
  const MonteCarloResult closed_mc =
      runMonteCarlo(world, start, shortestPathPolicy(table), kSceneTrials, kMonteCarloSeed);
  const MonteCarloResult open_mc =
      runMonteCarlo(world, start, openLoopPolicy(plan.controls), kSceneTrials, kMonteCarloSeed);
  auto report = [](const char* name, const MonteCarloResult& r) {
    std::printf("[ scene      ] %-28s P_s = %.4f [%.4f, %.4f], %.1f steps, %.1f flips\n", name,
                r.rate(), r.interval().low, r.interval().high, r.mean_steps, r.mean_flips);
  };
  report("MDP policy (closed loop)", mdp_mc);
  report("shortest path, closed loop", closed_mc);
  report("shortest path, open loop", open_mc);
  std::printf("[ scene      ] MDP gain over shortest path: x%.2f closed loop, x%.2f open loop\n",
              mdp_mc.rate() / std::max(closed_mc.rate(), 1e-12),
              mdp_mc.rate() / std::max(open_mc.rate(), 1e-12));
  // Dissertation 5.1: maximising P_s beats shortest paths under uncertainty. The 95 % intervals
  // must not overlap.
  EXPECT_GT(mdp_mc.interval().low, closed_mc.interval().high);
  EXPECT_GT(mdp_mc.interval().low, open_mc.interval().high);
}

}  // namespace
}  // namespace needle_guidance::steering

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
