// Tests for the interpolated transition model (not in 5.4.2; steering_model.h kInterpolated):
// deflection bins whose variance equals sigma^2, bilinear splitting that reproduces the exact arc
// end, an exact end in the target as success, refusal-free absorbing states, and the 5.4.2
// model's hashes left as they were, and the solver's tables fixed bit for bit.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <vector>

#include "../steering_shapes.h"
#include "needle_guidance/math.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/steering_model.h"
#include "needle_guidance/steering/value_iteration.h"

namespace needle_guidance::steering {
namespace {

constexpr double kDeg = kPi / 180.0;
constexpr double kVarianceTol_rad2 = 1e-10;    // bisection to ~1e-15 rad, probabilities in double
constexpr double kFloatProbabilityTol = 1e-6;  // stencil probabilities are float
constexpr double kPositionTol_m = 1e-7;        // float weights times a 1 mm cell
/// Float values solved to epsilon 1e-7: the fixed point holds to float rounding of ~30 terms.
constexpr double kBellmanTol = 1e-4;

SteeringProblem interpolated(SteeringProblem p, int subdivision = 1) {
  p.params.transition_model = TransitionModel::kInterpolated;
  p.params.orientation_subdivision = subdivision;
  return p;
}

TEST(SteeringInterpolatedTest, DeflectionVarianceEqualsSigmaSquared) {
  for (int s : {1, 2, 4}) {
    for (double sigma_deg : {1.0, 5.0, 10.0, 20.0}) {
      const SteeringModel m(
          interpolated(test_shapes::openProblem(2e-3, sigma_deg * kDeg, sigma_deg * kDeg), s), 1);
      const double alpha = m.grid().alphaRad();
      for (Control u : {Control::kInsert, Control::kFlip}) {
        const auto& p = m.deflectionProbabilities(u);
        double total = 0.0, mean = 0.0, var = 0.0;
        for (std::size_t i = 0; i < p.size(); ++i) {
          const double beta = (m.firstDeflection(u) + static_cast<int>(i)) * alpha;
          total += p[i];
          mean += p[i] * beta;
          var += p[i] * beta * beta;
        }
        EXPECT_NEAR(total, 1.0, 1e-12) << "s " << s << ", sigma " << sigma_deg;
        EXPECT_NEAR(mean, 0.0, 1e-12);
        EXPECT_NEAR(var, std::pow(sigma_deg * kDeg, 2), kVarianceTol_rad2)
            << "s " << s << ", sigma " << sigma_deg << " deg";
      }
    }
  }
}

TEST(SteeringInterpolatedTest, RoundedModelKeepsSigmaAndItsHash) {
  const SteeringProblem rounded = test_shapes::openProblem(1e-3, 5 * kDeg, 10 * kDeg);
  const SteeringModel m(rounded, 1);
  EXPECT_EQ(m.binSigma(Control::kInsert), 5 * kDeg);
  EXPECT_EQ(m.transitionModel(), TransitionModel::kRounded);
  // The split model is another problem (its own table file), the 5.4.2 one unchanged.
  EXPECT_NE(problemHash(rounded), problemHash(interpolated(rounded)));
  SteeringProblem explicit_rounded = rounded;
  explicit_rounded.params.transition_model = TransitionModel::kRounded;
  EXPECT_EQ(problemHash(rounded), problemHash(explicit_rounded));
}

TEST(SteeringInterpolatedTest, SplitReproducesTheExactArcEnd) {
  // No deflection: one group of four corners whose weighted mean is the exact end point.
  const SteeringModel m(interpolated(test_shapes::openProblem(1e-3)), 1);
  const GridSpec& g = m.grid();
  for (int k : {0, 3, 10, 37}) {
    for (Bevel b : {Bevel::kLeft, Bevel::kRight}) {
      const StateId s = g.state(40, 50, k, b);
      const auto groups = m.successorGroups(s, Control::kInsert);
      ASSERT_EQ(groups.size(), 1u);
      Point2 mean = Point2::Zero();
      double total = 0.0;
      for (const Transition& t : groups[0]) {
        ASSERT_GE(t.next, 0);
        mean += t.probability * g.pose(t.next).p_SceneTip;
        total += t.probability;
      }
      const TipPose exact =
          advanceTip(g.pose(s), Control::kInsert, 0.0, m.arcLength_m(), m.params().radius_m);
      EXPECT_NEAR(total, 1.0, kFloatProbabilityTol);
      EXPECT_NEAR((mean / total - exact.p_SceneTip).norm(), 0.0, kPositionTol_m) << "k " << k;
      // Every corner carries the exact end orientation.
      for (const Transition& t : groups[0]) {
        EXPECT_NEAR(std::remainder(g.pose(t.next).theta_rad - exact.theta_rad, 2 * kPi), 0.0, 1e-9);
      }
    }
  }
}

TEST(SteeringInterpolatedTest, AnExactEndInTheTargetSucceeds) {
  // Target of radius 0.3 mm (no grid point inside at 1 mm spacing is not required): place it on
  // the exact end of the straight-ahead arc from (40, 50) mm so only the exact check can see it.
  SteeringProblem p = interpolated(test_shapes::openProblem(1e-3));
  const TipPose start{Point2(0.040, 0.050), 0.0, Bevel::kLeft};
  const TipPose end = advanceTip(start, Control::kInsert, 0.0, 2 * kPi * 0.05 / 40, 0.05);
  p.target.position = end.p_SceneTip;
  p.target.radius_m = 1e-4;
  const SteeringModel m(p, 1);
  const StateId s = m.grid().nearestState(start);
  const auto groups = m.successorGroups(s, Control::kInsert);
  ASSERT_EQ(groups.size(), 1u);
  ASSERT_EQ(groups[0].size(), 1u);
  EXPECT_EQ(groups[0][0].next, kSuccessState);
  const PolicyTable t = solveValueIteration(m);
  EXPECT_FLOAT_EQ(t.value(s), 1.0f);
}

TEST(SteeringInterpolatedTest, SolvedValuesAreProbabilitiesAndBeatNoWorseThanZero) {
  SteeringProblem p = interpolated(problemFromScene(scene::loadSceneSpec("steering_workspace")), 2);
  p.params.grid_spacing_m = 2e-3;
  const SteeringModel m(p, 2);
  SolveStats stats;
  const PolicyTable t = solveValueIteration(m, {}, &stats);
  ASSERT_TRUE(stats.converged);
  float best = 0.0f;
  for (std::int64_t i = 0; i < m.numStates(); ++i) {
    ASSERT_GE(t.value(i), 0.0f);
    ASSERT_LE(t.value(i), 1.0f + 1e-6f);
    best = std::max(best, t.value(i));
  }
  EXPECT_GT(t.bestStart(startOptionsFromScene(scene::loadSceneSpec("steering_workspace")))
                .best.probability_of_success,
            0.3f);
}

TEST(SteeringInterpolatedTest, SolutionSatisfiesTheBellmanEquationOfItsSuccessors) {
  // The solver factors the split per arc; successorGroups() is the plain per-deflection form.
  SteeringProblem p = interpolated(problemFromScene(scene::loadSceneSpec("steering_workspace")), 1);
  p.params.grid_spacing_m = 2e-3;
  const SteeringModel m(p, 2);
  SolverOptions options;
  options.epsilon = 1e-7;
  const PolicyTable t = solveValueIteration(m, options);
  double worst = 0.0;
  for (StateId s = 0; s < m.numStates(); s += 7) {
    if (m.cell(s / (2 * m.grid().nc)) != Cell::kFree) {
      continue;
    }
    double q[2] = {0.0, 0.0};
    for (int u = 0; u < 2; ++u) {
      for (const Transition& tr : m.successors(s, static_cast<Control>(u))) {
        const double v = tr.next == kSuccessState ? 1.0
                         : tr.next == kFailState  ? 0.0
                                                  : double(t.value(tr.next));
        q[u] += tr.probability * v;
      }
    }
    worst = std::max(worst, std::abs(std::max(q[0], q[1]) - double(t.value(s))));
  }
  EXPECT_LT(worst, kBellmanTol);
}

TEST(SteeringInterpolatedTest, SceneKeySelectsTheModelAndBadValuesAreRefused) {
  const scene::Scene s = scene::loadSceneSpec("steering_workspace");
  scene::Scene copy = s;
  copy.steering->transition_model = "interpolated";
  EXPECT_EQ(problemFromScene(copy).params.transition_model, TransitionModel::kInterpolated);
  copy.steering->transition_model = "cubic";
  EXPECT_THROW(problemFromScene(copy), std::invalid_argument);
}

/// FNV-1a over the bit patterns of every value and the control of every state.
std::uint64_t tableFingerprint(const PolicyTable& t, std::int64_t states) {
  std::uint64_t h = 1469598103934665603ull;
  const auto mix = [&h](std::uint32_t x) { h = (h ^ x) * 1099511628211ull; };
  for (const float v : t.values()) {
    std::uint32_t bits = 0;
    std::memcpy(&bits, &v, sizeof(bits));
    mix(bits);
  }
  for (std::int64_t s = 0; s < states; ++s) {
    mix(t.control(s) == Control::kFlip ? 1u : 0u);
  }
  return h;
}

/// The solver's arithmetic is fixed: register-held and vectorised deflection sums, prefetched
/// corners and a snapshot copied only where values changed leave every value and control
/// bit-identical to the plain per-term loops. The fingerprints were recorded with those loops:
/// orientation counts that are (160, 80) and are not (44) a multiple of the vector width, one
/// and two threads, both transition models.
TEST(SteeringInterpolatedTest, SolverTablesAreBitIdenticalToThePlainLoops) {
  struct Case {
    const char* name;
    SteeringProblem problem;
    int threads;
    std::uint64_t fingerprint;
  };
  SteeringProblem workspace = problemFromScene(scene::loadSceneSpec("steering_workspace"));
  workspace.params.grid_spacing_m = 1.5e-3;
  SteeringProblem odd = interpolated(test_shapes::openProblem(2e-3, 6 * kDeg, 6 * kDeg), 1);
  odd.params.orientations = 44;
  SteeringProblem rounded = workspace;
  rounded.params.transition_model = TransitionModel::kRounded;
  const std::vector<Case> cases = {
      {"interpolated s = 4, 2 threads", interpolated(workspace, 4), 2, 0x851704ba6b35caabull},
      {"interpolated s = 2, 1 thread", interpolated(workspace, 2), 1, 0x99f1b22e4181f163ull},
      {"interpolated N_c = 44, 2 threads", odd, 2, 0xe710535dceee315bull},
      {"rounded, 2 threads", rounded, 2, 0x218bb3db7a33c7e7ull},
  };
  for (const Case& c : cases) {
    const SteeringModel m(c.problem, 2);
    SolverOptions options;
    options.threads = c.threads;
    SolveStats stats;
    const PolicyTable t = solveValueIteration(m, options, &stats);
    ASSERT_TRUE(stats.converged) << c.name;
    EXPECT_EQ(tableFingerprint(t, m.numStates()), c.fingerprint)
        << c.name << ": 0x" << std::hex << tableFingerprint(t, m.numStates());
  }
}

}  // namespace
}  // namespace needle_guidance::steering

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
