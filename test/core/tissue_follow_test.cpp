// The follow_tissue cut track (fem::EmbeddedNeedle, scene key needle.track): the tip cuts the
// tissue now in front of it, so the track bends in the reference where the tissue ahead has
// moved sideways, and the seed lands off the needle line. Tests: step halving in 3-D and 2-D,
// mesh refinement, a symmetric scene without lateral drift, the scene key, the 3-D planner
// correcting the lateral position, and the search for the best template hole.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/fem/embedded_needle.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue_3d/offset_planner_3d.h"
#include "tissue_3d_scene_text.h"

namespace needle_guidance::tissue_3d {
namespace {

constexpr double kStepHalving_m = 5e-6;   // target: halving the step moves a seed <= 0.005 mm
constexpr double kPlacementTol_m = 1e-4;  // target: seeds within 0.1 mm

/// A 20 kPa block fixed at its far face with a stiff inclusion beside the needle path: the
/// tissue ahead of the tip moves sideways around it.
std::string sceneText(const std::string& track, double fine_mm, bool inclusion = true) {
  std::string s = testBlock("follow_block");
  if (inclusion) {
    s += R"(regions:
  - name: inclusion
    ellipsoid: {center_mm: [30, 6, 0], semi_axes_mm: [10, 4, 8]}
    material: {young_modulus_kPa: 400, poisson_ratio: 0.45}
)";
  }
  return s + testNeedleStageMesh("  track: " + track + "\n", std::to_string(fine_mm)) +
         R"(targets:
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

TEST(FollowTissue3d, HalvingTheStepMovesNoSeed) {
  Fixture f = follow();
  Fixture straight(parseTissueScene3d(sceneText("rest_line", 4), "r.yaml", "."));
  OffsetPlanner3 planner(f.scene, f.model), rest(straight.scene, straight.model);
  const Eigen::Vector2d lateral(0.0, 1e-3);
  const Vector3 a = planner.simulateImplant(lateral, 0.04, 1.0);
  const Vector3 b = planner.simulateImplant(lateral, 0.04, 0.5);
  const Vector3 c = planner.simulateImplant(lateral, 0.04, 0.25);
  ASSERT_TRUE(a.allFinite() && b.allFinite() && c.allFinite());
  EXPECT_LT((a - b).norm(), kStepHalving_m);
  EXPECT_LT((b - c).norm(), kStepHalving_m);
  // The rest line keeps the seed on the needle line; the followed track leaves it, and the
  // depth stays that of the rest line (the tip's cutting is the same).
  const Vector3 r = rest.simulateImplant(lateral, 0.04, 1.0);
  EXPECT_LT((r.tail<2>() - lateral).norm(), 1e-9);
  EXPECT_GT((a.tail<2>() - lateral).norm(), 1e-6);
  EXPECT_NEAR(a.x(), r.x(), 1e-4);
  // On a followed track the shaft holds one point per element on its axis; the tissue between
  // strays from the axis by 0.0066 mm here.
  constexpr double kShaftOffAxis_m = 1.5e-5;
  NeedleInsertion3 needle(f.model, f.scene.needle, 0.0, 0.04);
  for (double s = 0.0; s <= 0.04 + 1e-12; s += 5e-4) {
    ASSERT_TRUE(needle.moveTo(lateral, s));
  }
  double off_axis = 0.0;
  for (const Vector3& p : needle.shaftReference()) {
    off_axis = std::max(off_axis, (needle.worldOf(p).tail<2>() - lateral).norm());
  }
  EXPECT_LT(off_axis, kShaftOffAxis_m);
}

TEST(FollowTissue3d, SymmetricSceneDriftsOnlyByTheMeshAsymmetry) {
  // A homogeneous block and the needle on its axis of symmetry: the track would stay on the
  // axis but for the unstructured mesh (the seed's lateral offset is 0.0076 mm here, against
  // 0.03 mm beside the inclusion).
  constexpr double kMeshAsymmetry_m = 1.5e-5;
  Fixture f = follow(4, false);
  OffsetPlanner3 planner(f.scene, f.model);
  const Vector3 a = planner.simulateImplant(Eigen::Vector2d::Zero(), 0.04, 1.0);
  EXPECT_LT(a.tail<2>().norm(), kMeshAsymmetry_m) << a.transpose();
}

TEST(FollowTissue3d, MeshRefinementMovesTheLateralOffsetLittle) {
  // Fine size 4 mm -> 2 mm at the needle. The seed's lateral offset changes by 0.0093 mm; its
  // depth moves by about 2 mm in either track model (the point tip's indentation scales with
  // the element size: docs/tissue_3d.md, limits).
  constexpr double kLateralChange_m = 2e-5;
  Fixture coarse = follow(4), fine = follow(2);
  OffsetPlanner3 pc(coarse.scene, coarse.model), pf(fine.scene, fine.model);
  const Eigen::Vector2d lateral(0.0, 1e-3);
  const Vector3 a = pc.simulateImplant(lateral, 0.04, 1.0);
  const Vector3 b = pf.simulateImplant(lateral, 0.04, 1.0);
  EXPECT_GT(fine.model.mesh().elements.size(), coarse.model.mesh().elements.size());
  EXPECT_LT((a.tail<2>() - b.tail<2>()).norm(), kLateralChange_m)
      << a.transpose() << " / " << b.transpose();
}

TEST(FollowTissue3d, PlannerCorrectsTheLateralPosition) {
  Fixture f = follow();
  OffsetPlanner3 planner(f.scene, f.model);
  const PlanResult3 r = planner.plan(f.scene.targets[0]);
  ASSERT_TRUE(r.placed) << r.refusal;
  EXPECT_LE(r.verified_error_m, kPlacementTol_m);
  EXPECT_GE(r.predicted_error_m, 0.0);
  // The needle goes in off the target's line to cancel the track's lateral drift.
  EXPECT_GT((r.lateral_m - f.scene.targets[0].position_m.tail<2>()).norm(), 1e-6);
}

// ---- Template grid: the best hole ----

/// The inclusion scene with the stage replaced by a template grid (`grid`: the template map).
Fixture onTemplate(const std::string& track, const std::string& grid) {
  std::string text = sceneText(track, 4);
  const std::string stage = "  stage: {y_min_mm: -20, y_max_mm: 20, z_min_mm: -20, z_max_mm: 20}";
  text.replace(text.find(stage), stage.size(), "  template: " + grid);
  return Fixture(parseTissueScene3d(text, "t.yaml", "."));
}

TEST(FollowTissue3dTemplate, NearestHoleMissesAnotherHoleLands) {
  // A positioning grid finer than the followed track's drift (0.02 mm holes, drift about
  // 0.03 mm beside the inclusion) and a tolerance of 0.01 mm: the target is where hole B's seed
  // lands, so the hole nearest to the target is another one, whose seed misses by about the
  // hole spacing. The planner must find B (or a hole as good) from the drift it measured at the
  // nearest hole, verifying at most 3 holes.
  constexpr double kTolerance_m = 1e-5;
  Fixture f = onTemplate("follow_tissue",
                         "{origin_mm: [-0.4, 0.6], spacing_mm: 0.02, rows: 41, columns: 41}");
  const Workspace3& w = f.scene.workspace;
  PlannerOptions3 options;
  options.tolerance_m = kTolerance_m;
  options.unplanned = false;
  OffsetPlanner3 planner(f.scene, f.model, options);
  const Eigen::Vector2d hole_b = w.hole(20, 20);  // (0, 1 mm)
  const Vector3 seed_b = planner.simulateImplant(hole_b, 0.04);
  const Eigen::Vector2i nearest = w.holeIndex(seed_b.tail<2>());
  ASSERT_NE(nearest, Eigen::Vector2i(20, 20))
      << "the drift " << (seed_b.tail<2>() - hole_b).transpose() << " m stays within hole B";
  const PlanResult3 r = planner.plan({"at_b", seed_b});
  ASSERT_TRUE(r.placed) << r.refusal;
  EXPECT_LE(r.verified_error_m, kTolerance_m);
  EXPECT_EQ(r.nearest_hole, nearest);
  EXPECT_GT(r.nearest_hole_error_m, kTolerance_m);  // the nearest hole misses
  EXPECT_NE(r.hole, r.nearest_hole);
  EXPECT_TRUE(w.reaches(r.lateral_m));
  EXPECT_LE(r.holes_verified, 3);
  EXPECT_GE(r.holes_verified, 2);
}

TEST(FollowTissue3dTemplate, OutOfReachNamesTheNearestHoleOnBothTracks) {
  // The clinical 5 mm grid and a target 2.5 mm from the holes in y and z: no hole lands within
  // 0.1 mm on either track (the drift is a few hundredths of a millimetre). Refused as out of
  // reach, naming the nearest hole and its verified miss; one hole verified, one simulation.
  for (const std::string track : {"rest_line", "follow_tissue"}) {
    Fixture f = onTemplate(track, "{origin_mm: [-15, -14], spacing_mm: 5, rows: 7, columns: 7}");
    OffsetPlanner3 planner(f.scene, f.model);
    const Vector3 between(0.04, 2.5e-3, 3.5e-3);  // holes at y = 0, 5 mm and z = 1, 6 mm
    const PlanResult3 r = planner.plan({"between", between});
    EXPECT_FALSE(r.placed) << track;
    EXPECT_TRUE(r.unreachable) << track;
    EXPECT_NE(r.refusal.find("out of reach"), std::string::npos) << r.refusal;
    EXPECT_NE(r.refusal.find("nearest hole, row "), std::string::npos) << r.refusal;
    EXPECT_NE(r.refusal.find("(verified)"), std::string::npos) << r.refusal;
    // Its miss is the lateral distance to the hole, sqrt(2.5^2 + 2.5^2) mm, give or take the
    // drift and the depth.
    EXPECT_NEAR(r.nearest_hole_error_m, 3.536e-3, 0.1e-3) << track;
    EXPECT_EQ(r.verified_error_m, r.nearest_hole_error_m) << track;
    EXPECT_EQ(r.holes_verified, 1) << track;
    // A target on a hole is placed through that hole.
    const Vector3 on_hole(0.04, 0.0, 1e-3);
    const PlanResult3 ok = planner.plan({"on_hole", on_hole});
    ASSERT_TRUE(ok.placed) << track << ": " << ok.refusal;
    EXPECT_LE(ok.verified_error_m, kPlacementTol_m);
    EXPECT_EQ(ok.hole, Eigen::Vector2i(3, 3));
    EXPECT_EQ(ok.hole, ok.nearest_hole);
  }
}

// ---- 2-D: the same core on plane-strain triangles ----

std::string sagittalText() {
  std::ifstream in(std::string(NG_SOURCE_DIR) + "/config/scenes/prostate_sagittal.yaml");
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

TEST(FollowTissue2d, PlanarSceneKeyNeedsTheTipsSize) {
  const std::string base = sagittalText();
  const std::string anchor = "  radius_of_curvature_cm: 0\n";
  ASSERT_NE(base.find(anchor), std::string::npos);
  std::string follow = base;
  follow.replace(follow.find(anchor), anchor.size(), anchor + "  track: follow_tissue\n");
  EXPECT_TRUE(scene::parseScene(follow, "f.yaml").needle.follow_tissue);
  EXPECT_FALSE(scene::parseScene(base, "r.yaml").needle.follow_tissue);
  const std::string diameter = "  diameter_mm: 1.27";
  ASSERT_NE(follow.find(diameter), std::string::npos);
  follow.replace(follow.find(diameter), diameter.size(), "  diameter_mm: 0");
  try {
    scene::parseScene(follow, "f.yaml");
    FAIL() << "a followed track without the tip's size was accepted";
  } catch (const scene::SceneError& e) {
    EXPECT_NE(std::string(e.what()).find("needle.track"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("diameter"), std::string::npos) << e.what();
  }
}

/// A structured triangle mesh of a 60 x 40 mm slice, held at x = 60 mm, with a 400 kPa band
/// above the needle's path (y in [4, 10] mm, x in [20, 40] mm).
struct Slice {
  fem::SimplexMesh<2> mesh;
  std::vector<char> fixed;
  std::vector<fem::Material> materials{{20e3, 0.45}, {400e3, 0.45}};
  explicit Slice(double h) {
    const int nx = static_cast<int>(std::lround(0.06 / h)),
              ny = static_cast<int>(std::lround(0.04 / h));
    for (int j = 0; j <= ny; ++j) {
      for (int i = 0; i <= nx; ++i) {
        mesh.nodes.emplace_back(i * h, -0.02 + j * h);
        fixed.push_back(i == nx ? 1 : 0);
      }
    }
    for (int j = 0; j < ny; ++j) {
      for (int i = 0; i < nx; ++i) {
        const int a = j * (nx + 1) + i, b = a + 1, c = a + nx + 1, d = c + 1;
        const fem::Point<2> mid((i + 0.5) * h, -0.02 + (j + 0.5) * h);
        const int m =
            (mid.x() > 0.02 && mid.x() < 0.04 && mid.y() > 0.004 && mid.y() < 0.01) ? 1 : 0;
        mesh.elements.push_back({a, b, d});
        mesh.elements.push_back({a, d, c});
        mesh.element_material.push_back(m);
        mesh.element_material.push_back(m);
      }
    }
  }
};

Eigen::Vector2d implant2d(const fem::EmbeddingTissue<2>& tissue, double step_m) {
  fem::EmbeddedNeedleParams p;
  p.follow_tissue = true;
  fem::EmbeddedNeedle<2> needle(tissue, p, 0.0, 0.05);
  const Eigen::Matrix<double, 1, 1> lateral(0.0);
  for (double s = -step_m; s < 0.04;) {
    s = std::min(s + step_m, 0.04);
    EXPECT_TRUE(needle.moveTo(lateral, s));
  }
  const std::optional<int> seed = needle.implantSeed();
  EXPECT_TRUE(seed.has_value());
  for (double s = 0.04; s > -step_m;) {
    s = std::max(s - step_m, -step_m);
    EXPECT_TRUE(needle.moveTo(lateral, s));
  }
  return needle.seedWorld(*seed);
}

TEST(FollowTissue2d, HalvingTheStepMovesNoSeed) {
  Slice slice(2e-3);
  fem::EmbeddingTissue<2> tissue(slice.mesh, slice.fixed, slice.materials, 0.01);
  const Eigen::Vector2d a = implant2d(tissue, 5e-4);
  const Eigen::Vector2d b = implant2d(tissue, 2.5e-4);
  ASSERT_TRUE(a.allFinite() && b.allFinite());
  EXPECT_LT((a - b).norm(), kStepHalving_m);
  EXPECT_GT(std::abs(a.y()), 1e-6);  // the stiff band moves the tissue ahead sideways
}

}  // namespace
}  // namespace needle_guidance::tissue_3d

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
