// Tests for the 3-D model's planar special case (planar_check_3d.h): prism meshes, the extruded
// workspace against the planar one, and the 3-D loop under the MDP's policy against the planar
// Monte Carlo of the same policy (both simulate 5.3's continuous model).
#include <gtest/gtest.h>

#include <cmath>

#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/value_iteration.h"
#include "needle_guidance/steering_3d/planar_check_3d.h"

namespace needle_guidance::steering_3d {

using namespace needle_model;  // the needle, meshes and scenes the planner works on
namespace {

constexpr double kDistanceTol_m = 1e-9;

TEST(Planar3d, PrismOfANonConvexPolygonIsClosedAndExact) {
  // An "L": the notch corner (1, 1) is reflex.
  const std::vector<Eigen::Vector2d> l_shape{{0, 0}, {2, 0}, {2, 1}, {1, 1}, {1, 2}, {0, 2}};
  const Mesh3 prism = prismMesh(l_shape, -1.0, 1.0);
  EXPECT_EQ(prism.triangles.size(), 6u * 2u + 2u * 4u);
  const MeshDistance d(prism);
  EXPECT_TRUE(d.insideOrOn(Eigen::Vector3d(0.5, 0.5, 0)));
  EXPECT_FALSE(d.insideOrOn(Eigen::Vector3d(1.5, 1.5, 0)));  // in the notch
  EXPECT_NEAR(d.distance(Eigen::Vector3d(1.5, 1.5, 0)), 0.5, kDistanceTol_m);
  EXPECT_NEAR(d.distance(Eigen::Vector3d(0.5, 0.5, 3)), 2.0, kDistanceTol_m);
  EXPECT_THROW(prismMesh({{0, 0}, {1, 0}, {2, 0}}, 0, 1), std::invalid_argument);
}

steering::SteeringProblem coarseProblem() {
  steering::SteeringProblem p =
      steering::problemFromScene(scene::defaultScene("steering_workspace"));
  p.params.grid_spacing_m = 2e-3;  // fast to solve; the bench uses the scene's own grid
  p.params.orientation_subdivision = 1;
  return p;
}

TEST(Planar3d, ExtrudedWorldAgreesWithThePlanarWorkspaceInTheMidPlane) {
  const steering::SteeringProblem problem = coarseProblem();
  const steering::ContinuousWorkspace planar(problem);
  const CollisionWorld3 world = extrudedWorld(problem, 0.05, 1e-5);
  int disagreements = 0, checked = 0;
  for (double x = 0.001; x < 0.1; x += 0.0023) {
    for (double y = 0.001; y < 0.1; y += 0.0023) {
      const bool in2d = planar.obstacleAt(geometry::Point2(x, y)) >= 0;
      const PointCheck c = world.classify(Vector3(x, y, 0.0));
      // Points within 1e-5 m of an expanded edge may fall either way (chords).
      if (std::abs(c.margin_m) < 1e-5) {
        continue;
      }
      ++checked;
      disagreements += in2d != (c.contact == Contact3::kObstacle) ? 1 : 0;
    }
  }
  EXPECT_GT(checked, 1500);
  EXPECT_EQ(disagreements, 0);
}

TEST(Planar3d, FlipsOnlyLoopMatchesThePlanarMonteCarlo) {
  const steering::SteeringProblem problem = coarseProblem();
  const steering::SteeringModel model(problem);
  const steering::PolicyTable table = steering::solveValueIteration(model);
  const scene::Scene scene = scene::defaultScene("steering_workspace");
  const steering::BestStart best = table.bestStart(steering::startOptionsFromScene(scene));
  ASSERT_TRUE(best) << best.toString();
  constexpr std::int64_t kTrials = 400;
  const PlanarConsistency r = planarConsistency(problem, table, best.best.pose, kTrials, 11);
  // Two independent samples of the same Bernoulli: their difference has standard deviation
  // sqrt(2 p (1 - p) / n); 3.5 of them is a 1-in-2000 false alarm.
  const double p = 0.5 * (r.rate3d() + r.planar_mc.rate());
  const double tol = 3.5 * std::sqrt(2.0 * p * (1.0 - p) / kTrials) + 1e-9;
  EXPECT_NEAR(r.rate3d(), r.planar_mc.rate(), tol)
      << "3-D " << r.rate3d() << " planar " << r.planar_mc.rate() << " P_s " << r.predicted_ps;
  EXPECT_GT(r.rate3d(), 0.2);  // the policy works at all in 3-D
}

}  // namespace
}  // namespace needle_guidance::steering_3d

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
