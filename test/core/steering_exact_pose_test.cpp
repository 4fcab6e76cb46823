// Tests for the prediction at a continuous pose by one exact Bellman step over the solved table
// (exact_pose_prediction.h, dissertation 5.4.2-5.4.3): it reproduces the table at grid states,
// it follows the continuous needle beside an obstacle corner where the rounded look-up does not,
// and poses off the grid, in an obstacle or in the target give their status, never NaN.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>

#include "../steering_shapes.h"
#include "needle_guidance/math.h"
#include "needle_guidance/steering/exact_pose_prediction.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/value_iteration.h"

namespace needle_guidance::steering {
namespace {

constexpr double kDeg = kPi / 180.0;
constexpr double kSolveEpsilon = 1e-5;
/// The solver's fixed point holds to its epsilon per update; float values of ~30 terms add
/// rounding of a few 1e-6.
constexpr double kGridPoseTol = 2e-4;
/// Corner test: the exact prediction is within this of a 20,000-trial Monte Carlo (3 SE at
/// P_s 0.25 is 0.009, the rest the model's own error), the rounded look-up farther than this.
constexpr double kCornerTol = 0.02;
constexpr std::int64_t kCornerTrials = 20000;
/// Corner poses the needle reaches the target from (a pose heading into the block is trivial).
constexpr double kNonTrivialPs = 0.1;
constexpr std::uint64_t kSeed = 5;

/// 10 x 10 cm, a 2 x 3 cm block with 1 mm clearance in the middle between entry and target,
/// sigma 5 / 10 degrees.
SteeringProblem blockProblem(TransitionModel transitions, int subdivision,
                             double spacing_m = 2e-3) {
  SteeringProblem p = test_shapes::openProblem(spacing_m, 5 * kDeg, 10 * kDeg);
  p.obstacles.push_back(
      test_shapes::obstacle("block", test_shapes::rect(0.04, 0.035, 0.06, 0.065), 0.001));
  p.params.transition_model = transitions;
  p.params.orientation_subdivision = subdivision;
  return p;
}

struct Solved {
  std::unique_ptr<SteeringModel> model;
  std::unique_ptr<PolicyTable> table;
};

Solved solve(const SteeringProblem& problem) {
  Solved out;
  out.model = std::make_unique<SteeringModel>(problem, 2);
  SolverOptions options;
  options.epsilon = kSolveEpsilon;
  out.table = std::make_unique<PolicyTable>(solveValueIteration(*out.model, options));
  return out;
}

class ExactPoseTest : public ::testing::TestWithParam<TransitionModel> {};

TEST_P(ExactPoseTest, GridPosesReproduceTheTable) {
  const Solved s = solve(blockProblem(GetParam(), 1));
  const ExactPosePrediction exact(*s.model, *s.table, PoseControl::kLookAhead);
  const GridSpec& g = s.table->grid();
  std::mt19937_64 rng(kSeed);
  int compared = 0, controls_compared = 0;
  for (int i = 0; i < 3000; ++i) {
    const StateId state = std::uniform_int_distribution<StateId>(0, g.numStates() - 1)(rng);
    if (s.table->cell(state / (2 * g.nc)) != Cell::kFree) {
      continue;
    }
    const TipPose pose = g.pose(state);
    const PosePrediction p = exact.predict(pose);
    ASSERT_TRUE(p) << p.toString();
    EXPECT_NEAR(p.probability_of_success, s.table->value(state), kGridPoseTol)
        << "state " << state << " at " << pose.p_SceneTip.transpose() << ", theta "
        << pose.theta_rad;
    if (std::abs(p.control_ps[0] - p.control_ps[1]) > 2 * kGridPoseTol) {
      EXPECT_EQ(p.control, s.table->control(state)) << "state " << state;
      ++controls_compared;
    }
    ++compared;
  }
  EXPECT_GT(compared, 1000);
  EXPECT_GT(controls_compared, 100);
}

INSTANTIATE_TEST_SUITE_P(BothTransitionModels, ExactPoseTest,
                         ::testing::Values(TransitionModel::kRounded,
                                           TransitionModel::kInterpolated));

TEST(ExactPosePrediction, FollowsTheNeedleBesideAnObstacleCornerWhereRoundingDoesNot) {
  // Interpolated transitions on a 1 mm grid, the table's own policy: beside the block's expanded
  // corners the rounded state lies up to 0.7 mm away, on the other side of the corner's
  // expanded boundary (an obstacle cell, P_s 0), while the needle passes the corner.
  const Solved s = solve(blockProblem(TransitionModel::kInterpolated, 1, 1e-3));
  const ExactPosePrediction exact(*s.model, *s.table);
  const ContinuousWorkspace& world = exact.world();
  // Poses around the block's upstream corners (expanded: x 39 mm, y 34 / 66 mm), heading +x at
  // the orientations of the grid; the one where the two predictions differ most.
  TipPose worst;
  double worst_difference = -1.0;
  for (double cy : {0.034, 0.066}) {
    for (double dx = -4e-3; dx <= 0.5e-3; dx += 0.3e-3) {
      for (double dy = -2e-3; dy <= 2e-3; dy += 0.3e-3) {
        for (int k : {-2, -1, 0, 1, 2}) {
          for (Bevel b : {Bevel::kLeft, Bevel::kRight}) {
            TipPose pose;
            pose.p_SceneTip = Point2(0.039 + dx, cy + dy);
            pose.theta_rad = k * s.table->grid().alphaRad();
            pose.bevel = b;
            const PosePrediction p = exact.predict(pose);
            if (!p || p.probability_of_success < kNonTrivialPs) {
              continue;
            }
            const double d =
                std::abs(p.probability_of_success - s.table->lookup(pose).probability_of_success);
            if (d > worst_difference) {
              worst_difference = d;
              worst = pose;
            }
          }
        }
      }
    }
  }
  ASSERT_GT(worst_difference, 2 * kCornerTol);
  const double predicted = exact.predict(worst).probability_of_success;
  const double rounded = s.table->lookup(worst).probability_of_success;
  const double mc = runMonteCarlo(world, worst, exact.policy(), kCornerTrials, kSeed, 2).rate();
  EXPECT_NEAR(predicted, mc, kCornerTol) << "at " << worst.p_SceneTip.transpose() << ", theta "
                                         << worst.theta_rad << ", rounded look-up " << rounded;
  EXPECT_GT(std::abs(rounded - mc), kCornerTol);
}

TEST(ExactPosePrediction, PosesOffTheGridInAnObstacleOrInTheTargetGiveTheirStatus) {
  const Solved s = solve(blockProblem(TransitionModel::kInterpolated, 1));
  const ExactPosePrediction exact(*s.model, *s.table, PoseControl::kLookAhead);
  auto at = [](double x, double y) {
    TipPose pose;
    pose.p_SceneTip = Point2(x, y);
    return pose;
  };
  const PosePrediction outside = exact.predict(at(-0.01, 0.05));
  EXPECT_EQ(outside.status, ControlLookup::Status::kOutsideGrid);
  EXPECT_EQ(outside.probability_of_success, 0.0);
  const PosePrediction nan = exact.predict(at(std::numeric_limits<double>::quiet_NaN(), 0.05));
  EXPECT_EQ(nan.status, ControlLookup::Status::kOutsideGrid);
  EXPECT_EQ(nan.probability_of_success, 0.0);
  TipPose bad_angle = at(0.01, 0.05);
  bad_angle.theta_rad = std::numeric_limits<double>::infinity();
  EXPECT_EQ(exact.predict(bad_angle).status, ControlLookup::Status::kOutsideGrid);
  const PosePrediction block = exact.predict(at(0.05, 0.05));
  EXPECT_EQ(block.status, ControlLookup::Status::kInObstacle);
  EXPECT_EQ(block.probability_of_success, 0.0);
  const PosePrediction target = exact.predict(at(0.085, 0.052));
  EXPECT_EQ(target.status, ControlLookup::Status::kInTarget);
  EXPECT_EQ(target.probability_of_success, 1.0);
  const PosePrediction free = exact.predict(at(0.0101, 0.0203));
  ASSERT_TRUE(free) << free.toString();
  EXPECT_TRUE(std::isfinite(free.probability_of_success));
  EXPECT_GE(free.probability_of_success, 0.0);
  EXPECT_LE(free.probability_of_success, 1.0);
}

TEST(ExactPosePrediction, RefusesATableOfAnotherModel) {
  const Solved a = solve(blockProblem(TransitionModel::kInterpolated, 1));
  const SteeringModel other(blockProblem(TransitionModel::kRounded, 1), 1);
  EXPECT_THROW(ExactPosePrediction(other, *a.table), std::invalid_argument);
}

}  // namespace
}  // namespace needle_guidance::steering

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
