// The needle–tissue interaction converged in the step (dissertation 2.3.4–2.3.6 with event
// location): cutting, stick–slip friction, seed release and retraction give the same seed
// however the motion is cut into steps, with the depth grid off (every command one step), on the
// embedded track (the default) and on the node-moving cut.
#include <gtest/gtest.h>

#include <random>

#include "needle_guidance/rigid_planning/rigid_planner.h"
#include "needle_guidance/tissue/interaction_events.h"

namespace needle_guidance::tissue {
namespace {

/// Seeds from any two step schedules agree within this (the bench's step-halving target) [m].
constexpr double kConvergedTol_m = 5e-6;
constexpr double kInsertSpeed_m_s = 0.01;

scene::Scene stiffGland() {
  scene::Scene scene = scene::defaultScene("prostate_sagittal");
  scene.materials.at(1).young_modulus_Pa *= 10.0;
  return scene;
}

/// A simulation of `scene` refined along the path to `target`, stepping at every command.
std::unique_ptr<TissueSimulation> rawSimulation(const scene::Scene& scene, const Point2& target,
                                                NeedleModel model) {
  TissueSimOptions options = optionsFromScene(scene);
  options.needle_model = model;
  options.depth_grid.step_m = 0.0;
  options.meshing.refine_points.push_back(target);
  options.meshing.refine_lines.push_back({Point2(scene.workspace_min.x(), target.y()), target});
  return std::make_unique<TissueSimulation>(scene, options);
}

/// Inserts from -1 mm to release.x() through the depths `steps` (ascending, ending at
/// release.x()), implants, retracts in 0.5 mm steps and returns the seed at rest.
Point2 implantThrough(TissueSimulation& sim, const Point2& release,
                      const std::vector<double>& steps) {
  double x = -0.001;
  for (double next : steps) {
    const double dt = std::max(1e-6, (next - x) / kInsertSpeed_m_s);
    const StepStatus status = sim.step(dt, release.y(), next);
    EXPECT_TRUE(status) << status.toString();
    x = next;
  }
  std::string why;
  const std::optional<int> id = sim.implantSeed(&why);
  EXPECT_TRUE(id.has_value()) << why;
  for (double back = x - 5e-4; back > -0.001; back -= 5e-4) {
    EXPECT_TRUE(sim.step(0.025, release.y(), back));
  }
  EXPECT_TRUE(sim.step(0.025, release.y(), -0.001));
  EXPECT_TRUE(sim.step(0.025, release.y(), -0.001));  // at rest with the needle out
  return sim.seedPosition(sim.seeds().at(static_cast<std::size_t>(*id)));
}

std::vector<double> uniformSteps(double to_m, double step_m) {
  std::vector<double> depths;
  for (double x = -0.001 + step_m; x < to_m - 1e-12; x += step_m) {
    depths.push_back(x);
  }
  depths.push_back(to_m);
  return depths;
}

TEST(InteractionEvents, CrossingsAreLocatedOnTheStep) {
  EXPECT_DOUBLE_EQ(events::upCrossing(0.0, 2.0, 1.0), 0.5);
  EXPECT_EQ(events::upCrossing(1.5, 2.0, 1.0), 0.0);
  EXPECT_EQ(events::upCrossing(0.0, 0.5, 1.0), events::kNever);
  EXPECT_DOUBLE_EQ(events::magnitudeCrossing(0.0, -4.0, 1.0), 0.25);
  EXPECT_DOUBLE_EQ(events::magnitudeCrossing(-0.5, 2.5, 1.0), 0.5);
  EXPECT_EQ(events::magnitudeCrossing(0.2, 0.9, 1.0), events::kNever);
  EXPECT_TRUE(events::sticks(1e-4, 0.99e-4, 0.01, 5e-4));
  EXPECT_FALSE(events::sticks(1e-4, 0.9e-4, 0.01, 5e-4));
}

class StepConvergence : public ::testing::TestWithParam<std::tuple<int, NeedleModel>> {};

TEST_P(StepConvergence, TheSeedDoesNotDependOnTheStep) {
  // Three targets on the 10x gland: across the gland edge, deep in the gland, in the fat.
  const std::vector<Point2> targets{Point2(0.0181, 0.030), Point2(0.033, 0.0185),
                                    Point2(0.012, 0.045)};
  const scene::Scene scene = stiffGland();
  const Point2 target = targets.at(static_cast<std::size_t>(std::get<0>(GetParam())));
  const Point2 release(target.x() + 0.0021, target.y() + 0.0002);
  auto seedFor = [&](const std::vector<double>& steps) {
    const auto sim = rawSimulation(scene, target, std::get<1>(GetParam()));
    return implantThrough(*sim, release, steps);
  };
  const Point2 coarse = seedFor(uniformSteps(release.x(), 1e-4));
  const Point2 halved = seedFor(uniformSteps(release.x(), 5e-5));
  EXPECT_LT((coarse - halved).norm(), kConvergedTol_m) << "halving the step";
  // Irregular steps (fixed seed), and an insertion that stops half-way and resumes.
  std::mt19937 rng(29);
  std::uniform_real_distribution<double> step(1e-5, 3e-4);
  std::vector<double> irregular;
  for (double x = -0.001 + step(rng); x < release.x(); x += step(rng)) {
    irregular.push_back(x);
  }
  irregular.push_back(release.x());
  EXPECT_LT((seedFor(irregular) - coarse).norm(), kConvergedTol_m) << "irregular steps";
  std::vector<double> paused = uniformSteps(0.5 * release.x(), 1e-4);
  paused.insert(paused.end(), 5, 0.5 * release.x());  // stands still
  const std::vector<double> rest = uniformSteps(release.x(), 1e-4);
  for (double x : rest) {
    if (x > 0.5 * release.x()) {
      paused.push_back(x);
    }
  }
  EXPECT_LT((seedFor(paused) - coarse).norm(), kConvergedTol_m) << "stop and resume";
}

INSTANTIATE_TEST_SUITE_P(Targets, StepConvergence,
                         ::testing::Combine(::testing::Values(0, 1, 2),
                                            ::testing::Values(NeedleModel::kEmbeddedTrack,
                                                              NeedleModel::kNodeMoving)));

TEST(StepConvergenceHardCases, AStepLongerThanAnElementIsConverged) {
  const scene::Scene scene = stiffGland();
  const Point2 target(0.025, 0.030);
  const Point2 release(target.x(), target.y());
  for (NeedleModel model : {NeedleModel::kEmbeddedTrack, NeedleModel::kNodeMoving}) {
    const auto fine = rawSimulation(scene, target, model);
    const Point2 reference = implantThrough(*fine, release, uniformSteps(release.x(), 1e-4));
    // 2 mm steps, longer than the finest elements (1 mm here): still the same seed.
    const auto coarse = rawSimulation(scene, target, model);
    EXPECT_LT(
        (implantThrough(*coarse, release, uniformSteps(release.x(), 2e-3)) - reference).norm(),
        kConvergedTol_m)
        << toString(model);
  }
  // The embedded track cuts continuously: one step across the whole gland is the same seed.
  const auto fine = rawSimulation(scene, target, NeedleModel::kEmbeddedTrack);
  const Point2 reference = implantThrough(*fine, release, uniformSteps(release.x(), 1e-4));
  const auto one = rawSimulation(scene, target, NeedleModel::kEmbeddedTrack);
  EXPECT_LT((implantThrough(*one, release, {release.x()}) - reference).norm(), kConvergedTol_m);
}

TEST(StepConvergenceHardCases, TheNodeMovingCutRefusesAStepOfTooManyCuts) {
  const scene::Scene scene = stiffGland();
  const Point2 target(0.025, 0.030);
  const Point2 release(target.x(), target.y());
  // One step across the whole gland needs more cuts than a step may make: refused, saying so.
  const auto jump = rawSimulation(scene, target, NeedleModel::kNodeMoving);
  const StepStatus status = jump->step(1.0, release.y(), release.x());
  EXPECT_FALSE(status);
  EXPECT_NE(status.toString().find("max_cuts_per_step"), std::string::npos) << status.toString();
  EXPECT_FALSE(jump->needleInTissue());  // state unchanged
}

}  // namespace
}  // namespace needle_guidance::tissue

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
