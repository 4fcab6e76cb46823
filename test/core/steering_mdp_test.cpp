// Hard cases of the steerable-needle MDP solver (dissertation 5.4.3), and
// a problem small enough to solve by hand.
//
// Target inside an obstacle: not refused. The model reports it in diagnostics() and P_s is 0
// everywhere, so a node still has a defined (if useless) policy and says why; bestStart() then
// returns "not found" with a message.
#include <gtest/gtest.h>

#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/math.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/steering_model.h"
#include "needle_guidance/steering/value_iteration.h"

#include "../steering_shapes.h"

namespace needle_guidance::steering {
namespace {

constexpr double kDeg = kPi / 180.0;
constexpr double kValueTol = 1e-6;            // P_s stored as float, exact problems
constexpr double kResidualTol = 5e-3;         // Bellman residual after an epsilon = 1e-3 solve
constexpr double kThreadAgreementTol = 5e-3;  // P_s, 1 vs 2 threads (both within epsilon)
constexpr int kMaxRolloutSteps = 400;

using test_shapes::entryLine;
using test_shapes::obstacle;
using test_shapes::openProblem;
using test_shapes::rect;

double normalCdf(double z) {
  return 0.5 * std::erfc(-z / std::sqrt(2.0));
}

/// Follows the policy with sigma = 0 (one successor per control) from s; returns the states
/// visited, ending in a target cell, kFailState, or after kMaxRolloutSteps.
std::vector<StateId> rollout(const SteeringModel& m, const PolicyTable& t, StateId s) {
  std::vector<StateId> path{s};
  for (int i = 0; i < kMaxRolloutSteps; ++i) {
    const std::int64_t pos = s / (2 * m.grid().nc);
    if (m.cell(pos) != Cell::kFree)
      break;
    const auto next = m.successors(s, t.control(s));
    EXPECT_EQ(next.size(), 1u);
    s = next.front().next;
    path.push_back(s);
    if (s == kFailState)
      break;
  }
  return path;
}

bool endsInTarget(const SteeringModel& m, const std::vector<StateId>& path) {
  return path.back() != kFailState && m.cell(path.back() / (2 * m.grid().nc)) == Cell::kTarget;
}

// ---- solved by hand
// ------------------------------------------------------------------------------
//
// N_c = 4 (alpha = 90 degrees), r = Delta = 1 m, workspace [0, 2]^2: the grid is {0, 1}^2 and
// the rounded control-circle points are exact, so every arc is a quarter circle. Target: the
// disc of radius 0.25 m around (1, 1). From (0, 0) facing +x:
//   bevel left, insert: no deflection -> quarter circle to (1, 1) = target; d = +-1 -> the arc
//     leaves the workspace. Flip: only d = +1 (start tangent +y, traced clockwise) reaches (1, 1).
//   bevel right: the mirror image: insert reaches the target only with d = +1, flip with d = 0.
// With the tails folded (sigma = 20 and 30 degrees both give m = 1):
//   p0(sigma) = erf(45 / (sigma sqrt 2)),  p+1(sigma) = 1 - Phi(45 / sigma).
TEST(SteeringMdpTest, QuarterCircleProblemSolvedByHand) {
  SteeringProblem p;
  p.workspace_min = Point2(0.0, 0.0);
  p.workspace_max = Point2(2.0, 2.0);
  p.target.position = Point2(1.0, 1.0);
  p.target.radius_m = 0.25;
  p.params.grid_spacing_m = 1.0;
  p.params.orientations = 4;
  p.params.radius_m = 1.0;
  p.params.sigma_insert_rad = 20 * kDeg;
  p.params.sigma_flip_rad = 30 * kDeg;
  const SteeringModel m(p, 1);
  ASSERT_EQ(m.grid().nx, 2);
  ASSERT_EQ(m.grid().ny, 2);
  ASSERT_EQ(m.deflectionProbabilities(Control::kInsert).size(), 3u);
  ASSERT_EQ(m.deflectionProbabilities(Control::kFlip).size(), 3u);
  SolverOptions tight;
  tight.epsilon = 1e-9;
  const PolicyTable t = solveValueIteration(m, tight);

  const double p0_insert = std::erf(45.0 / (20.0 * std::sqrt(2.0)));
  const double p1_insert = 1.0 - normalCdf(45.0 / 20.0);
  const double p0_flip = std::erf(45.0 / (30.0 * std::sqrt(2.0)));
  const double p1_flip = 1.0 - normalCdf(45.0 / 30.0);
  const StateId left = m.grid().state(0, 0, 0, Bevel::kLeft);
  const StateId right = m.grid().state(0, 0, 0, Bevel::kRight);
  // Left: max(p0(sigma_i) = 0.976, p+1(sigma_r) = 0.067) -> insert.
  EXPECT_NEAR(t.value(left), std::max(p0_insert, p1_flip), kValueTol);
  EXPECT_EQ(t.control(left), Control::kInsert);
  // Right: max(p+1(sigma_i) = 0.012, p0(sigma_r) = 0.866) -> flip.
  EXPECT_NEAR(t.value(right), std::max(p1_insert, p0_flip), kValueTol);
  EXPECT_EQ(t.control(right), Control::kFlip);
  EXPECT_EQ(m.cell(m.grid().position(1, 1)), Cell::kTarget);
}

// ---- sigma = 0 ---------------------------------------------------------------------------------

TEST(SteeringMdpTest, DeterministicMotionGivesZeroOrOne) {
  SteeringProblem p =
      test_shapes::dissertation(problemFromScene(scene::loadSceneSpec("steering_workspace")));
  p.params.grid_spacing_m = 2e-3;
  p.params.sigma_insert_rad = 0.0;
  p.params.sigma_flip_rad = 0.0;
  const SteeringModel m(p);
  const PolicyTable t = solveValueIteration(m);
  std::int64_t ones = 0;
  for (float v : t.values()) {
    ASSERT_TRUE(v == 0.0f || v == 1.0f) << v;
    ones += v == 1.0f ? 1 : 0;
  }
  EXPECT_GT(ones, 0);
  const BestStart best = t.bestStart(entryLine());
  ASSERT_TRUE(best) << best.toString();
  EXPECT_EQ(best.best.probability_of_success, 1.0f);
  // The policy really gets there: every state with P_s = 1 reaches the target.
  const auto path = rollout(m, t, best.best.state);
  EXPECT_TRUE(endsInTarget(m, path)) << "path of " << path.size() << " states";
  for (StateId s = 0; s < m.numStates(); s += 997) {
    if (t.value(s) == 1.0f) {
      EXPECT_TRUE(endsInTarget(m, rollout(m, t, s))) << s;
    }
  }
}

// Hand check on an open workspace: a state one deterministic step from the target has P_s = 1,
// a state whose every arc leaves the workspace has P_s = 0.
TEST(SteeringMdpTest, OpenWorkspaceDeterministicByHand) {
  const SteeringModel m(openProblem(1e-3, 0.0, 0.0));
  const PolicyTable t = solveValueIteration(m);
  const GridSpec& g = m.grid();
  // Arc 0 (theta = 0, bevel left) moves (8, 1) cells: from (77, 49) it ends at (85, 50).
  ASSERT_EQ(m.arcDisplacement(0), std::make_pair(8, 1));
  const StateId one_step = g.state(77, 49, 0, Bevel::kLeft);
  EXPECT_EQ(t.value(one_step), 1.0f);
  EXPECT_EQ(t.control(one_step), Control::kInsert);
  // At the right edge facing +x: any arc of 7.85 mm leaves the workspace.
  const StateId at_edge = g.state(99, 50, 0, Bevel::kLeft);
  EXPECT_EQ(t.value(at_edge), 0.0f);
  EXPECT_EQ(t.control(at_edge), Control::kInsert);  // ties keep insert: the policy is defined
}

// ---- very large sigma
// ----------------------------------------------------------------------------

TEST(SteeringMdpTest, VeryLargeSigmaIsSmallButFinite) {
  const SteeringModel m(openProblem(2e-3, 3.0, 3.0));  // 3 rad: the wrapped normal, k = 40
  EXPECT_EQ(m.maxTransitions(), 40);
  const PolicyTable t = solveValueIteration(m);
  float max_free = 0.0f;
  for (StateId s = 0; s < m.numStates(); ++s) {
    const float v = t.value(s);
    ASSERT_TRUE(std::isfinite(v)) << s;
    ASSERT_GE(v, 0.0f);
    ASSERT_LE(v, 1.0f);
    if (m.cell(s / 80) == Cell::kFree)
      max_free = std::max(max_free, v);
  }
  EXPECT_GT(max_free, 0.0f);  // next to the target many outcomes still land in it
  EXPECT_LT(max_free, 1.0f);
  const BestStart best = t.bestStart(entryLine());
  EXPECT_GT(best.best.probability_of_success, 0.0f);
  EXPECT_LT(best.best.probability_of_success, 0.05f);
  // Compared with modest noise, P_s at the entry falls.
  const PolicyTable modest =
      solveValueIteration(SteeringModel(openProblem(2e-3, 5 * kDeg, 10 * kDeg)));
  EXPECT_GT(modest.bestStart(entryLine()).best.probability_of_success,
            best.best.probability_of_success);
}

// ---- unreachable target
// ----------------------------------------------------------------------------

TEST(SteeringMdpTest, TargetBehindAFullWallIsUnreachable) {
  SteeringProblem p = openProblem(2e-3, 5 * kDeg, 10 * kDeg);
  p.obstacles.push_back(obstacle("wall", rect(0.04, -0.01, 0.05, 0.11), 1e-3));
  const SteeringModel m(p);
  const PolicyTable t = solveValueIteration(m);
  const GridSpec& g = m.grid();
  for (int ix = 0; ix < 20; ++ix) {  // x < 40 mm: left of the wall
    for (int iy = 0; iy < g.ny; ++iy) {
      for (int bk = 0; bk < 80; ++bk) {
        const StateId s = g.position(ix, iy) * 80 + bk;
        ASSERT_EQ(t.value(s), 0.0f);
        ASSERT_EQ(t.control(s), Control::kInsert);
      }
    }
  }
  const BestStart best = t.bestStart(entryLine());
  EXPECT_FALSE(best);
  EXPECT_NE(best.toString().find("P_s = 0"), std::string::npos) << best.toString();
  TipPose pose;
  pose.p_SceneTip = Point2(0.0, 0.05);
  const auto l = t.lookup(pose);
  EXPECT_TRUE(l);  // the look-up still answers: insert, P_s = 0
  EXPECT_EQ(l.control, Control::kInsert);
  EXPECT_EQ(l.probability_of_success, 0.0f);
}

TEST(SteeringMdpTest, TargetBetweenGridPointsIsUnreachableEverywhere) {
  SteeringProblem p = openProblem(2e-3, 5 * kDeg, 10 * kDeg);
  p.target.position = Point2(0.085, 0.051);  // 1 mm from the nearest grid point
  p.target.radius_m = 0.5e-3;
  const SteeringModel m(p);
  EXPECT_EQ(m.targetCells(), 0);
  ASSERT_EQ(m.diagnostics().size(), 1u);
  EXPECT_NE(m.diagnostics().front().find("no grid point"), std::string::npos)
      << m.diagnostics().front();
  const PolicyTable t = solveValueIteration(m);
  for (float v : t.values())
    ASSERT_EQ(v, 0.0f);
}

// ---- start in an obstacle; target in an obstacle
// --------------------------------------------------

TEST(SteeringMdpTest, StartInsideAnObstacleHasZeroProbability) {
  SteeringProblem p = openProblem(2e-3, 5 * kDeg, 10 * kDeg);
  p.obstacles.push_back(
      obstacle("entry_block", rect(-0.01, -0.01, 0.01, 0.03), 1e-3));  // covers y <= 31 mm at x = 0
  const SteeringModel m(p);
  const PolicyTable t = solveValueIteration(m);
  TipPose pose;
  pose.p_SceneTip = Point2(0.0, 0.02);
  const auto l = t.lookup(pose);
  EXPECT_EQ(l.status, ControlLookup::Status::kInObstacle);
  EXPECT_EQ(l.probability_of_success, 0.0f);
  const auto candidates = t.startCandidates(entryLine());
  int blocked = 0;
  for (const auto& c : candidates) {
    if (c.pose.p_SceneTip.y() <= 0.031) {
      EXPECT_EQ(c.probability_of_success, 0.0f);
      ++blocked;
    }
  }
  EXPECT_EQ(blocked, 16 * 21 * 2);  // y = 0..30 mm at 2 mm, 21 angles, 2 bevels
  const BestStart best = t.bestStart(entryLine());
  ASSERT_TRUE(best) << best.toString();
  EXPECT_GT(best.best.pose.p_SceneTip.y(), 0.031);
}

TEST(SteeringMdpTest, TargetInsideAnObstacleIsReportedAndHasZeroProbability) {
  SteeringProblem p = openProblem(2e-3, 5 * kDeg, 10 * kDeg);
  p.obstacles.push_back(obstacle("tumour_wall", rect(0.075, 0.04, 0.095, 0.06), 1e-3));
  const SteeringModel m(p);
  EXPECT_EQ(m.targetCells(), 0);
  ASSERT_EQ(m.diagnostics().size(), 1u);
  EXPECT_NE(m.diagnostics().front().find("inside expanded obstacles"), std::string::npos)
      << m.diagnostics().front();
  EXPECT_NE(m.diagnostics().front().find("P_s = 0 everywhere"), std::string::npos);
  const PolicyTable t = solveValueIteration(m);
  for (float v : t.values())
    ASSERT_EQ(v, 0.0f);
  EXPECT_FALSE(t.bestStart(entryLine()));
}

// ---- a narrow gap
// ----------------------------------------------------------------------------------

/// A wall at x = 40..50 mm over the full height with a gap at y = 47..53 mm (6 mm; 4 mm after a
/// 1 mm clearance, `clearance_m` given).
SteeringProblem gapProblem(double sigma_rad, double clearance_m) {
  SteeringProblem p = openProblem(1e-3, sigma_rad, sigma_rad);
  p.obstacles.push_back(obstacle("wall_low", rect(0.04, -0.01, 0.05, 0.047), clearance_m));
  p.obstacles.push_back(obstacle("wall_high", rect(0.04, 0.053, 0.05, 0.11), clearance_m));
  return p;
}

TEST(SteeringMdpTest, NarrowGapIsThreadedDeterministically) {
  const SteeringModel m(gapProblem(0.0, 1e-3));
  const PolicyTable t = solveValueIteration(m);
  const BestStart best = t.bestStart(entryLine());
  ASSERT_TRUE(best) << best.toString();
  EXPECT_EQ(best.best.probability_of_success, 1.0f);
  const auto path = rollout(m, t, best.best.state);
  ASSERT_TRUE(endsInTarget(m, path));
  // Every state of the path inside the wall's x range lies within the (cleared) gap.
  int in_wall_range = 0;
  for (StateId s : path) {
    const Point2 q = m.grid().pose(s).p_SceneTip;
    if (q.x() >= 0.039 && q.x() <= 0.051) {
      ++in_wall_range;
      EXPECT_GE(q.y(), 0.048 - 1e-9);
      EXPECT_LE(q.y(), 0.052 + 1e-9);
    }
  }
  EXPECT_GE(in_wall_range, 1);
}

TEST(SteeringMdpTest, NarrowGapUnderUncertaintyAndClosedGap) {
  const PolicyTable noisy = solveValueIteration(SteeringModel(gapProblem(2 * kDeg, 1e-3)));
  const float ps = noisy.bestStart(entryLine()).best.probability_of_success;
  EXPECT_GT(ps, 0.0f);
  EXPECT_LT(ps, 1.0f);
  // A clearance of 3.5 mm closes the 6 mm gap: nothing left of the wall reaches the target.
  const SteeringModel closed_model(gapProblem(0.0, 3.5e-3));
  const PolicyTable closed = solveValueIteration(closed_model);
  EXPECT_FALSE(closed.bestStart(entryLine()));
  const GridSpec& g = closed_model.grid();
  for (int ix = 0; ix < 36; ++ix) {
    for (int iy = 0; iy < g.ny; ++iy) {
      for (int bk = 0; bk < 80; ++bk) {
        ASSERT_EQ(closed.value(g.position(ix, iy) * 80 + bk), 0.0f);
      }
    }
  }
}

// ---- the solver itself
// -----------------------------------------------------------------------------

TEST(SteeringMdpTest, SolutionSatisfiesTheBellmanEquation) {
  SteeringProblem p =
      test_shapes::dissertation(problemFromScene(scene::loadSceneSpec("steering_workspace")));
  p.params.grid_spacing_m = 2e-3;
  const SteeringModel m(p);
  SolveStats stats;
  const PolicyTable t = solveValueIteration(m, {}, &stats);
  EXPECT_TRUE(stats.converged);
  EXPECT_LT(stats.last_max_change, 1e-3);
  EXPECT_EQ(stats.max_change_per_sweep.size(), static_cast<std::size_t>(stats.sweeps));
  double worst = 0.0;
  for (StateId s = 0; s < m.numStates(); ++s) {
    if (m.cell(s / 80) != Cell::kFree)
      continue;
    double q[2] = {0.0, 0.0};
    for (int u = 0; u < 2; ++u) {
      for (const auto& tr : m.successors(s, static_cast<Control>(u))) {
        q[u] += tr.probability * (tr.next == kFailState ? 0.0 : t.value(tr.next));
      }
    }
    worst = std::max(worst, std::abs(std::max(q[0], q[1]) - t.value(s)));
    // The stored control attains the maximum (up to the residual).
    EXPECT_GE(q[static_cast<int>(t.control(s))], std::max(q[0], q[1]) - kResidualTol);
  }
  EXPECT_LT(worst, kResidualTol);
}

TEST(SteeringMdpTest, ThreadsAreDeterministicAndAgree) {
  SteeringProblem p =
      test_shapes::dissertation(problemFromScene(scene::loadSceneSpec("steering_workspace")));
  p.params.grid_spacing_m = 2e-3;
  const SteeringModel m(p);
  SolverOptions one, two;
  one.threads = 1;
  two.threads = 2;
  const PolicyTable a = solveValueIteration(m, two);
  const PolicyTable b = solveValueIteration(m, two);
  EXPECT_EQ(a.values(), b.values());  // bit-identical: no timing dependence
  const PolicyTable c = solveValueIteration(m, one);
  double max_diff = 0.0;
  for (std::size_t i = 0; i < a.values().size(); ++i) {
    max_diff = std::max(max_diff, double(std::abs(a.values()[i] - c.values()[i])));
  }
  EXPECT_LT(max_diff, kThreadAgreementTol);
}

TEST(SteeringMdpTest, TighterEpsilonOnRequest) {
  SteeringProblem p =
      test_shapes::dissertation(problemFromScene(scene::loadSceneSpec("steering_workspace")));
  p.params.grid_spacing_m = 2e-3;
  const SteeringModel m(p);
  SolveStats loose_stats, tight_stats;
  const PolicyTable loose = solveValueIteration(m, {}, &loose_stats);
  SolverOptions o;
  o.epsilon = 1e-7;
  const PolicyTable tight = solveValueIteration(m, o, &tight_stats);
  EXPECT_TRUE(tight_stats.converged);
  EXPECT_LT(tight_stats.last_max_change, 1e-7);
  EXPECT_GE(tight_stats.sweeps, loose_stats.sweeps);
  EXPECT_EQ(tight.epsilon(), 1e-7);
  // Values rise monotonically from 0, so the tighter solve is never below the looser one.
  for (std::size_t i = 0; i < tight.values().size(); ++i) {
    ASSERT_GE(tight.values()[i], loose.values()[i] - 1e-6f);
  }
}

TEST(SteeringMdpTest, BadSolverOptionsAreRefused) {
  const SteeringModel m(openProblem(4e-3, 0.0, 0.0));
  SolverOptions o;
  o.epsilon = 0.0;
  EXPECT_THROW(solveValueIteration(m, o), std::invalid_argument);
  o = SolverOptions{};
  o.threads = 0;
  EXPECT_THROW(solveValueIteration(m, o), std::invalid_argument);
  o = SolverOptions{};
  o.max_sweeps = 0;
  EXPECT_THROW(solveValueIteration(m, o), std::invalid_argument);
  o = SolverOptions{};
  o.max_sweeps = 1;
  SolveStats stats;
  solveValueIteration(m, o, &stats);
  EXPECT_FALSE(stats.converged);  // one sweep cannot show a full quiet cycle
  EXPECT_EQ(stats.sweeps, 1);
}

}  // namespace
}  // namespace needle_guidance::steering

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
