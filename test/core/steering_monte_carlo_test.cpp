// The continuous needle world and the Monte Carlo truth check: exact arcs and
// contacts, an analytic success probability, the Wilson interval, thread independence, and
// agreement with the MDP where the discretisation is exact (sigma = 0).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/math.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/value_iteration.h"

#include "../steering_shapes.h"

namespace needle_guidance::steering {
namespace {

constexpr double kDeg = kPi / 180.0;
constexpr double kExact_m = 1e-12;       // same formula, rounding only [m]
constexpr double kChordTol_m = 1e-5;     // ContinuousWorkspace default chord tolerance [m]
constexpr double kContactTol_m = 2e-5;   // contact point to expanded boundary [m]
constexpr double kWilsonTol = 1e-4;      // published interval values, 4 decimals
constexpr double kStandardErrors = 4.0;  // Monte Carlo vs analytic, in binomial SEs
constexpr int kRandomArcs = 2000;        // random arcs checked against dense samples
constexpr int kArcSamples = 200;         // samples per arc
constexpr unsigned kArcSeed = 5;

/// The open workspace (Delta = 1 mm, sigma = 0) with the target at x = 80 mm.
SteeringProblem openProblem() {
  return test_shapes::openProblem(1e-3, 0.0, 0.0, 0.08);
}

scene::Obstacle wall(double x0, double y0, double x1, double y1, double clearance_m) {
  return test_shapes::obstacle("wall", test_shapes::rect(x0, y0, x1, y1), clearance_m);
}

double delta(const SteeringProblem& p) {
  return 2.0 * kPi * p.params.radius_m / p.params.orientations;
}

TEST(ContinuousWorkspace, FreeArcEndsWhereAdvanceTipSays) {
  const ContinuousWorkspace world(openProblem());
  TipPose start;
  start.p_SceneTip = Point2(0.01, 0.05);
  start.theta_rad = 10 * kDeg;
  for (Control u : {Control::kInsert, Control::kFlip}) {
    const ArcTrace t = world.traceArc(start, u, 3 * kDeg, 0.0078);
    const TipPose want = advanceTip(start, u, 3 * kDeg, 0.0078, 0.05);
    EXPECT_EQ(t.outcome, ArcOutcome::kFree);
    EXPECT_NEAR(t.free_length_m, 0.0078, kExact_m);
    EXPECT_NEAR((t.end.p_SceneTip - want.p_SceneTip).norm(), 0.0, kExact_m);
    EXPECT_NEAR(t.end.theta_rad, want.theta_rad, kExact_m);
    EXPECT_EQ(t.end.bevel, want.bevel);
  }
}

TEST(ContinuousWorkspace, ArcStopsAtTheExpandedObstacle) {
  SteeringProblem p = openProblem();
  p.obstacles.push_back(wall(0.03, 0.0, 0.035, 0.1, 0.002));  // expanded face at x = 0.028
  const ContinuousWorkspace world(p);
  TipPose start;
  start.p_SceneTip = Point2(0.02, 0.05);
  const ArcTrace t = world.traceArc(start, Control::kInsert, 0.0, 0.02);
  ASSERT_EQ(t.outcome, ArcOutcome::kObstacle);
  EXPECT_EQ(t.obstacle, "wall");
  EXPECT_NEAR(t.end.p_SceneTip.x(), 0.028, kContactTol_m);
  EXPECT_LT(t.free_length_m, 0.02);
  EXPECT_NEAR(world.expandedObstacles()[0].distanceToBoundary(t.end.p_SceneTip), 0.0,
              kContactTol_m);
  // The same arc, shorter than the gap, is free.
  EXPECT_EQ(world.traceArc(start, Control::kInsert, 0.0, 0.005).outcome, ArcOutcome::kFree);
}

TEST(ContinuousWorkspace, LeavingTheWorkspaceStopsOnTheBoundary) {
  const ContinuousWorkspace world(openProblem());
  TipPose start;
  start.p_SceneTip = Point2(0.095, 0.05);
  const ArcTrace t = world.traceArc(start, Control::kInsert, 0.0, 0.02);
  ASSERT_EQ(t.outcome, ArcOutcome::kLeftWorkspace);
  EXPECT_NEAR(t.end.p_SceneTip.x(), 0.1, kChordTol_m);
  EXPECT_GT(t.free_length_m, 0.0049);
}

TEST(ContinuousWorkspace, ArcsNearAndFarFromObstaclesAgreeWithDenseSamplesOfTheArc) {
  // Arcs from random poses (some clear of every edge and obstacle by their length, some not):
  // a free arc has every dense sample in the workspace and outside the expanded obstacles (to
  // the chord tolerance); a stopped one ends on the expanded boundary or the workspace's edge.
  SteeringProblem p = openProblem();
  p.obstacles.push_back(wall(0.04, 0.03, 0.05, 0.06, 0.002));
  const ContinuousWorkspace world(p);
  const geometry::Polygon& expanded = world.expandedObstacles().front();
  std::mt19937 rng(kArcSeed);
  std::uniform_real_distribution<double> coordinate(0.002, 0.098), angle(-kPi, kPi);
  int free = 0, stopped = 0;
  for (int i = 0; i < kRandomArcs; ++i) {
    TipPose start;
    start.p_SceneTip = Point2(coordinate(rng), coordinate(rng));
    start.theta_rad = angle(rng);
    if (world.obstacleAt(start.p_SceneTip) >= 0) {
      continue;
    }
    const Control u = i % 2 ? Control::kFlip : Control::kInsert;
    const double beta = 0.1 * angle(rng);
    const ArcTrace t = world.traceArc(start, u, beta, delta(p));
    const double length = t.outcome == ArcOutcome::kFree ? delta(p) : t.free_length_m;
    for (int k = 0; k <= kArcSamples; ++k) {
      const Point2 q =
          advanceTip(start, u, beta, length * k / kArcSamples, p.params.radius_m).p_SceneTip;
      const double depth = expanded.contains(q) ? expanded.distanceToBoundary(q) : 0.0;
      ASSERT_LE(depth, kChordTol_m) << "arc " << i << " sample " << k;
      ASSERT_TRUE((q.array() >= -kChordTol_m).all() && (q.array() <= 0.1 + kChordTol_m).all())
          << "arc " << i << " sample " << k;
    }
    if (t.outcome == ArcOutcome::kFree) {
      ++free;
      continue;
    }
    ++stopped;
    const Point2 e = t.end.p_SceneTip;
    const double to_edge = std::min({e.x(), e.y(), 0.1 - e.x(), 0.1 - e.y()});
    EXPECT_LE(std::min(std::abs(to_edge), std::abs(expanded.distanceToBoundary(e))), kContactTol_m)
        << "arc " << i;
  }
  EXPECT_GT(free, kRandomArcs / 4);
  EXPECT_GT(stopped, 0);
}

TEST(ContinuousWorkspace, BadStartsAreFailuresNotNaN) {
  SteeringProblem p = openProblem();
  p.obstacles.push_back(wall(0.03, 0.04, 0.04, 0.06, 0.0));
  const ContinuousWorkspace world(p);
  TipPose inside;
  inside.p_SceneTip = Point2(0.035, 0.05);
  EXPECT_EQ(world.traceArc(inside, Control::kInsert, 0.0, 0.01).outcome, ArcOutcome::kObstacle);
  TipPose nan_pose;
  nan_pose.p_SceneTip = Point2(std::numeric_limits<double>::quiet_NaN(), 0.05);
  const ArcTrace t = world.traceArc(nan_pose, Control::kInsert, 0.0, 0.01);
  EXPECT_EQ(t.outcome, ArcOutcome::kLeftWorkspace);
  EXPECT_EQ(t.free_length_m, 0.0);
  TipPose ok;
  ok.p_SceneTip = Point2(0.01, 0.05);
  EXPECT_EQ(world.traceArc(ok, Control::kInsert, std::nan(""), 0.01).outcome,
            ArcOutcome::kLeftWorkspace);
  SteeringProblem bad = openProblem();
  bad.params.radius_m = 0.0;
  EXPECT_THROW(ContinuousWorkspace{bad}, std::invalid_argument);
}

TEST(Wilson, MatchesPublishedValues) {
  // Wilson score 95 % intervals (Newcombe 1998, table I): 81/263 and 0/10.
  const Interval a = wilsonInterval(81, 263);
  EXPECT_NEAR(a.low, 0.2553, kWilsonTol);
  EXPECT_NEAR(a.high, 0.3662, kWilsonTol);
  const Interval b = wilsonInterval(0, 10);
  EXPECT_NEAR(b.low, 0.0, kWilsonTol);
  EXPECT_NEAR(b.high, 0.2775, kWilsonTol);
  const Interval none = wilsonInterval(0, 0);
  EXPECT_EQ(none.low, 0.0);
  EXPECT_EQ(none.high, 1.0);
}

/// Paired outcomes: `both` trials where a and b succeed, then only a, only b, and neither.
void pairs(int both, int only_a, int only_b, int neither, std::vector<bool>& a,
           std::vector<bool>& b) {
  a.clear();
  b.clear();
  const int counts[] = {both, only_a, only_b, neither};
  for (int cell = 0; cell < 4; ++cell) {
    for (int i = 0; i < counts[cell]; ++i) {
      a.push_back(cell < 2);
      b.push_back(cell == 0 || cell == 2);
    }
  }
}

TEST(PairedDifference, UncorrelatedPairsGiveTheIndependentNewcombeInterval) {
  // phi = 0 when n11 n00 = n10 n01: the square-and-add of the two Wilson intervals.
  std::vector<bool> a, b;
  pairs(30, 10, 15, 5, a, b);  // 30 * 5 = 10 * 15
  const PairedDifference d = pairedDifference(a, b);
  const Interval ia = wilsonInterval(40, 60), ib = wilsonInterval(45, 60);
  const double pa = 40.0 / 60.0, pb = 45.0 / 60.0;
  EXPECT_NEAR(d.difference, pa - pb, 1e-15);
  EXPECT_NEAR(d.interval.low, pa - pb - std::hypot(pa - ia.low, ib.high - pb), 1e-12);
  EXPECT_NEAR(d.interval.high, pa - pb + std::hypot(ia.high - pa, pb - ib.low), 1e-12);
  EXPECT_EQ(d.only_a, 10);
  EXPECT_EQ(d.only_b, 15);
  // Positively correlated pairs with the same margins: a narrower interval.
  pairs(40, 0, 5, 15, a, b);
  const PairedDifference c = pairedDifference(a, b);
  EXPECT_NEAR(c.difference, pa - pb, 1e-15);
  EXPECT_LT(c.interval.high - c.interval.low, d.interval.high - d.interval.low);
  EXPECT_THROW(pairedDifference(a, std::vector<bool>(3, true)), std::invalid_argument);
  EXPECT_THROW(pairedDifference({}, {}), std::invalid_argument);
}

TEST(PairedDifference, CoversTheTrueDifferenceOfCorrelatedArms) {
  // Arms that share most of their randomness (common random numbers): a succeeds when u < 0.30,
  // b when u' < 0.25 with u' = u for 80 % of the trials. True difference 0.05.
  constexpr int kSeeds = 1000, kTrials = 400;
  constexpr double kCoverageFloor = 0.93;  // 95 % nominal, 1000 seeds: ~3 standard errors
  int covered = 0, excluded_zero = 0;
  for (int seed = 0; seed < kSeeds; ++seed) {
    std::mt19937_64 rng(static_cast<std::uint64_t>(seed) + 17u);
    std::uniform_real_distribution<double> u01(0.0, 1.0);
    std::vector<bool> a, b;
    for (int i = 0; i < kTrials; ++i) {
      const double u = u01(rng);
      const double v = u01(rng) < 0.8 ? u : u01(rng);
      a.push_back(u < 0.30);
      b.push_back(v < 0.25);
    }
    const PairedDifference d = pairedDifference(a, b);
    covered += d.interval.contains(0.05) ? 1 : 0;
    excluded_zero += d.excludesZero() ? 1 : 0;
  }
  EXPECT_GE(double(covered) / kSeeds, kCoverageFloor);
  // Unpaired, 400 trials per arm would show a 0.05 difference in about 35 % of the seeds.
  EXPECT_GE(double(excluded_zero) / kSeeds, 0.6) << "pairing gained no power";
}

TEST(MonteCarlo, OneStepSuccessMatchesTheNormalIntegral) {
  // One insertion aimed at the target centre: the tip lands in the disc iff the chord rotated
  // by beta ends within rho of the centre, i.e. |beta| <= 2 asin(rho / (2 c)) for chord c.
  SteeringProblem p = openProblem();
  p.params.sigma_insert_rad = 5 * kDeg;
  TipPose start;
  start.p_SceneTip = Point2(0.02, 0.05);
  const TipPose aim = advanceTip(start, Control::kInsert, 0.0, delta(p), p.params.radius_m);
  p.target.position = aim.p_SceneTip;
  p.target.radius_m = 0.0005;
  const ContinuousWorkspace world(p);
  const double chord = (aim.p_SceneTip - start.p_SceneTip).norm();
  const double bound = 2.0 * std::asin(p.target.radius_m / (2.0 * chord));
  const double analytic = std::erf(bound / (p.params.sigma_insert_rad * std::sqrt(2.0)));
  TrialOptions one;
  one.max_steps = 1;
  const std::int64_t n = 20000;
  const MonteCarloResult r = runMonteCarlo(
      world, start, [](const TipPose&, int) { return Control::kInsert; }, n, 3, 2, one);
  const double se = std::sqrt(analytic * (1.0 - analytic) / n);
  EXPECT_NEAR(r.rate(), analytic, kStandardErrors * se);
  EXPECT_EQ(r.successes + r.step_limit + r.hit_obstacle + r.left_workspace, n);
}

/// The open workspace with insertion and flip noise, its solved policy and a start on the
/// entry line: the runs below compare Monte Carlo results of one policy.
struct NoisyOpenCase {
  SteeringProblem problem = [] {
    SteeringProblem p = openProblem();
    p.params.sigma_insert_rad = 5 * kDeg;
    p.params.sigma_flip_rad = 10 * kDeg;
    return p;
  }();
  ContinuousWorkspace world{problem};
  PolicyTable table = solveValueIteration(SteeringModel(problem));
  TipPose start = [] {
    TipPose t;
    t.p_SceneTip = Point2(0.0, 0.05);
    return t;
  }();
};

TEST(MonteCarlo, ResultDoesNotDependOnThreads) {
  const NoisyOpenCase c;
  const ContinuousWorkspace& world = c.world;
  const PolicyTable& table = c.table;
  const TipPose& start = c.start;
  const MonteCarloResult one = runMonteCarlo(world, start, tablePolicy(table), 3000, 9, 1);
  const MonteCarloResult two = runMonteCarlo(world, start, tablePolicy(table), 3000, 9, 2);
  EXPECT_EQ(one.successes, two.successes);
  EXPECT_EQ(one.hit_obstacle, two.hit_obstacle);
  EXPECT_EQ(one.left_workspace, two.left_workspace);
  EXPECT_DOUBLE_EQ(one.mean_steps, two.mean_steps);
  const MonteCarloResult other_seed = runMonteCarlo(world, start, tablePolicy(table), 3000, 10, 2);
  EXPECT_NE(one.successes, other_seed.successes);
}

TEST(MonteCarlo, ContinuedRunEqualsOneRun) {
  // Trials 0..999 and then 1000..2999 (first_trial) combined are the 3000 trials of one run.
  const NoisyOpenCase c;
  const ContinuousWorkspace& world = c.world;
  const PolicyTable& table = c.table;
  const TipPose& start = c.start;
  const MonteCarloResult one = runMonteCarlo(world, start, tablePolicy(table), 3000, 9, 2);
  const MonteCarloResult first = runMonteCarlo(world, start, tablePolicy(table), 1000, 9, 2);
  TrialOptions rest;
  rest.first_trial = 1000;
  const MonteCarloResult both =
      combined(first, runMonteCarlo(world, start, tablePolicy(table), 2000, 9, 1, rest));
  EXPECT_EQ(both.trials, 3000);
  EXPECT_EQ(both.successes, one.successes);
  EXPECT_EQ(both.hit_obstacle, one.hit_obstacle);
  EXPECT_EQ(both.left_workspace, one.left_workspace);
  EXPECT_NEAR(both.mean_steps, one.mean_steps, 1e-12);
  rest.first_trial = -1;
  EXPECT_THROW(runMonteCarlo(world, start, tablePolicy(table), 10, 9, 1, rest),
               std::invalid_argument);
}

// sigma = 0 (5.4.2): following the MDP's controls, the continuous needle has exactly the
// discrete orientation, and its position stays within E_h = h Delta sqrt(2) + Delta sqrt(2)/2
// of the discrete state after h direction changes. So a P_s = 1 path ends within E_h of the
// target disc (not necessarily inside it: rounding can put a grid point in the disc that
// the true tip misses). The same holds with the orientation subdivided (s > 1).
void expectWithinTheDiscretisationBound(int subdivision, double start_theta_rad) {
  SCOPED_TRACE("orientation_subdivision " + std::to_string(subdivision));
  SteeringProblem p = openProblem();
  p.params.orientation_subdivision = subdivision;
  p.obstacles.push_back(wall(0.04, 0.0, 0.045, 0.045, 0.001));
  const ContinuousWorkspace world(p);
  const SteeringModel model(p);
  const PolicyTable table = solveValueIteration(model);
  const GridSpec& grid = model.grid();
  const double spacing = p.params.grid_spacing_m;
  TipPose pose;
  pose.p_SceneTip = Point2(0.0, 0.06);
  pose.theta_rad = start_theta_rad;
  StateId s = grid.nearestState(pose);
  ASSERT_FLOAT_EQ(table.value(s), 1.0f);
  int flips = 0;
  int steps = 0;
  double worst_ratio = 0.0;
  while (model.cell(s / (2 * grid.nc)) == Cell::kFree && steps < 100) {
    const Control u = table.control(s);
    const std::vector<Transition> next = model.successors(s, u);
    ASSERT_EQ(next.size(), 1u);
    ASSERT_NE(next[0].next, kFailState);
    const ArcTrace arc = world.traceArc(pose, u, 0.0, delta(p));
    ASSERT_EQ(arc.outcome, ArcOutcome::kFree) << "step " << steps;
    pose = arc.end;
    s = next[0].next;
    flips += u == Control::kFlip ? 1 : 0;
    ++steps;
    const TipPose discrete = grid.pose(s);
    const double bound = flips * spacing * std::sqrt(2.0) + spacing * std::sqrt(2.0) / 2.0;
    const double error = (pose.p_SceneTip - discrete.p_SceneTip).norm();
    EXPECT_LE(error, bound) << "step " << steps << ", " << flips << " direction changes";
    worst_ratio = std::max(worst_ratio, error / bound);
    EXPECT_NEAR(std::remainder(pose.theta_rad - discrete.theta_rad, 2.0 * kPi), 0.0, 1e-9);
    EXPECT_EQ(pose.bevel, discrete.bevel);
  }
  ASSERT_EQ(model.cell(s / (2 * grid.nc)), Cell::kTarget);
  const double final_bound = flips * spacing * std::sqrt(2.0) + spacing * std::sqrt(2.0) / 2.0;
  EXPECT_LE((pose.p_SceneTip - p.target.position).norm(), p.target.radius_m + final_bound);
  std::cout << "s = " << subdivision << ": " << steps << " steps, " << flips
            << " direction changes, worst error / E_h = " << worst_ratio << "\n";
}

TEST(MonteCarlo, DeterministicNeedleStaysWithinTheDiscretisationBound) {
  expectWithinTheDiscretisationBound(1, 0.0);
  expectWithinTheDiscretisationBound(2, 4.5 * kDeg);  // an orientation only s = 2 has
}

// The solver's P_s is the success probability of its own Markov chain: sampling the chain
// (runDiscreteChain) must agree with the table within binomial noise, from several starts of
// the scene with obstacles and a narrow channel. This checks value iteration independently of
// any discretisation error.
TEST(DiscreteChain, SuccessRateMatchesThePredictedPs) {
  SteeringProblem p =
      test_shapes::dissertation(problemFromScene(scene::loadSceneSpec("steering_workspace")));
  p.params.grid_spacing_m = 2e-3;
  const SteeringModel model(p);
  SolverOptions tight;
  tight.epsilon = 1e-7;
  const PolicyTable table = solveValueIteration(model, tight);
  constexpr std::int64_t kTrials = 20000;
  int checked = 0;
  for (double y_mm : {6.0, 10.0, 30.0, 54.0, 60.0}) {
    for (Bevel b : {Bevel::kLeft, Bevel::kRight}) {
      TipPose start;
      start.p_SceneTip = Point2(0.0, y_mm * 1e-3);
      start.bevel = b;
      const double predicted = table.lookup(start).probability_of_success;
      const ChainResult chain = runDiscreteChain(model, table, start, kTrials, 7);
      ASSERT_EQ(chain.trials, kTrials);
      EXPECT_EQ(
          chain.successes + chain.failed_arcs + chain.rounded_into_obstacle + chain.step_limit,
          kTrials);
      const double se = std::sqrt(std::max(predicted * (1 - predicted), 1e-4) / kTrials);
      EXPECT_NEAR(chain.rate(), predicted, kStandardErrors * se) << "y " << y_mm << " mm";
      checked += predicted > 0.05 ? 1 : 0;
    }
  }
  EXPECT_GE(checked, 6);  // most starts have a non-trivial P_s
}

// sigma = 0: the chain is the deterministic discrete path, so a P_s = 1 start always succeeds
// and a P_s = 0 start always fails; bad requests are refused.
TEST(DiscreteChain, DeterministicAndRefusals) {
  SteeringProblem p = openProblem();
  p.obstacles.push_back(wall(0.04, 0.0, 0.045, 0.045, 0.001));
  const SteeringModel model(p);
  const PolicyTable table = solveValueIteration(model);
  TipPose start;
  start.p_SceneTip = Point2(0.0, 0.06);
  ASSERT_FLOAT_EQ(table.lookup(start).probability_of_success, 1.0f);
  EXPECT_EQ(runDiscreteChain(model, table, start, 50, 1).successes, 50);
  start.p_SceneTip = Point2(0.0, 0.0);
  start.theta_rad = -kPi / 2;  // straight out of the workspace
  ASSERT_FLOAT_EQ(table.lookup(start).probability_of_success, 0.0f);
  EXPECT_EQ(runDiscreteChain(model, table, start, 50, 1).successes, 0);
  EXPECT_THROW(runDiscreteChain(model, table, start, 0, 1), std::invalid_argument);
  start.p_SceneTip = Point2(0.5, 0.5);
  EXPECT_THROW(runDiscreteChain(model, table, start, 10, 1), std::invalid_argument);
  SteeringProblem other = p;
  other.params.grid_spacing_m = 2e-3;
  const SteeringModel other_model(other);
  start.p_SceneTip = Point2(0.0, 0.06);
  EXPECT_THROW(runDiscreteChain(other_model, table, start, 10, 1), std::invalid_argument);
}

TEST(MonteCarlo, StartsInObstacleOutsideOrInTargetEndAtOnce) {
  SteeringProblem p = openProblem();
  p.obstacles.push_back(wall(0.03, 0.04, 0.04, 0.06, 0.0));
  const ContinuousWorkspace world(p);
  const SteeringPolicy insert = [](const TipPose&, int) { return Control::kInsert; };
  TipPose s;
  s.p_SceneTip = Point2(0.035, 0.05);
  EXPECT_EQ(simulateTrial(world, s, insert, 1).outcome, TrialOutcome::kHitObstacle);
  s.p_SceneTip = Point2(-0.01, 0.05);
  EXPECT_EQ(simulateTrial(world, s, insert, 1).outcome, TrialOutcome::kLeftWorkspace);
  s.p_SceneTip = p.target.position;
  const Trial in_target = simulateTrial(world, s, insert, 1);
  EXPECT_TRUE(in_target.success());
  EXPECT_EQ(in_target.steps, 0);
  s.p_SceneTip = Point2(0.0, 0.05);
  s.theta_rad = std::nan("");
  EXPECT_EQ(simulateTrial(world, s, insert, 1).outcome, TrialOutcome::kLeftWorkspace);
  EXPECT_THROW(runMonteCarlo(world, s, insert, 0, 1), std::invalid_argument);
  EXPECT_THROW(runMonteCarlo(world, s, insert, 10, 1, 0), std::invalid_argument);
}

TEST(MonteCarlo, OpenLoopPolicyReplaysItsControls) {
  const SteeringPolicy policy = openLoopPolicy({Control::kFlip, Control::kInsert});
  const TipPose any;
  EXPECT_EQ(policy(any, 0), Control::kFlip);
  EXPECT_EQ(policy(any, 1), Control::kInsert);
  EXPECT_EQ(policy(any, 7), Control::kInsert);
}

}  // namespace
}  // namespace needle_guidance::steering

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
