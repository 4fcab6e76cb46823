// Tests for the steerable-needle MDP discretisation (dissertation 5.4.2), the O(1) look-up and
// the table file (5.4.3): independent re-derivations of the stencil, deflection probabilities,
// collision flags against CGAL's exact predicates, rounding, hashing and file refusals.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <random>
#include <stdexcept>
#include <string>

#include "../steering_shapes.h"
#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/math.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/steering_model.h"
#include "needle_guidance/steering/value_iteration.h"

namespace needle_guidance::steering {
namespace {

constexpr double kDeg = kPi / 180.0;
constexpr double kProbabilityTol = 1e-12;      // probabilities computed in double
constexpr double kFloatProbabilityTol = 1e-6;  // probabilities stored as float
constexpr double kPositionTol_m = 1e-12;
constexpr double kAngleTol_rad = 1e-12;
/// The collision check follows chords at most arc_chord_tolerance_m inside the arc; an arc
/// that passes closer than this to an obstacle boundary may be classified either way [m].
constexpr double kGrazeTol_m = 3e-5;
constexpr double kLookupBudget_us = 10.0;  // policy look-up time target
constexpr unsigned kSeed = 42;

double normalCdf(double z) {
  return 0.5 * std::erfc(-z / std::sqrt(2.0));
}

SteeringProblem workspaceProblem(double spacing_m) {
  SteeringProblem p =
      test_shapes::dissertation(problemFromScene(scene::loadSceneSpec("steering_workspace")));
  p.params.grid_spacing_m = spacing_m;
  return p;
}

TEST(SteeringModelTest, ProblemFromSceneTakesTheSteeringSection) {
  const scene::Scene s = scene::loadSceneSpec("steering_workspace");
  const SteeringProblem p = problemFromScene(s);
  EXPECT_EQ(p.params.orientations, 40);
  EXPECT_NEAR(p.params.grid_spacing_m, 1.4e-3, kPositionTol_m);
  EXPECT_NEAR(p.ps_tolerance, 0.005, 1e-12);
  EXPECT_EQ(p.params.orientation_subdivision, 3);
  EXPECT_EQ(p.params.transition_model, TransitionModel::kInterpolated);
  EXPECT_NEAR(p.params.radius_m, 0.05, kPositionTol_m);
  EXPECT_NEAR(p.params.sigma_insert_rad, 5 * kDeg, kAngleTol_rad);
  EXPECT_NEAR(p.params.sigma_flip_rad, 10 * kDeg, kAngleTol_rad);
  EXPECT_EQ(p.target.name, "target");
  EXPECT_EQ(p.obstacles.size(), 4u);
  EXPECT_THROW(problemFromScene(s, "nope"), std::out_of_range);
  EXPECT_THROW(problemFromScene(scene::loadSceneSpec("prostate_sagittal")), std::invalid_argument);
}

TEST(SteeringModelTest, EightHundredThousandStatesAtOneMillimetre) {
  const SteeringModel m(workspaceProblem(1e-3));
  EXPECT_EQ(m.grid().nx, 100);
  EXPECT_EQ(m.grid().ny, 100);
  EXPECT_EQ(m.numStates(), 800000);
  EXPECT_NEAR(m.arcLength_m(), 2 * kPi * 0.05 / 40, kPositionTol_m);
}

TEST(SteeringModelTest, OrientationsNotAMultipleOfFourAreRefused) {
  for (int nc : {38, 42, 2, 0, -4}) {
    SteeringProblem p = workspaceProblem(4e-3);
    p.params.orientations = nc;
    try {
      SteeringModel m(p);
      ADD_FAILURE() << "N_c = " << nc << " accepted";
    } catch (const std::invalid_argument& e) {
      const std::string what = e.what();
      EXPECT_NE(what.find("N_c = " + std::to_string(nc)), std::string::npos) << what;
      EXPECT_NE(what.find("multiple of 4"), std::string::npos) << what;
    }
  }
}

TEST(SteeringModelTest, BadParametersAreRefused) {
  auto refused = [](auto edit) {
    SteeringProblem p = workspaceProblem(4e-3);
    edit(p);
    EXPECT_THROW(SteeringModel m(p), std::invalid_argument);
  };
  refused([](SteeringProblem& p) { p.params.grid_spacing_m = 0.0; });
  refused([](SteeringProblem& p) { p.params.grid_spacing_m = 0.2; });  // wider than the workspace
  refused([](SteeringProblem& p) { p.params.radius_m = -1.0; });
  refused([](SteeringProblem& p) { p.params.sigma_insert_rad = -0.1; });
  refused([](SteeringProblem& p) { p.params.sigma_flip_rad = std::nan(""); });
  refused([](SteeringProblem& p) { p.params.tail_mass = 1.0; });
  refused([](SteeringProblem& p) { p.workspace_max = p.workspace_min; });
  refused([](SteeringProblem& p) { p.target.radius_m = -1e-3; });
  refused([](SteeringProblem& p) { p.obstacles.front().clearance_m = -1e-3; });
}

// Figure 5.4: bins of width alpha centred on d alpha, tails folded into the end bins.
TEST(SteeringModelTest, DeflectionProbabilitiesIntegrateTheNormal) {
  SteeringProblem p = workspaceProblem(4e-3);
  p.params.sigma_insert_rad = 5 * kDeg;  // alpha = 9 deg: m = 1 (tail beyond 13.5 deg = 0.7 %)
  p.params.sigma_flip_rad = 10 * kDeg;   // m = 3 (tail beyond 31.5 deg = 0.2 %; 22.5 deg: 2.4 %)
  const SteeringModel m(p);
  const auto& pi = m.deflectionProbabilities(Control::kInsert);
  ASSERT_EQ(pi.size(), 3u);
  EXPECT_EQ(m.firstDeflection(Control::kInsert), -1);
  const double p0 = std::erf(4.5 / (5.0 * std::sqrt(2.0)));
  EXPECT_NEAR(pi[1], p0, kProbabilityTol);
  EXPECT_NEAR(pi[0], 0.5 * (1.0 - p0), kProbabilityTol);
  EXPECT_NEAR(pi[2], 0.5 * (1.0 - p0), kProbabilityTol);

  const auto& pr = m.deflectionProbabilities(Control::kFlip);
  ASSERT_EQ(pr.size(), 7u);
  EXPECT_EQ(m.firstDeflection(Control::kFlip), -3);
  double sum = 0.0;
  for (double q : pr)
    sum += q;
  EXPECT_NEAR(sum, 1.0, kProbabilityTol);
  EXPECT_NEAR(pr[3], normalCdf(0.45) - normalCdf(-0.45), kProbabilityTol);
  EXPECT_NEAR(pr[6], 1.0 - normalCdf(2.25), kProbabilityTol);  // folded right tail
  EXPECT_NEAR(pr[0], pr[6], kProbabilityTol);
}

TEST(SteeringModelTest, ZeroSigmaIsOneTransitionAndHugeSigmaWrapsTheCircle) {
  SteeringProblem p = workspaceProblem(4e-3);
  p.params.sigma_insert_rad = 0.0;
  p.params.sigma_flip_rad = 10.0;  // rad: wider than the circle
  const SteeringModel m(p);
  ASSERT_EQ(m.deflectionProbabilities(Control::kInsert).size(), 1u);
  EXPECT_EQ(m.deflectionProbabilities(Control::kInsert)[0], 1.0);
  const auto& pr = m.deflectionProbabilities(Control::kFlip);
  ASSERT_EQ(pr.size(), 40u);
  double sum = 0.0;
  for (double q : pr) {
    EXPECT_TRUE(std::isfinite(q));
    EXPECT_GT(q, 0.0);
    sum += q;
  }
  EXPECT_NEAR(sum, 1.0, kProbabilityTol);
  EXPECT_NEAR(pr.front(), 1.0 / 40, 1e-3);  // nearly uniform
}

// Figure 5.3: transitions are the vectors between rounded control-circle points.
TEST(SteeringModelTest, StencilIsTheRoundedControlCircle) {
  const SteeringModel m(workspaceProblem(1e-3));
  const int nc = 40;
  const double r_cells = 50.0;  // r / Delta
  auto rounded = [&](int k) {
    const double t = 2 * kPi * k / nc;
    return std::make_pair(std::lround(r_cells * std::sin(t)), std::lround(-r_cells * std::cos(t)));
  };
  int sum_lx = 0, sum_ly = 0, sum_rx = 0, sum_ry = 0;
  for (int o = 0; o < nc; ++o) {
    const auto a = rounded(o);
    const auto b = rounded((o + 1) % nc);
    const auto left = m.arcDisplacement(o);
    EXPECT_EQ(left.first, b.first - a.first) << o;
    EXPECT_EQ(left.second, b.second - a.second) << o;
    // A flip is the 180-degree rotation: the right arc from o retraces the left arc o-1 -> o.
    const auto right = m.arcDisplacement(nc + o);
    const auto left_prev = m.arcDisplacement((o + nc - 1) % nc);
    EXPECT_EQ(right, left_prev) << o;
    sum_lx += left.first;
    sum_ly += left.second;
    sum_rx += right.first;
    sum_ry += right.second;
  }
  // A full turn returns exactly to the start: no orientation or position drift (5.4.2).
  EXPECT_EQ(sum_lx, 0);
  EXPECT_EQ(sum_ly, 0);
  EXPECT_EQ(sum_rx, 0);
  EXPECT_EQ(sum_ry, 0);
  // Orientation 0 (along +x), bevel left: r = 50 Delta, arc of 9 degrees.
  EXPECT_EQ(m.arcDisplacement(0), std::make_pair(8, 1));
}

TEST(SteeringModelTest, SuccessorsFollowTheStencil) {
  SteeringProblem p = workspaceProblem(1e-3);
  const SteeringModel m(p);
  const GridSpec& g = m.grid();
  // A free state far from obstacles and edges: (20 mm, 30 mm), theta = 0, bevel left.
  const StateId s = g.state(20, 30, 0, Bevel::kLeft);
  ASSERT_EQ(m.cell(g.position(20, 30)), Cell::kFree);
  const auto ins = m.successors(s, Control::kInsert);
  ASSERT_EQ(ins.size(), 3u);
  double sum = 0.0;
  for (std::size_t i = 0; i < ins.size(); ++i) {
    sum += ins[i].probability;
    const int d = static_cast<int>(i) - 1;  // start orientation o = d, end o + 1
    const auto disp = m.arcDisplacement((d + 40) % 40);
    EXPECT_EQ(ins[i].next, g.state(20 + disp.first, 30 + disp.second, (d + 41) % 40, Bevel::kLeft));
  }
  EXPECT_NEAR(sum, 1.0, kProbabilityTol);
  const auto flip = m.successors(s, Control::kFlip);
  ASSERT_EQ(flip.size(), 7u);
  const auto mid = flip[3];  // no deflection: right arc from o = 0 to o = 39
  const auto disp = m.arcDisplacement(40);
  EXPECT_EQ(mid.next, g.state(20 + disp.first, 30 + disp.second, 39, Bevel::kRight));
  // Absorbing states map to themselves.
  int tx = static_cast<int>(std::lround(p.target.position.x() / 1e-3));
  int ty = static_cast<int>(std::lround(p.target.position.y() / 1e-3));
  const StateId t = g.state(tx, ty, 5, Bevel::kRight);
  ASSERT_EQ(m.cell(g.position(tx, ty)), Cell::kTarget);
  const auto at_target = m.successors(t, Control::kFlip);
  ASSERT_EQ(at_target.size(), 1u);
  EXPECT_EQ(at_target[0].next, t);
  EXPECT_THROW(m.successors(m.numStates(), Control::kInsert), std::out_of_range);
}

// Orientation subdivision s (beyond 5.4.2): orientation in alpha / s steps, each arc still
// turns alpha and inserts delta; deflections integrated into alpha / s bins.
TEST(SteeringModelTest, SubdividedOrientationTracksTheSameArcs) {
  SteeringProblem p = workspaceProblem(1e-3);
  p.params.orientation_subdivision = 2;
  const SteeringModel m(p);
  const GridSpec& g = m.grid();
  ASSERT_EQ(g.nc, 80);
  EXPECT_EQ(m.numStates(), 1600000);
  EXPECT_NEAR(m.arcLength_m(), 2 * kPi * 0.05 / 40, kPositionTol_m);  // delta unchanged
  const double r_cells = 50.0;
  for (int o = 0; o < 80; ++o) {
    // Left arc from orientation o (o alpha / 2) to o + 2: between rounded points of 80.
    const double t0 = 2 * kPi * o / 80, t1 = 2 * kPi * (o + 2) / 80;
    const auto left = m.arcDisplacement(o);
    EXPECT_EQ(left.first, std::lround(r_cells * std::sin(t1)) - std::lround(r_cells * std::sin(t0)))
        << o;
    EXPECT_EQ(left.second,
              std::lround(-r_cells * std::cos(t1)) - std::lround(-r_cells * std::cos(t0)))
        << o;
  }
  // sigma_i = 5 deg in 4.5-degree bins: the tails beyond 2.5 bins hold 2.4 %, beyond 3.5 bins
  // 0.2 %, so d = -3..3 (tail_mass 1 %), the last bin holding everything beyond 2.5 bins.
  const auto& ins = m.deflectionProbabilities(Control::kInsert);
  ASSERT_EQ(ins.size(), 7u);
  ASSERT_EQ(m.firstDeflection(Control::kInsert), -3);
  const double sigma = 5.0 * kDeg, half_bin = 2.25 * kDeg;
  EXPECT_NEAR(ins[3], normalCdf(half_bin / sigma) - normalCdf(-half_bin / sigma), kProbabilityTol);
  EXPECT_NEAR(ins[6], 1.0 - normalCdf(5 * half_bin / sigma), kProbabilityTol);
  // Successor of an undeflected insert: orientation o + 2, position by arc o.
  const StateId s = g.state(20, 30, 6, Bevel::kLeft);
  const auto next = m.successors(s, Control::kInsert);
  const auto disp = m.arcDisplacement(6);
  EXPECT_EQ(next[3].next, g.state(20 + disp.first, 30 + disp.second, 8, Bevel::kLeft));
  // The pose of state k is k alpha / 2.
  EXPECT_NEAR(g.pose(s).theta_rad, 6 * 4.5 * kDeg, kAngleTol_rad);
  // A different model: a different table file.
  EXPECT_NE(m.hash(), problemHash(workspaceProblem(1e-3)));
}

TEST(SteeringModelTest, BadSubdivisionIsRefused) {
  for (int bad : {0, -1, 65}) {
    SteeringProblem p = workspaceProblem(4e-3);
    p.params.orientation_subdivision = bad;
    try {
      SteeringModel m(p);
      ADD_FAILURE() << "s = " << bad << " accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("orientation_subdivision"), std::string::npos)
          << e.what();
    }
  }
  SteeringProblem p = workspaceProblem(4e-3);
  p.params.orientations = 2048;
  p.params.orientation_subdivision = 4;  // 8192 orientations: more than arc ids hold
  EXPECT_THROW(SteeringModel m(p), std::invalid_argument);
}

// The discrete transition matches the continuous model from the grid point up to the
// rounding of the control-circle points: |error| <= Delta sqrt(2) (5.4.2).
TEST(SteeringModelTest, DiscreteStepsTrackTheContinuousArc) {
  SteeringProblem p = workspaceProblem(1e-3);
  p.params.sigma_insert_rad = 0.0;  // one transition: no deflection
  const SteeringModel m(p);
  const GridSpec& g = m.grid();
  ASSERT_TRUE(m.allArcsValid(g.position(20, 30)));  // 20 mm from every obstacle and edge
  for (int k = 0; k < 40; ++k) {
    for (int b = 0; b < 2; ++b) {
      const StateId s = g.state(20, 30, k, static_cast<Bevel>(b));
      const TipPose start = g.pose(s);
      const TipPose end = advanceTip(start, Control::kInsert, 0.0, m.arcLength_m(), 0.05);
      const auto successors = m.successors(s, Control::kInsert);
      ASSERT_EQ(successors.size(), 1u);
      const auto next = successors.front();
      ASSERT_NE(next.next, kFailState);
      const TipPose discrete = g.pose(next.next);
      EXPECT_LE((discrete.p_SceneTip - end.p_SceneTip).norm(),
                1e-3 * std::sqrt(2.0) + kPositionTol_m);
      EXPECT_NEAR(std::remainder(discrete.theta_rad - end.theta_rad, 2 * kPi), 0.0, 1e-9);
    }
  }
}

TEST(SteeringModelTest, AdvanceTipTracesArcsOfRadiusR) {
  TipPose p;
  p.p_SceneTip = Point2(0.0, 0.0);
  // Quarter turn, bevel left from theta = 0 with r = 1: centre (0, 1), end (1, 1) facing +y.
  const TipPose q = advanceTip(p, Control::kInsert, 0.0, kPi / 2, 1.0);
  EXPECT_NEAR(q.p_SceneTip.x(), 1.0, kPositionTol_m);
  EXPECT_NEAR(q.p_SceneTip.y(), 1.0, kPositionTol_m);
  EXPECT_NEAR(q.theta_rad, kPi / 2, kAngleTol_rad);
  EXPECT_EQ(q.bevel, Bevel::kLeft);
  // A flip: same orientation, traced clockwise: centre (0, -1), end (1, -1) facing -y.
  const TipPose f = advanceTip(p, Control::kFlip, 0.0, kPi / 2, 1.0);
  EXPECT_NEAR(f.p_SceneTip.x(), 1.0, kPositionTol_m);
  EXPECT_NEAR(f.p_SceneTip.y(), -1.0, kPositionTol_m);
  EXPECT_NEAR(f.theta_rad, -kPi / 2, kAngleTol_rad);
  EXPECT_EQ(f.bevel, Bevel::kRight);
  // A deflection rotates the start tangent.
  const TipPose d = advanceTip(p, Control::kInsert, kPi / 2, kPi / 2, 1.0);
  EXPECT_NEAR(d.p_SceneTip.x(), -1.0, kPositionTol_m);
  EXPECT_NEAR(d.p_SceneTip.y(), 1.0, kPositionTol_m);
}

// Arc flags against an independent check: a fine polyline tested with CGAL's exact predicates
// (geometry::segmentIntersectsPolygon), the workspace rectangle and the grid bounds.
TEST(SteeringModelTest, ArcValidityAgreesWithExactGeometry) {
  const SteeringModel m(workspaceProblem(2e-3));
  const GridSpec& g = m.grid();
  const auto& wmin = m.problem().workspace_min;
  const auto& wmax = m.problem().workspace_max;
  std::mt19937 rng(kSeed);
  int checked = 0, invalid = 0, graze = 0;
  constexpr int kFineSegments = 64;
  for (int trial = 0; trial < 40000; ++trial) {
    const int ix = static_cast<int>(rng() % g.nx);
    const int iy = static_cast<int>(rng() % g.ny);
    const int arc = static_cast<int>(rng() % 80);
    const std::int64_t pos = g.position(ix, iy);
    if (m.cell(pos) != Cell::kFree)
      continue;
    TipPose start;
    start.p_SceneTip = g.point(ix, iy);
    start.theta_rad = (arc % 40) * 2 * kPi / 40;
    start.bevel = arc < 40 ? Bevel::kLeft : Bevel::kRight;
    bool ok = true;
    double closest_m = 1e9;
    Point2 prev = start.p_SceneTip;
    for (int i = 1; i <= kFineSegments && ok; ++i) {
      const Point2 p =
          advanceTip(start, Control::kInsert, 0.0, m.arcLength_m() * i / kFineSegments, 0.05)
              .p_SceneTip;
      ok = p.x() >= wmin.x() && p.x() <= wmax.x() && p.y() >= wmin.y() && p.y() <= wmax.y();
      for (const auto& poly : m.expandedObstacles()) {
        ok = ok && !geometry::segmentIntersectsPolygon({prev, p}, poly);
        closest_m = std::min(closest_m, poly.distanceToBoundary(p));
      }
      prev = p;
    }
    const auto d = m.arcDisplacement(arc);
    ok = ok && ix + d.first >= 0 && ix + d.first < g.nx && iy + d.second >= 0 &&
         iy + d.second < g.ny;
    ++checked;
    invalid += ok ? 0 : 1;
    if (ok != m.arcValid(pos, arc)) {
      ++graze;
      EXPECT_LT(closest_m, kGrazeTol_m) << "arc " << arc << " from (" << ix << ", " << iy << ")";
    }
  }
  EXPECT_GT(checked, 20000);
  EXPECT_GT(invalid, 1000);  // the sample does exercise collisions
  EXPECT_LE(graze, 5);
}

TEST(SteeringModelTest, CellsFollowTheExpandedObstaclesAndTarget) {
  const SteeringModel m(workspaceProblem(1e-3));
  const GridSpec& g = m.grid();
  const auto& target = m.problem().target;
  for (int ix = 0; ix < g.nx; ++ix) {
    for (int iy = 0; iy < g.ny; ++iy) {
      const Point2 q = g.point(ix, iy);
      bool in_obstacle = false;
      for (const auto& o : m.problem().obstacles) {
        // Independent: distance to the unexpanded polygon vs its clearance (slack for the
        // polygonal approximation of the offset's rounded corners).
        const bool inside =
            o.polygon.contains(q) || o.polygon.distanceToBoundary(q) < o.clearance_m - 1e-4;
        in_obstacle = in_obstacle || inside;
      }
      const Cell c = m.cell(g.position(ix, iy));
      if (in_obstacle) {
        EXPECT_EQ(c, Cell::kObstacle) << ix << ", " << iy;
      } else if ((q - target.position).norm() < target.radius_m - 1e-9) {
        EXPECT_EQ(c, Cell::kTarget) << ix << ", " << iy;
      }
    }
  }
  EXPECT_GT(m.targetCells(), 70);  // pi (5 mm)^2 / (1 mm)^2 ~ 78
  EXPECT_TRUE(m.diagnostics().empty());
}

TEST(SteeringModelTest, HashDependsOnGeometryAndParametersOnly) {
  const SteeringProblem a = workspaceProblem(2e-3);
  SteeringProblem b = a;
  EXPECT_EQ(problemHash(a), problemHash(b));
  b.params.sigma_flip_rad += 1e-6;
  EXPECT_NE(problemHash(a), problemHash(b));
  b = a;
  b.target.radius_m += 1e-6;
  EXPECT_NE(problemHash(a), problemHash(b));
  b = a;
  b.obstacles.front().clearance_m += 1e-6;
  EXPECT_NE(problemHash(a), problemHash(b));
  b = a;
  b.params.grid_spacing_m = 1e-3;
  EXPECT_NE(problemHash(a), problemHash(b));
}

// ---- look-up and table file ------------------------------------------------------------------

class SteeringTableTest : public ::testing::Test {
protected:
  static void SetUpTestSuite() {
    model_ = new SteeringModel(workspaceProblem(2e-3));
    table_ = new PolicyTable(solveValueIteration(*model_));
  }
  static void TearDownTestSuite() {
    delete table_;
    delete model_;
  }
  static SteeringModel* model_;
  static PolicyTable* table_;
};
SteeringModel* SteeringTableTest::model_ = nullptr;
PolicyTable* SteeringTableTest::table_ = nullptr;

TEST_F(SteeringTableTest, LookupRoundsToTheNearestState) {
  const GridSpec& g = table_->grid();
  const double alpha = 2 * kPi / 40;
  TipPose pose;
  pose.p_SceneTip = g.point(10, 20) + Point2(0.49, -0.49) * g.spacing_m;
  pose.theta_rad = 3 * alpha + 0.49 * alpha;
  pose.bevel = Bevel::kRight;
  const auto l = table_->lookup(pose);
  ASSERT_TRUE(l) << l.toString();
  EXPECT_EQ(l.state, g.state(10, 20, 3, Bevel::kRight));
  EXPECT_EQ(l.control, table_->control(l.state));
  EXPECT_EQ(l.probability_of_success, table_->value(l.state));
  // Orientation wraps: -alpha/3 and 2 pi - alpha/3 are orientation 0; -alpha is 39.
  pose.theta_rad = -alpha / 3;
  EXPECT_EQ(table_->lookup(pose).state, g.state(10, 20, 0, Bevel::kRight));
  pose.theta_rad = 2 * kPi - alpha / 3;
  EXPECT_EQ(table_->lookup(pose).state, g.state(10, 20, 0, Bevel::kRight));
  pose.theta_rad = -alpha;
  EXPECT_EQ(table_->lookup(pose).state, g.state(10, 20, 39, Bevel::kRight));
  pose.theta_rad = -7 * 2 * kPi + alpha;
  EXPECT_EQ(table_->lookup(pose).state, g.state(10, 20, 1, Bevel::kRight));
}

TEST_F(SteeringTableTest, LookupReportsOffGridTargetAndObstacle) {
  TipPose pose;
  pose.p_SceneTip = Point2(-0.01, 0.05);
  EXPECT_EQ(table_->lookup(pose).status, ControlLookup::Status::kOutsideGrid);
  pose.p_SceneTip = Point2(std::nan(""), 0.05);
  EXPECT_EQ(table_->lookup(pose).status, ControlLookup::Status::kOutsideGrid);
  pose.p_SceneTip = Point2(0.05, 0.05);
  pose.theta_rad = std::numeric_limits<double>::infinity();
  EXPECT_EQ(table_->lookup(pose).status, ControlLookup::Status::kOutsideGrid);
  pose.theta_rad = 0.0;
  pose.p_SceneTip = model_->problem().target.position;
  const auto t = table_->lookup(pose);
  EXPECT_EQ(t.status, ControlLookup::Status::kInTarget);
  EXPECT_EQ(t.probability_of_success, 1.0f);
  EXPECT_FALSE(t);
  pose.p_SceneTip = Point2(0.035, 0.03);  // inside lower_wall
  const auto o = table_->lookup(pose);
  EXPECT_EQ(o.status, ControlLookup::Status::kInObstacle);
  EXPECT_EQ(o.probability_of_success, 0.0f);
  EXPECT_EQ(o.toString(), "in obstacle");
}

TEST_F(SteeringTableTest, LookupIsFast) {
  std::mt19937 rng(kSeed);
  std::uniform_real_distribution<double> u(0.0, 0.1), ut(-kPi, kPi);
  constexpr int kLookups = 100000;
  std::vector<TipPose> poses(kLookups);
  for (auto& p : poses) {
    p.p_SceneTip = Point2(u(rng), u(rng));
    p.theta_rad = ut(rng);
    p.bevel = rng() % 2 ? Bevel::kLeft : Bevel::kRight;
  }
  double sum = 0.0;
  const auto t0 = std::chrono::steady_clock::now();
  for (const auto& p : poses)
    sum += table_->lookup(p).probability_of_success;
  const double us =
      std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - t0).count() /
      kLookups;
  EXPECT_LT(us, kLookupBudget_us);
  EXPECT_GE(sum, 0.0);
}

TEST_F(SteeringTableTest, BestStartScansTheEntryLine) {
  const StartOptions start = startOptionsFromScene(scene::loadSceneSpec("steering_workspace"));
  const auto candidates = table_->startCandidates(start);
  // 50 heights x 21 angles (-90..90 degrees in 9-degree steps) x 2 bevels.
  EXPECT_EQ(candidates.size(), 50u * 21u * 2u);
  const BestStart best = table_->bestStart(start);
  ASSERT_TRUE(best) << best.toString();
  for (const auto& c : candidates) {
    EXPECT_LE(c.probability_of_success, best.best.probability_of_success);
    EXPECT_NEAR(c.pose.p_SceneTip.x(), 0.0, kPositionTol_m);
    EXPECT_LE(std::abs(c.pose.theta_rad), kPi / 2 + 1e-9);
  }
  EXPECT_EQ(table_->lookup(best.best.pose).state, best.best.state);
  StartOptions off = start;
  off.start_x_m = -0.05;
  const BestStart none = table_->bestStart(off);
  EXPECT_FALSE(none);
  EXPECT_NE(none.toString().find("no grid state"), std::string::npos);
}

TEST_F(SteeringTableTest, SaveLoadRoundTripAndRefusals) {
  const std::string path = ::testing::TempDir() + "steering_table_test.table";
  table_->save(path);
  LoadStatus status;
  const auto loaded = PolicyTable::load(path, model_->hash(), status);
  ASSERT_TRUE(loaded) << status.toString();
  ASSERT_TRUE(status);
  EXPECT_EQ(loaded->values(), table_->values());
  for (StateId s = 0; s < table_->grid().numStates(); s += 7) {
    EXPECT_EQ(loaded->control(s), table_->control(s));
  }
  EXPECT_EQ(loaded->epsilon(), table_->epsilon());
  EXPECT_EQ(loaded->sweeps(), table_->sweeps());

  // Other parameters: refused, naming both hashes.
  SteeringProblem other = model_->problem();
  other.params.sigma_insert_rad *= 2.0;
  EXPECT_FALSE(PolicyTable::load(path, problemHash(other), status));
  EXPECT_EQ(status.code(), LoadStatus::Code::kMismatch);
  EXPECT_NE(status.message().find("re-solve"), std::string::npos) << status.message();
  // Looser than requested.
  EXPECT_FALSE(PolicyTable::load(path, model_->hash(), status, 1e-5));
  EXPECT_EQ(status.code(), LoadStatus::Code::kTooLoose);
  // Missing and damaged files.
  EXPECT_FALSE(PolicyTable::load(path + ".missing", model_->hash(), status));
  EXPECT_EQ(status.code(), LoadStatus::Code::kCannotOpen);
  {
    std::fstream f(path, std::ios::in | std::ios::out | std::ios::binary);
    f.seekp(200);
    const char junk = 0x5a;
    f.write(&junk, 1);
  }
  EXPECT_FALSE(PolicyTable::load(path, model_->hash(), status));
  EXPECT_EQ(status.code(), LoadStatus::Code::kCorrupt);
  {
    std::ofstream f(path, std::ios::binary | std::ios::trunc);
    f << "not a table";
  }
  EXPECT_FALSE(PolicyTable::load(path, model_->hash(), status));
  EXPECT_EQ(status.code(), LoadStatus::Code::kCorrupt);
  std::remove(path.c_str());
  EXPECT_THROW(table_->save("/nonexistent_dir/x.table"), std::runtime_error);
}

}  // namespace
}  // namespace needle_guidance::steering

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
