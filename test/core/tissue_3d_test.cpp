// tissue_3d: scene loading and refusals, CGAL tetrahedral meshing and the near-zero-volume
// repair, needle insertion (puncture at the cutting force, track points, friction, seed
// release, retraction), step convergence, and the 3-D offset planner's placements and
// physical refusals (target in bone, needle line grazing a region, very stiff gland).
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <cstdlib>
#include <string>

#include "needle_guidance/fem/condensed_compliance.h"
#include "needle_guidance/fem/corotation.h"
#include "needle_guidance/fem/fixed_point.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue_3d/offset_planner_3d.h"
#include "tissue_3d_scene_text.h"

namespace needle_guidance::tissue_3d {
namespace {

constexpr double kForceTol_N = 1e-6;      // located events: tip force at f_b
constexpr double kStepHalving_m = 5e-6;   // target: halving the step moves a seed <= 0.005 mm
constexpr double kPlacementTol_m = 1e-4;  // target: seeds within 0.1 mm
constexpr double kRelaxed_m = 1e-9;       // after full retraction the tissue is back at rest

std::string sceneText(double gland_kpa, const std::string& extra_targets = "") {
  return testBlock("test_block") + R"(regions:
  - name: gland
    ellipsoid: {center_mm: [35, 0, 0], semi_axes_mm: [14, 12, 12]}
    material: {young_modulus_kPa: )" +
         std::to_string(gland_kpa) + R"(, poisson_ratio: 0.45}
  - name: bone
    ellipsoid: {center_mm: [30, 19, 0], semi_axes_mm: [6, 4, 15]}
    fixed: true
)" + testNeedleStageMesh() +
         R"(targets:
  - {name: center, position_mm: [36, 1, 2]}
)" + extra_targets;
}

TissueScene3d testScene(double gland_kpa = 60, const std::string& extra = "") {
  return parseTissueScene3d(sceneText(gland_kpa, extra), "test.yaml", ".");
}

struct Fixture {
  TissueScene3d scene;
  TissueModel3 model;
  explicit Fixture(TissueScene3d s)
      : scene(std::move(s)),
        model(meshTissue3d(scene, {}), scene.materialTable(), scene.corotational) {}
};

TEST(Tissue3dScene, ShippedScenesLoadAndMesh) {
  for (const char* name : {"prostate_block_3d", "prostate_template_3d", "heldout_3d"}) {
    const TissueScene3d s = loadTissueScene3d(std::string(NG_SOURCE_DIR) +
                                              "/config/scenes/tissue_3d/" + name + ".yaml");
    EXPECT_EQ(s.name, name);
    EXPECT_FALSE(s.targets.empty()) << name;
    EXPECT_FALSE(s.regions.empty()) << name;
  }
}

TEST(Tissue3dScene, BadScenesNameKeyAndReason) {
  std::string text = sceneText(60);
  auto refuses = [](const std::string& t, const std::string& what) {
    try {
      parseTissueScene3d(t, "bad.yaml", ".");
      ADD_FAILURE() << "accepted: " << what;
    } catch (const scene::SceneError& e) {
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
  };
  std::string t = text;
  t.replace(t.find("fixed_faces: x_max"), 18, "fixed_faces: x_top");
  refuses(t, "x_top");
  t = text;
  t.replace(t.find("kinetic_friction_N_per_cm: 0.2"), 30, "kinetic_friction_N_per_cm: 0.5");
  refuses(t, "kinetic friction exceeds static");
  t = text;
  t.replace(t.find("semi_axes_mm: [14, 12, 12]"), 26, "semi_axes_mm: [40, 12, 12]");
  refuses(t, "leaves the block");
  t = text;
  t.replace(t.find("position_mm: [36, 1, 2]"), 23, "position_mm: [36, 1, 99]");
  refuses(t, "outside the tissue block");
}

TEST(Tissue3dScene, InteractionPresetGivesTheNeedleDefaults) {
  // config/interaction/liver_de_jong_2017.yaml, read by the planar scenes' reader.
  constexpr double kPresetCuttingForce_N = 0.3697;
  constexpr double kPresetKineticFriction_N_per_m = 15.77;
  constexpr double kSame = 1e-12;
  std::string t = sceneText(60);
  const std::string keys =
      "  cutting_force_N: 0.5\n  static_friction_N_per_cm: 0.3\n"
      "  kinetic_friction_N_per_cm: 0.2\n";
  t.replace(t.find(keys), keys.size(), "  interaction: liver_de_jong_2017\n");
  const TissueScene3d preset = parseTissueScene3d(t, "preset.yaml", ".");
  EXPECT_NEAR(preset.needle.cutting_force_N, kPresetCuttingForce_N, kSame);
  EXPECT_NEAR(preset.needle.kinetic_friction_N_per_m, kPresetKineticFriction_N_per_m, 1e-9);
  // The scene's own key overrides the preset.
  std::string own = t;
  own.replace(own.find("  interaction: liver_de_jong_2017\n"), 0, "  cutting_force_N: 0.8\n");
  EXPECT_NEAR(parseTissueScene3d(own, "own.yaml", ".").needle.cutting_force_N, 0.8, kSame);
  std::string unknown = t;
  unknown.replace(unknown.find("liver_de_jong_2017"), 18, "no_such_tissue");
  try {
    parseTissueScene3d(unknown, "unknown.yaml", ".");
    ADD_FAILURE() << "an unknown preset was accepted";
  } catch (const scene::SceneError& e) {
    EXPECT_NE(std::string(e.what()).find("needle.interaction"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("no_such_tissue"), std::string::npos) << e.what();
  }
}

TEST(Tissue3dMesh, GradedMeshHeldAndOfGoodQuality) {
  const TissueScene3d s = testScene();
  TetMeshReport report;
  const TetMesh3 m = meshTissue3d(s, {}, 1.0, &report);
  EXPECT_GT(m.elementCount(), 500);
  EXPECT_GT(m.fixedCount(), 4);
  EXPECT_GE(report.min_quality, kMinTetQuality);
  EXPECT_TRUE(report.note.empty()) << report.note;
  // Grading: many more elements along the target's needle line than without the target.
  TissueScene3d no_target = s;
  no_target.targets.clear();
  const TetMesh3 coarse = meshTissue3d(no_target, {}, 1.0);
  auto nearLine = [](const TetMesh3& mesh) {
    int n = 0;
    for (int e = 0; e < mesh.elementCount(); ++e) {
      const fem::Corners<3> c = fem::corners<3>(mesh, e);
      const Vector3 centre = (c[0] + c[1] + c[2] + c[3]) / 4.0;
      n += std::hypot(centre.y() - 1e-3, centre.z() - 2e-3) < 3e-3 ? 1 : 0;
    }
    return n;
  };
  EXPECT_GT(nearLine(m), 3 * nearLine(coarse));
}

TEST(Tissue3dMesh, NearZeroVolumeElementRepairedAndSaid) {
  TetMesh3 m;
  m.nodes = {Vector3(0, 0, 0), Vector3(1, 0, 0), Vector3(0, 1, 0), Vector3(0, 0, 1),
             Vector3(1, 1, 1e-9)};
  m.elements = {{0, 1, 2, 3}, {0, 1, 4, 2}};  // the second is flat (volume ~ 1e-10 of the first)
  m.element_material = {0, 0};
  m.node_fixed = {1, 1, 1, 0, 0};
  TetMeshReport report;
  repairTetMesh(m, kMinTetQuality, report);
  EXPECT_EQ(report.dropped_elements, 1);
  EXPECT_EQ(m.elementCount(), 1);
  EXPECT_EQ(m.nodeCount(), 4);
  EXPECT_NE(report.note.find("near-zero volume"), std::string::npos) << report.note;
  // An inverted element is refused, naming it.
  TetMesh3 inv = m;
  std::swap(inv.elements[0][1], inv.elements[0][2]);
  TetMeshReport r2;
  try {
    repairTetMesh(inv, kMinTetQuality, r2);
    FAIL() << "inverted element accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("element 0"), std::string::npos) << e.what();
  }
}

TEST(Tissue3dInsertion, PunctureCutFrictionSeedAndRetraction) {
  Fixture f(testScene());
  NeedleInsertion3 needle(f.model, f.scene.needle, 0.0, 0.04);
  const Eigen::Vector2d lateral(1e-3, 2e-3);
  double peak_before_puncture = 0.0;
  for (double s = 0.0; s <= 0.036 + 1e-12; s += 5e-4) {
    ASSERT_TRUE(needle.moveTo(lateral, s));
    if (!needle.punctured()) {
      peak_before_puncture = std::max(peak_before_puncture, needle.lastMove().tip_force_N);
    } else {
      // Cutting holds the tip force at f_b; a new shaft point can relieve it for a moment.
      EXPECT_LE(needle.lastMove().tip_force_N, f.scene.needle.cutting_force_N + kForceTol_N);
      EXPECT_GT(needle.lastMove().tip_force_N, 0.0);
    }
  }
  EXPECT_LT(peak_before_puncture, f.scene.needle.cutting_force_N + kForceTol_N);
  ASSERT_TRUE(needle.punctured());
  // Tissue ahead of the tip is compressed: its tissue point lags the needle tip.
  EXPECT_LT(needle.tipReference().x(), 0.036);
  EXPECT_GT(needle.lastMove().shaft_points, 10);
  EXPECT_GT(needle.lastMove().friction_force_N, 0.0);
  const std::optional<int> seed = needle.implantSeed();
  ASSERT_TRUE(seed.has_value());
  EXPECT_LT((needle.seedWorld(*seed) - Vector3(0.036, 1e-3, 2e-3)).norm(), 1e-6);
  // Retraction: friction drags the tissue back, then everything is released.
  ASSERT_TRUE(needle.moveTo(lateral, 0.030));
  EXPECT_LT(needle.lastMove().friction_force_N, 0.0);
  ASSERT_TRUE(needle.moveTo(lateral, -1e-3));
  EXPECT_FALSE(needle.inTissue());
  EXPECT_LT((needle.seedWorld(*seed) - needle.seedReference(*seed)).norm(), kRelaxed_m);
  std::string why;
  EXPECT_FALSE(needle.moveTo(lateral, std::nan(""), &why));
  EXPECT_FALSE(why.empty());
}

TissueScene3d grippyScene(bool follow_tissue) {
  TissueScene3d scene = testScene();
  scene.needle.stick_velocity_m_s = 2.0 * scene.needle.insertion_velocity_m_s;
  scene.needle.static_friction_N_per_m = 300.0;  // a grippy shaft: 0.3 N per 1 mm point
  scene.needle.follow_tissue = follow_tissue;
  return scene;
}

TEST(Tissue3dInsertion, SlowNeedleShaftSticks) {
  Fixture f(grippyScene(false));  // on the rest line (the followed track: next test)
  NeedleInsertion3 needle(f.model, f.scene.needle, 0.0, 0.04);
  bool saw_stuck = false;
  int max_points = 0;
  for (double s = 0.0; s <= 0.03 + 1e-12; s += 2e-4) {  // short moves: a drag below the limit
    ASSERT_TRUE(needle.moveTo(Eigen::Vector2d(1e-3, 2e-3), s));
    const InsertionInfo3& info = needle.lastMove();
    saw_stuck = saw_stuck || info.slipping < info.shaft_points;
    max_points = std::max(max_points, info.shaft_points);
    // No shaft point is held with more than the static friction.
    EXPECT_LE(std::abs(info.friction_force_N), f.scene.needle.static_friction_N_per_m *
                                                       f.scene.needle.track_spacing_m *
                                                       info.shaft_points +
                                                   kForceTol_N);
  }
  EXPECT_GT(max_points, 10);
  EXPECT_TRUE(saw_stuck);  // points cut by a slow needle stick before the drag makes them slip
}

TEST(Tissue3dInsertion, GrippyShaftOnTheFollowedTrackGoesOnOrRefusesClearly) {
  // The stuck shaft's point loads (0.3 N each on 4 mm elements of 20 kPa tissue) displace the
  // tissue by millimetres next to the shaft, beyond the linear field's small-strain range: the
  // tissue ahead of the tip may not be locatable (the field folds). The followed track then
  // refuses the move naming the point, and leaves nothing undefined behind.
  Fixture f(grippyScene(true));
  NeedleInsertion3 needle(f.model, f.scene.needle, 0.0, 0.04);
  std::string why;
  for (double s = 0.0; s <= 0.03 + 1e-12; s += 2e-4) {
    if (!needle.moveTo(Eigen::Vector2d(1e-3, 2e-3), s, &why)) {
      EXPECT_NE(why.find("tissue ahead of the tip"), std::string::npos) << why;
      EXPECT_TRUE(needle.displacementField().allFinite());
      return;
    }
  }
  EXPECT_TRUE(needle.displacementField().allFinite());
}

TEST(Tissue3dInsertion, SeedsOfEarlierNeedlesStayAndMoveWithTheTissue) {
  // tissue_sim's reset between needles: a fresh needle takes over the implant's seeds.
  constexpr double kMoved_m = 1e-6;  // the next needle visibly displaces the kept seed
  Fixture f(testScene());
  NeedleInsertion3 first(f.model, f.scene.needle, 0.0, 0.04);
  const Eigen::Vector2d a(1e-3, 2e-3), b(1e-3, 5e-3);
  for (double s = 0.0; s <= 0.036 + 1e-12; s += 1e-3) {
    ASSERT_TRUE(first.moveTo(a, s));
  }
  ASSERT_TRUE(first.implantSeed().has_value());
  ASSERT_TRUE(first.moveTo(a, -1e-3));
  NeedleInsertion3 second(f.model, f.scene.needle, 0.0, 0.04);
  EXPECT_EQ(second.addSeed(first.seedReference(0)), 0);
  EXPECT_LT((second.seedWorld(0) - first.seedWorld(0)).norm(), kRelaxed_m);
  for (double s = 0.0; s <= 0.038 + 1e-12; s += 1e-3) {  // 3 mm beside the first track
    ASSERT_TRUE(second.moveTo(b, s));
  }
  EXPECT_GT((second.seedWorld(0) - second.seedReference(0)).norm(), kMoved_m);
  ASSERT_TRUE(second.implantSeed().has_value());
  EXPECT_EQ(second.seedCount(), 2);
  ASSERT_TRUE(second.moveTo(b, -1e-3));
  EXPECT_LT((second.seedWorld(0) - second.seedReference(0)).norm(), kRelaxed_m);
  EXPECT_THROW(second.addSeed(Vector3(1.0, 0.0, 0.0)), std::invalid_argument);
  EXPECT_EQ(second.seedCount(), 2);
}

TEST(Tissue3dInsertion, HalvingTheStepMovesNoSeed) {
  Fixture f(testScene());
  OffsetPlanner3 planner(f.scene, f.model);
  const Eigen::Vector2d lateral(1e-3, 2e-3);
  const Vector3 a = planner.simulateImplant(lateral, 0.04, 1.0);
  const Vector3 b = planner.simulateImplant(lateral, 0.04, 0.5);
  const Vector3 c = planner.simulateImplant(lateral, 0.04, 0.25);
  EXPECT_LT((a - b).norm(), kStepHalving_m);
  EXPECT_LT((b - c).norm(), kStepHalving_m);
  EXPECT_TRUE(a.allFinite());
}

/// The seed of an insertion to x = 30 mm at (y, z) = (1, 2) mm in the test block, the elements
/// along the needle line fine_mm in size, the needle's keys needle_keys.
Vector3 blockSeed(const std::string& needle_keys, const std::string& fine_mm) {
  Fixture f(parseTissueScene3d(testBlock("refine") + testNeedleStageMesh(needle_keys, fine_mm) +
                                   "targets:\n  - {name: t, position_mm: [30, 1, 2]}\n",
                               "refine.yaml", "."));
  OffsetPlanner3 planner(f.scene, f.model);
  return planner.simulateImplant(Eigen::Vector2d(1e-3, 2e-3), 0.030);
}

TEST(Tissue3dInsertion, SectionLoadConvergesUnderMeshRefinement) {
  // A point force displaces its own element by ~ F / (E h): the tip's tissue point lags the
  // tip more as the elements shrink, and the seed (that tissue point) moves with the mesh.
  // Spread over the needle's cross-section the answer converges once the elements are below
  // its radius: a needle of 8 mm diameter, elements at the tip refined from 4 to 2 mm.
  constexpr double kPointChangeMin_m = 1e-3;  // the point load's seed moves by > 1 mm
  constexpr double kConvergedShare = 0.35;    // the section's change: below this share of it
  const std::string point = "  diameter_mm: 8\n";
  const std::string section = point + "  load: cross_section\n";
  const Vector3 point_4 = blockSeed(point, "4"), point_2 = blockSeed(point, "2");
  const Vector3 section_4 = blockSeed(section, "4"), section_2 = blockSeed(section, "2");
  ASSERT_TRUE(point_2.allFinite() && section_2.allFinite());
  const double point_change = (point_4 - point_2).norm();
  const double section_change = (section_4 - section_2).norm();
  EXPECT_GT(point_change, kPointChangeMin_m);
  EXPECT_LT(section_change, kConvergedShare * point_change)
      << section_change * 1e3 << " mm against " << point_change * 1e3 << " mm";
  // The section lags less: its compliance is that of the disc, not of one small element.
  EXPECT_GT(section_2.x(), point_2.x());
}

TEST(Tissue3dInsertion, CrossSectionWeightsSpreadOverTheDisc) {
  constexpr double kSumTol = 1e-12;
  Fixture f(testScene());
  const Vector3 centre(0.03, 1e-3, 2e-3);
  const auto point = f.model.embedding().locateSection(centre, 0.0);
  ASSERT_TRUE(point.has_value());
  EXPECT_TRUE(point->section.empty());  // radius 0: the point itself
  const auto disc = f.model.embedding().locateSection(centre, 4e-3);
  ASSERT_TRUE(disc.has_value());
  double sum = 0.0;
  Vector3 mean = Vector3::Zero();
  for (const fem::NodeWeight& w : disc->section) {
    sum += w.weight;
    mean += w.weight * f.model.mesh().nodes[static_cast<std::size_t>(w.node)];
  }
  EXPECT_NEAR(sum, 1.0, kSumTol);
  EXPECT_GT(disc->section.size(), 4u);  // beyond the one element at the centre
  // The weights reproduce the disc's centroid (linear shape functions, symmetric samples up to
  // the sunflower rule's imbalance, below a tenth of the radius).
  EXPECT_LT((mean - centre).norm(), 4e-4);
  EXPECT_FALSE(f.model.embedding().locateSection(Vector3(1.0, 0.0, 0.0), 4e-3).has_value());
}

TEST(Tissue3dPlanner, PlacesReachableTargetAndRefusesBone) {
  Fixture f(testScene(60, R"(  - {name: in_bone, position_mm: [30, 19, 0]}
  - {name: behind_bone, position_mm: [45, 19, 0]}
  - {name: grazing_gland, position_mm: [35, 0, 11.9]}
)"));
  OffsetPlanner3 planner(f.scene, f.model);
  const PlanResult3 ok = planner.plan(f.scene.targets[0]);
  EXPECT_TRUE(ok.placed) << ok.refusal;
  EXPECT_LE(ok.verified_error_m, kPlacementTol_m);
  EXPECT_GT(ok.unplanned_error_m, ok.verified_error_m);
  const PlanResult3 bone = planner.plan(f.scene.targets[1]);
  EXPECT_FALSE(bone.placed);
  EXPECT_NE(bone.refusal.find("inside fixed region 'bone'"), std::string::npos) << bone.refusal;
  EXPECT_LT(bone.verified_error_m, 0.0);  // undefined: never simulated
  EXPECT_TRUE(bone.unreachable);
  const PlanResult3 behind = planner.plan(f.scene.targets[2]);
  EXPECT_FALSE(behind.placed);
  EXPECT_NE(behind.refusal.find("crosses fixed region 'bone'"), std::string::npos)
      << behind.refusal;
  // The needle line runs along the gland's surface: placed, or refused with a figure.
  const PlanResult3 graze = planner.plan(f.scene.targets[3]);
  EXPECT_TRUE(graze.placed || !graze.refusal.empty());
  if (graze.placed) {
    EXPECT_LE(graze.verified_error_m, kPlacementTol_m);
  }
}

TEST(Tissue3dPlanner, VeryStiffGland) {
  Fixture f(testScene(10000));  // 10 MPa: the gland barely deforms, the tissue around it does
  OffsetPlanner3 planner(f.scene, f.model);
  const PlanResult3 r = planner.plan(f.scene.targets[0]);
  EXPECT_TRUE(r.placed) << r.refusal;
  EXPECT_LE(r.verified_error_m, kPlacementTol_m);
  EXPECT_TRUE(r.verified_seed_m.allFinite());
}

// ---- Corotational elasticity (scene key tissue.model) ----

TEST(Tissue3dCorotation, SceneKeyChoosesTheModel) {
  EXPECT_FALSE(testScene().corotational);         // linear is the default
  EXPECT_TRUE(testScene().needle.follow_tissue);  // and follow_tissue the default track
  std::string text = sceneText(60) + "tissue: {model: corotational}\n";
  EXPECT_TRUE(parseTissueScene3d(text, "corot.yaml", ".").corotational);
  text = sceneText(60) + "tissue: {model: linear}\n";
  EXPECT_FALSE(parseTissueScene3d(text, "linear.yaml", ".").corotational);
  try {
    parseTissueScene3d(sceneText(60) + "tissue: {model: hyperelastic}\n", "bad.yaml", ".");
    ADD_FAILURE() << "an unknown tissue model was accepted";
  } catch (const scene::SceneError& e) {
    EXPECT_NE(std::string(e.what()).find("tissue.model"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("hyperelastic"), std::string::npos) << e.what();
  }
}

/// A cantilever along x: length x h x h, n cubes along x, two across, six tetrahedra per cube
/// (all around the cube's diagonal), held at x = 0.
TetMesh3 beamMesh(double length, double h, int n) {
  TetMesh3 m;
  auto id = [&](int i, int j, int k) { return (i * 3 + j) * 3 + k; };
  for (int i = 0; i <= n; ++i) {
    for (int j = 0; j <= 2; ++j) {
      for (int k = 0; k <= 2; ++k) {
        m.nodes.emplace_back(length * i / n, h * j / 2.0, h * k / 2.0);
        m.node_fixed.push_back(i == 0 ? 1 : 0);
      }
    }
  }
  const int paths[6][3] = {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}};
  for (int i = 0; i < n; ++i) {
    for (int j = 0; j < 2; ++j) {
      for (int k = 0; k < 2; ++k) {
        for (const auto& path : paths) {
          std::array<int, 3> c = {i, j, k};
          std::array<int, 4> tet;
          tet[0] = id(c[0], c[1], c[2]);
          for (int a = 0; a < 3; ++a) {
            ++c[static_cast<std::size_t>(path[a])];
            tet[static_cast<std::size_t>(a + 1)] = id(c[0], c[1], c[2]);
          }
          fem::Corners<3> corners;
          for (int a = 0; a < 4; ++a) {
            corners[static_cast<std::size_t>(a)] = m.nodes[static_cast<std::size_t>(tet[a])];
          }
          if (fem::signedMeasure<3>(corners) < 0.0) {
            std::swap(tet[2], tet[3]);
          }
          m.elements.push_back(tet);
          m.element_material.push_back(0);
        }
      }
    }
  }
  return m;
}

/// Length of the beam's deformed centre line (nodes j = k = 1).
double centreLineLength(const TetMesh3& m, const Eigen::VectorXd& u, int n) {
  double length = 0.0;
  for (int i = 0; i < n; ++i) {
    const int a = (i * 3 + 1) * 3 + 1, b = ((i + 1) * 3 + 1) * 3 + 1;
    length += (m.nodes[static_cast<std::size_t>(b)] + u.segment<3>(3 * b) -
               m.nodes[static_cast<std::size_t>(a)] - u.segment<3>(3 * a))
                  .norm();
  }
  return length;
}

TEST(Tissue3dCorotation, LargeBendingKeepsTheLengthWhereLinearGrows) {
  // A soft cantilever bent by an end load to a deflection of 20 % of its length (end rotation
  // about 17 degrees): the linear element moves every point straight across, so the beam's
  // centre line stretches (spurious growth ~ the integral of w'^2 / 2); the corotational
  // element rotates it instead and keeps its length.
  constexpr double kLength_m = 0.05, kHeight_m = 0.006;
  constexpr int kCubes = 20;
  constexpr double kDeflection = 0.2;              // end deflection / length, linear model
  constexpr double kLinearGrowthMin = 0.015;       // the linear beam stretches by more than this
  constexpr double kCorotationalGrowthMax = 2e-3;  // the corotational one by less than this
  // The warp is solved in single precision: the fixed point's changes level off near 1e-6 of
  // the warp (about 1e-8 m at this 1 cm deflection), far below this.
  constexpr double kConverged_m = 1e-7;
  constexpr int kIncrements = 10;
  constexpr int kMaxIterations = 100;
  const TetMesh3 mesh = beamMesh(kLength_m, kHeight_m, kCubes);
  const std::vector<fem::Material> materials = {{1e4, 0.3}};
  TissueModel3 linear(mesh, materials, false);
  TissueModel3 corot(mesh, materials, true);
  Eigen::VectorXd f = Eigen::VectorXd::Zero(3 * mesh.nodeCount());
  for (int node = 0; node < mesh.nodeCount(); ++node) {
    if (mesh.nodes[static_cast<std::size_t>(node)].x() > kLength_m - 1e-9) {
      f(3 * node + 1) = 1.0;
    }
  }
  const int tip = (kCubes * 3 + 1) * 3 + 1;
  f *= kDeflection * kLength_m / linear.compliance().solve(f)(3 * tip + 1);
  const Eigen::VectorXd u_linear = linear.compliance().solve(f);
  EXPECT_TRUE(linear.corotationDisplacement(u_linear).size() == 0);  // linear: no warp
  // The load is applied in increments, each iterated to its fixed point (as the insertion
  // does step by step); Anderson mixing damps the beam's oscillating bending modes, on which
  // the plain iteration u <- K^-1 f + v(u) does not converge at all.
  Eigen::VectorXd u = Eigen::VectorXd::Zero(f.size()), u_next;
  for (int increment = 1; increment <= kIncrements; ++increment) {
    const Eigen::VectorXd u_load = corot.compliance().solve(f * increment / kIncrements);
    fem::AndersonAcceleration mixer;
    double change = 1.0;
    int it = 0;
    for (; it < kMaxIterations && change > kConverged_m; ++it) {
      u_next = mixer.next(u, u_load + corot.corotationDisplacement(u));
      change = (u_next - u).lpNorm<Eigen::Infinity>();
      u = u_next;
    }
    ASSERT_LE(change, kConverged_m) << "increment " << increment << ": no fixed point in " << it;
  }
  ASSERT_TRUE(u.allFinite());
  const double growth_linear = centreLineLength(mesh, u_linear, kCubes) / kLength_m - 1.0;
  const double growth_corot = centreLineLength(mesh, u, kCubes) / kLength_m - 1.0;
  EXPECT_GT(growth_linear, kLinearGrowthMin);
  EXPECT_LT(std::abs(growth_corot), kCorotationalGrowthMax);
  // The corotational end swings back towards the support (arc, not a straight shift).
  EXPECT_LT(u(3 * tip), -0.5 * kLinearGrowthMin * kLength_m);
}

/// On the rest line: these tests compare the elasticity models on the same cut track.
TissueScene3d corotationalScene() {
  TissueScene3d s =
      parseTissueScene3d(sceneText(60) + "tissue: {model: corotational}\n", "corot.yaml", ".");
  s.needle.follow_tissue = false;
  return s;
}

TissueScene3d linearRestLineScene() {
  TissueScene3d s = testScene();
  s.needle.follow_tissue = false;
  return s;
}

TEST(Tissue3dCorotation, SmallStrainGivesTheLinearSeed) {
  // Insertion strains stay at a few percent: the corotated answer differs from the linear one
  // by second-order terms (rotation x strain), here below 2 % of the deformation itself.
  constexpr double kRelativeTol = 0.02;
  Fixture lin(linearRestLineScene());
  Fixture rot(corotationalScene());
  ASSERT_TRUE(rot.model.corotational());
  const Eigen::Vector2d lateral(1e-3, 2e-3);
  const Vector3 aim(0.036, 1e-3, 2e-3);
  OffsetPlanner3 lin_planner(lin.scene, lin.model), rot_planner(rot.scene, rot.model);
  const Vector3 a = lin_planner.simulateImplant(lateral, aim.x());
  const Vector3 b = rot_planner.simulateImplant(lateral, aim.x());
  ASSERT_TRUE(b.allFinite());
  EXPECT_GT((a - aim).norm(), 1e-4);  // the tissue deforms: the seed is not at the tip's aim
  EXPECT_LT((a - b).norm(), kRelativeTol * (a - aim).norm()) << (a - b).transpose();
  // The corotational iteration ran and the tissue relaxed after the needle left.
  NeedleInsertion3 needle(rot.model, rot.scene.needle, 0.0, 0.04);
  for (double s = 0.0; s <= 0.03 + 1e-12; s += 1e-3) {
    ASSERT_TRUE(needle.moveTo(lateral, s));
  }
  EXPECT_GT(needle.lastMove().corotation_updates, 0);
  ASSERT_TRUE(needle.moveTo(lateral, -1e-3));
  EXPECT_LT(needle.displacementField().lpNorm<Eigen::Infinity>(), kRelaxed_m);
}

TEST(Tissue3dCorotation, HalvingTheStepMovesNoSeed) {
  Fixture f(corotationalScene());
  OffsetPlanner3 planner(f.scene, f.model);
  const Eigen::Vector2d lateral(1e-3, 2e-3);
  const Vector3 a = planner.simulateImplant(lateral, 0.04, 1.0);
  const Vector3 b = planner.simulateImplant(lateral, 0.04, 0.5);
  EXPECT_LT((a - b).norm(), kStepHalving_m);
  EXPECT_TRUE(a.allFinite() && b.allFinite());
}

/// The soft (5 kPa) corotational block of the test scene with a point tip, meshed 2 mm fine.
TissueScene3d softCorotationalScene() {
  std::string text = testBlock("soft") + testNeedleStageMesh("", "2") +
                     "targets:\n  - {name: t, position_mm: [30, 1, 2]}\n"
                     "tissue: {model: corotational}\n";
  text.replace(text.find("young_modulus_kPa: 20"), 21, "young_modulus_kPa: 5");
  return parseTissueScene3d(text, "soft.yaml", ".");
}

/// Inserts to depth_m in steps of step_m, releases a seed, retracts at the same step; the seed's
/// world position (NaN and a test failure if a move is refused).
/// The simulation's event tolerance on the warp.
constexpr double kDefaultEventTol_m = fem::EmbeddedNeedleParams{}.event_warp_tolerance_m;

Vector3 softImplant(TissueModel3& model, const TissueScene3d& scene, double depth_m, double step_m,
                    double event_tol_m = kDefaultEventTol_m) {
  const Eigen::Vector2d lateral(1e-3, 2e-3);
  NeedleInsertion3 needle(model, scene.needle, 0.0, 0.04, event_tol_m);
  std::string why;
  for (double s = -step_m; s < depth_m - 1e-12;) {
    s = std::min(s + step_m, depth_m);
    if (!needle.moveTo(lateral, s, &why)) {
      ADD_FAILURE() << "insertion at " << s * 1e3 << " mm, step " << step_m * 1e3 << " mm: " << why;
      return Vector3::Constant(std::nan(""));
    }
  }
  const int seed = needle.implantSeed().value();
  for (double s = depth_m; s > -step_m;) {
    s -= step_m;
    if (!needle.moveTo(lateral, s, &why)) {
      ADD_FAILURE() << "retraction at " << s * 1e3 << " mm, step " << step_m * 1e3
                    << " mm: " << why;
      return Vector3::Constant(std::nan(""));
    }
  }
  return needle.seedWorld(seed);
}

TEST(Tissue3dCorotation, ElementsCrushedByThePointTipConverge) {
  // Soft tissue (5 kPa) and a point tip: before puncture the tip pushes the surface ~10 mm in,
  // and the elements at the tip are crushed and inverted (Green strains of several hundred
  // percent). Their polar rotation jumps as they flip, so the fixed point cycled; beyond the
  // small-strain range an element's rotation now fades to none (fem::elementRotation), and
  // the insertion converges at every step.
  constexpr double kDepth_m = 0.030, kStep_m = 5e-4;
  Fixture f(softCorotationalScene());
  ASSERT_TRUE(f.model.corotational());
  TissueModel3& model = f.model;
  NeedleInsertion3 needle(model, f.scene.needle, 0.0, 0.04);
  const Eigen::Vector2d lateral(1e-3, 2e-3);
  int most_inverted = 0;
  for (double s = 0.0; s < kDepth_m - 1e-12;) {
    s = std::min(s + kStep_m, kDepth_m);
    std::string why;
    ASSERT_TRUE(needle.moveTo(lateral, s, &why)) << "at " << s * 1e3 << " mm: " << why;
    most_inverted = std::max(most_inverted, model.invertedElements());
  }
  EXPECT_GT(most_inverted, 0);  // the hard case: the tip inverted elements
  const int seed = needle.implantSeed().value();
  ASSERT_TRUE(needle.moveTo(lateral, -1e-3));
  const Vector3 x = needle.seedWorld(seed);
  ASSERT_TRUE(x.allFinite());
  // Relaxed to the corotational fixed point's tolerance (0.1 um of warp change).
  constexpr double kWarpRelaxed_m = 1e-7;
  EXPECT_LT(needle.displacementField().lpNorm<Eigen::Infinity>(), kWarpRelaxed_m);
  // The compression ahead of the soft tissue's tip: the seed lags the tip by millimetres.
  EXPECT_LT(x.x(), kDepth_m - 1e-3);
}

TEST(Tissue3dCorotation, SoftTissueSeedDoesNotDependOnTheStep) {
  // Soft tissue: the tip pushes the surface ~17 mm in before puncture and the warp changes by
  // tens of micrometres over one step. The puncture, each track point and the step's cut are
  // located on the warp where they happen (converged to 0.1 um per update), so the seed is
  // the same at 1 mm and 0.5 mm steps to within a few times that tolerance. Located on the
  // warp of the step's start, they lagged the warp by one step and the seed moved by 2.2 um.
  constexpr double kDepth_m = 0.030;
  constexpr double kSeedTol_m = 1e-6;  // a tenth of the warp's lag over one step
  Fixture coarse(softCorotationalScene()), fine(softCorotationalScene());
  const Vector3 a = softImplant(coarse.model, coarse.scene, kDepth_m, 1e-3);
  const Vector3 b = softImplant(fine.model, fine.scene, kDepth_m, 5e-4);
  ASSERT_TRUE(a.allFinite() && b.allFinite());
  EXPECT_LT((a - b).norm(), kSeedTol_m) << (a - b).transpose() * 1e3 << " mm";
}

TEST(Tissue3dCorotation, SeedDoesNotDependOnTheMoveLength) {
  // The planner moves its corotational insertion by 8 scene steps: each move holds several
  // located events (the puncture, track points 1 mm apart, stick to slip), each settled on the
  // warp where it happens from a guess extended over the segment ends before it. The seed is
  // the one of an insertion by scene steps to within the step-halving target.
  constexpr double kMoveLengthTol_m = 5e-6;  // 0.005 mm
  constexpr double kLongMoveSteps = 8.0;
  Fixture f(corotationalScene());
  OffsetPlanner3 planner(f.scene, f.model);
  const Eigen::Vector2d lateral(1e-3, 2e-3);
  const Vector3 a = planner.simulateImplant(lateral, 0.04, 1.0);
  const Vector3 b = planner.simulateImplant(lateral, 0.04, kLongMoveSteps);
  ASSERT_TRUE(a.allFinite() && b.allFinite());
  EXPECT_LT((a - b).norm(), kMoveLengthTol_m) << (a - b).transpose() * 1e3 << " mm";
}

/// The corotational test block, a needle line in it and the planner's long moves (8 scene
/// steps) from one move before the entry face.
struct LongMoveBlock {
  Fixture f{corotationalScene()};
  Eigen::Vector2d lateral{1e-3, 2e-3};
  double step = 8.0 * f.scene.needle.insertion_velocity_m_s * f.scene.needle.step_s;
  double start = f.scene.block_min_m.x() - step;

  /// An insertion to depth_m by these moves (every one but the last a transit when transit),
  /// the seed released there and the needle withdrawn; the seed's world position (NaN if
  /// refused). *updates gains the insertion's fixed-point updates.
  Vector3 implant(double depth_m, bool transit, double event_tol_m, int* updates) {
    NeedleInsertion3 needle(f.model, f.scene.needle, f.scene.block_min_m.x(), depth_m, event_tol_m);
    std::string why;
    for (double s = start; s < depth_m;) {
      s = std::min(s + step, depth_m);
      const bool last = s >= depth_m;
      EXPECT_TRUE(transit && !last ? needle.passTo(lateral, s, &why)
                                   : needle.moveTo(lateral, s, &why))
          << why;
      *updates += needle.lastMove().corotation_updates;
    }
    const std::optional<int> seed = needle.implantSeed(&why);
    EXPECT_TRUE(seed.has_value()) << why;
    EXPECT_TRUE(needle.moveTo(lateral, start, &why)) << why;
    return seed ? needle.seedWorld(*seed) : Vector3(Vector3::Constant(NAN));
  }
};

TEST(Tissue3dCorotation, TransitMovesLeaveTheSeedOfSettledMoves) {
  // passTo leaves its end's warp unsettled; the events after it are located on their own
  // settled warps, so an insertion by transit moves and a last settled one releases the seed of
  // one by settled moves, for fewer fixed-point updates.
  constexpr double kTransitSeedTol_m = 5e-7;  // 0.0005 mm, a tenth of the step-halving target
  constexpr double kDepth_m = 0.04;
  LongMoveBlock b;
  int settled_updates = 0, transit_updates = 0;
  const Vector3 settled = b.implant(kDepth_m, false, kDefaultEventTol_m, &settled_updates);
  const Vector3 transit = b.implant(kDepth_m, true, kDefaultEventTol_m, &transit_updates);
  ASSERT_TRUE(settled.allFinite() && transit.allFinite());
  EXPECT_LT((settled - transit).norm(), kTransitSeedTol_m)
      << (settled - transit).transpose() * 1e3 << " mm";
  EXPECT_LT(transit_updates, settled_updates) << transit_updates << " against " << settled_updates;
}

TEST(Tissue3dCorotation, StopEndsTheMoveWhereTheTipsTissuePointReachesIt) {
  // stopAtTissueX: the move ends where the tip's tissue point reaches the stop, located within
  // it like a track point; the same insertion by plain moves to that tip position puts the
  // tissue point there to within the warp's event tolerance.
  constexpr double kStopTol_m = 1e-9;       // the cut's root finding
  constexpr double kSameDepthTol_m = 5e-6;  // the step-halving target
  constexpr double kStop_m = 0.0253;        // between track points
  constexpr double kDeepest_m = 0.045;
  LongMoveBlock b;
  Fixture& f = b.f;
  const Eigen::Vector2d& lateral = b.lateral;
  const double step = b.step, start = b.start;
  NeedleInsertion3 stopped(f.model, f.scene.needle, f.scene.block_min_m.x(), kDeepest_m);
  stopped.stopAtTissueX(kStop_m);
  std::string why;
  int moves = 0;
  for (double s = start; s < kDeepest_m && !stopped.lastMove().stopped; ++moves) {
    s = std::min(s + step, kDeepest_m);
    ASSERT_TRUE(stopped.moveTo(lateral, s, &why)) << why;
  }
  ASSERT_TRUE(stopped.lastMove().stopped);
  EXPECT_NEAR(stopped.tipReference().x(), kStop_m, kStopTol_m);
  EXPECT_LT(stopped.tipX(), start + moves * step);
  // A further move stops at once.
  const double tip = stopped.tipX();
  ASSERT_TRUE(stopped.moveTo(lateral, kDeepest_m, &why)) << why;
  EXPECT_TRUE(stopped.lastMove().stopped);
  EXPECT_EQ(stopped.tipX(), tip);
  NeedleInsertion3 plain(f.model, f.scene.needle, f.scene.block_min_m.x(), kDeepest_m);
  for (double s = start; s < tip;) {
    s = std::min(s + step, tip);
    ASSERT_TRUE(plain.moveTo(lateral, s, &why)) << why;
  }
  EXPECT_NEAR(plain.tipReference().x(), kStop_m, kSameDepthTol_m);
}

TEST(Tissue3dCorotation, SeedWithTheDerivedWarpTolerancesIsTheTightlySettledOne) {
  // Every state but the one the seed is released from is settled to half the step-halving
  // target (2.5 um) instead of 0.1 um; the seed stays where the insertion settled to 0.1 um at
  // every event and move end put it (measured on this block with every tolerance at 0.1 um and
  // relocations to 0.5 um, moves of 8 scene steps) within a tenth of the target.
  constexpr double kTightlySettledSeedTol_m = 5e-7;  // 0.0005 mm
  constexpr double kLongMoveSteps = 8.0;
  const Vector3 tightly_settled(0.039466974, 0.001, 0.002);  // [m]
  Fixture f(corotationalScene());
  OffsetPlanner3 planner(f.scene, f.model);
  const Vector3 seed = planner.simulateImplant(Eigen::Vector2d(1e-3, 2e-3), 0.04, kLongMoveSteps);
  ASSERT_TRUE(seed.allFinite());
  EXPECT_LT((seed - tightly_settled).norm(), kTightlySettledSeedTol_m)
      << (seed - tightly_settled).transpose() * 1e3 << " mm";
}

TEST(Tissue3dCorotation, LooserEventToleranceMovesTheSeedByAFractionOfIt) {
  // The offset planner settles its insertion's events to 10 um (a tenth of its placement
  // tolerance) instead of the simulation's 2.5 um: an event's location moves by less than the
  // warp's error and the seed, whose tissue point each track point fixes afresh and whose own
  // release state is settled as tightly as before, by a fraction of that (measured 2e-13 m on
  // this block, 62 updates against 81), for fewer updates.
  constexpr double kLooseEventTol_m = 1e-5;
  constexpr double kSeedTol_m = 0.25 * kLooseEventTol_m;
  // Where the point tip crushes a soft block's surface before the puncture, the puncture is
  // located on the warp of its segment's start (docs/tissue_3d.md, Model): measured 6.3 um.
  constexpr double kCrushedSurfaceSeedTol_m = kLooseEventTol_m;
  constexpr double kDepth_m = 0.04;
  LongMoveBlock b;
  Fixture& f = b.f;
  int default_updates = 0, loose_updates = 0;
  const Vector3 settled = b.implant(kDepth_m, true, kDefaultEventTol_m, &default_updates);
  const Vector3 loose = b.implant(kDepth_m, true, kLooseEventTol_m, &loose_updates);
  ASSERT_TRUE(settled.allFinite() && loose.allFinite());
  EXPECT_LT((settled - loose).norm(), kSeedTol_m) << (settled - loose).transpose() * 1e3 << " mm";
  EXPECT_LT(loose_updates, default_updates) << loose_updates << " against " << default_updates;
  // The soft block, whose point tip crushes the surface before the puncture (the hard case).
  Fixture soft_default(softCorotationalScene()), soft_loose(softCorotationalScene());
  const Vector3 soft_settled = softImplant(soft_default.model, soft_default.scene, 0.03, 1e-3);
  const Vector3 soft =
      softImplant(soft_loose.model, soft_loose.scene, 0.03, 1e-3, kLooseEventTol_m);
  ASSERT_TRUE(soft_settled.allFinite() && soft.allFinite());
  EXPECT_LT((soft_settled - soft).norm(), kCrushedSurfaceSeedTol_m)
      << (soft_settled - soft).transpose() * 1e3 << " mm";
  // Refused: no tolerance.
  EXPECT_THROW(NeedleInsertion3(f.model, f.scene.needle, f.scene.block_min_m.x(), kDepth_m, 0.0),
               std::invalid_argument);
}

TEST(Tissue3dCorotation, RotationFadesBeyondTheSmallStrainRange) {
  const Eigen::Matrix3d r = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).matrix();
  // Sound: the polar rotation itself.
  const Eigen::Matrix3d sound = r * Eigen::Vector3d(1.1, 0.95, 1.0).asDiagonal();
  EXPECT_LT((fem::elementRotation<3>(sound) - r).norm(), 1e-9);
  // Inverted or crushed: no rotation (the linear element).
  const Eigen::Matrix3d inverted = r * Eigen::Vector3d(1.0, 1.0, -0.2).asDiagonal();
  EXPECT_LT((fem::elementRotation<3>(inverted) - Eigen::Matrix3d::Identity()).norm(), 1e-12);
  // Strained far beyond the small-strain range: none either; in between a proper rotation.
  const Eigen::Matrix3d stretched = r * Eigen::Vector3d(2.5, 1.0, 1.0).asDiagonal();
  EXPECT_LT((fem::elementRotation<3>(stretched) - Eigen::Matrix3d::Identity()).norm(), 1e-12);
  const Eigen::Matrix3d between = r * Eigen::Vector3d(1.5, 1.0, 1.0).asDiagonal();
  const Eigen::Matrix3d q = fem::elementRotation<3>(between);
  EXPECT_NEAR(q.determinant(), 1.0, 1e-12);
  EXPECT_LT((q.transpose() * q - Eigen::Matrix3d::Identity()).norm(), 1e-12);
  EXPECT_GT((q - Eigen::Matrix3d::Identity()).norm(), 1e-3);
  EXPECT_GT((q - r).norm(), 1e-3);
  // Continuous: a small change of F changes the rotation little.
  const Eigen::Matrix3d nudged = r * Eigen::Vector3d(1.5 + 1e-6, 1.0, 1.0).asDiagonal();
  EXPECT_LT((fem::elementRotation<3>(nudged) - q).norm(), 1e-4);
}

TEST(Tissue3dCorotation, NewtonPolarRotationMatchesTheSvd) {
  // Newton's iteration stops once its change falls below 1e-7 (the next error is about half its
  // square): the rotation agrees with the SVD's polar rotation and is orthonormal to round-off,
  // from near-rigid tissue to stretches of 150 % and 80 % compression.
  constexpr double kRotationTol = 1e-12;
  const Eigen::Vector3d axis = Eigen::Vector3d(1, -2, 3).normalized();
  for (const double angle : {0.0, 0.05, 0.7, 2.5}) {
    for (const Eigen::Vector3d& stretch :
         {Eigen::Vector3d(1.0, 1.0, 1.0), Eigen::Vector3d(1.02, 0.99, 1.0),
          Eigen::Vector3d(1.3, 0.8, 1.1), Eigen::Vector3d(2.5, 1.0, 0.2)}) {
      const Eigen::Matrix3d r = Eigen::AngleAxisd(angle, axis).matrix();
      const Eigen::Matrix3d shear = Eigen::AngleAxisd(0.4, Eigen::Vector3d::UnitX()).matrix();
      const Eigen::Matrix3d f = r * shear * stretch.asDiagonal() * shear.transpose();
      const Eigen::Matrix3d q = fem::fastPolarRotation<3>(f);
      EXPECT_LT((q - fem::polarRotation<3>(f)).norm(), kRotationTol) << angle;
      EXPECT_LT((q - r).norm(), kRotationTol) << angle;  // the stretch is symmetric
      EXPECT_LT((q.transpose() * q - Eigen::Matrix3d::Identity()).norm(), kRotationTol);
    }
  }
}

TEST(Tissue3dCorotation, CorotatedForcesEqualTheElementStiffnessForm) {
  // The element pass forms each element's force from its stress (|e| sigma grad_a): it must
  // equal sum_e R K_e (R^T x - X) - R_0 K_e R_0^T u with the 12 x 12 element stiffness, against
  // the identity and against a warped reference, for a turned and strained beam (fixed seed).
  // g is the small difference of the corotated and the reference forces, so round-off relative
  // to it is about 1e-12 (measured 2e-12 on an 18.6k-tetrahedron scene).
  constexpr double kRelTol = 1e-10;
  constexpr double kFadingStrain = 0.1;  // random nodal displacements of 10 % of the height
  const TetMesh3 mesh = beamMesh(0.05, 0.006, 6);
  const std::vector<fem::Material> materials = {{1e4, 0.3}};
  std::srand(7);
  auto field = [&](double turn_rad, double strain) {
    const Eigen::Matrix3d r =
        Eigen::AngleAxisd(turn_rad, Eigen::Vector3d(1, 2, 3).normalized()).matrix();
    Eigen::VectorXd u(3 * mesh.nodeCount());
    for (int i = 0; i < mesh.nodeCount(); ++i) {
      const Vector3& x = mesh.nodes[static_cast<std::size_t>(i)];
      u.segment<3>(3 * i) = r * x - x + strain * 0.006 * Eigen::Vector3d::Random();
    }
    return u;
  };
  auto deformation = [&](int e, const Eigen::VectorXd& u) {
    const Eigen::Matrix<double, 4, 3> grad = fem::shapeGradients<3>(fem::corners<3>(mesh, e));
    Eigen::Matrix3d f = Eigen::Matrix3d::Identity();
    for (int a = 0; a < 4; ++a) {
      f += u.segment<3>(3 * mesh.elements[static_cast<std::size_t>(e)][a]) * grad.row(a);
    }
    return f;
  };
  // The correction with 12 x 12 element matrices; reference_u empty: identity references.
  auto expected = [&](const Eigen::VectorXd& u, const Eigen::VectorXd& reference_u) {
    Eigen::VectorXd g = Eigen::VectorXd::Zero(u.size());
    for (int e = 0; e < mesh.elementCount(); ++e) {
      const fem::Corners<3> c = fem::corners<3>(mesh, e);
      const fem::ElementMatrix<3> k = fem::elementStiffness<3>(c, materials[0]);
      const Eigen::Matrix3d r = fem::elementRotation<3>(deformation(e, u));
      const Eigen::Matrix3d r0 = reference_u.size() > 0
                                     ? fem::elementRotation<3>(deformation(e, reference_u))
                                     : Eigen::Matrix3d::Identity();
      Eigen::Matrix<double, 12, 1> local, ue0;
      const auto& nodes = mesh.elements[static_cast<std::size_t>(e)];
      for (int a = 0; a < 4; ++a) {
        const Eigen::Vector3d ua = u.segment<3>(3 * nodes[a]);
        local.segment<3>(3 * a) =
            r.transpose() * (c[static_cast<std::size_t>(a)] + ua) - c[static_cast<std::size_t>(a)];
        ue0.segment<3>(3 * a) = r0.transpose() * ua;
      }
      const Eigen::Matrix<double, 12, 1> kl = k * local, ku = k * ue0;
      for (int a = 0; a < 4; ++a) {
        g.segment<3>(3 * nodes[a]) += r * kl.segment<3>(3 * a) - r0 * ku.segment<3>(3 * a);
      }
    }
    return g;
  };
  fem::CorotationalForces<3> forces(mesh, materials);
  const Eigen::VectorXd u_warp = field(0.5, 0.02), u = field(0.7, 0.05);
  const Eigen::VectorXd g_identity = expected(u, Eigen::VectorXd());
  EXPECT_GT(g_identity.norm(), 0.0);
  EXPECT_LT((forces.correction(u) - g_identity).norm(), kRelTol * g_identity.norm());
  forces.warpedStiffness(u_warp);
  const Eigen::VectorXd g_warped = expected(u, u_warp);
  EXPECT_GT(g_warped.norm(), 0.0);
  EXPECT_LT((forces.correction(u) - g_warped).norm(), kRelTol * g_warped.norm());
  // Strained into the fade: the pass forms the force of an element with its whole polar
  // rotation from R^T F = S symmetric, that of a faded one (crushed, inverted or strained
  // beyond kSmallStrain) from the general stress; the field has both kinds (69 and 75 of the
  // 144 elements).
  const Eigen::VectorXd u_fading = field(0.7, kFadingStrain);
  int whole = 0;
  int faded = 0;
  for (int e = 0; e < mesh.elementCount(); ++e) {
    const Eigen::Matrix3d f = deformation(e, u_fading);
    const bool polar = f.determinant() > 0.0 &&
                       (fem::elementRotation<3>(f) - fem::polarRotation<3>(f)).norm() < 1e-9;
    (polar ? whole : faded) += 1;
  }
  EXPECT_GT(whole, 0);
  EXPECT_GT(faded, 0);
  const Eigen::VectorXd g_fading = expected(u_fading, u_warp);
  EXPECT_LT((forces.correction(u_fading) - g_fading).norm(), kRelTol * g_fading.norm());
}

TEST(Tissue3dCorotation, WarpedStiffnessAndItsFactor) {
  // Every element turned rigidly by 0.6 rad about z: the corotated forces vanish, so against
  // the warped stiffness at that turn the correction is exactly -K_R u; the compliance
  // re-factored with K_R solves K_R x = e_j on the free DOFs, like a fresh factorisation.
  constexpr double kTurn_rad = 0.6;
  constexpr double kRelTol = 1e-9;
  const TetMesh3 mesh = beamMesh(0.05, 0.006, 6);
  const std::vector<fem::Material> materials = {{1e4, 0.3}};
  const Eigen::Matrix3d r = Eigen::AngleAxisd(kTurn_rad, Eigen::Vector3d::UnitZ()).matrix();
  Eigen::VectorXd u(3 * mesh.nodeCount());
  for (int i = 0; i < mesh.nodeCount(); ++i) {
    const Vector3& x = mesh.nodes[static_cast<std::size_t>(i)];
    u.segment<3>(3 * i) = r * x - x;
  }
  fem::CorotationalForces<3> forces(mesh, materials);
  double turn_rad = -1.0;
  const Eigen::VectorXd g_linear = forces.correction(u, nullptr, &turn_rad);
  EXPECT_NEAR(turn_rad, kTurn_rad, 1e-9);  // against the identity: the turn itself
  const fem::SparseMatrix k = fem::assembleStiffness<3>(mesh, materials);
  EXPECT_LT((g_linear + k * u).norm(), kRelTol * (k * u).norm());  // f_int = 0: g = -K u
  const fem::SparseMatrix k_r = forces.warpedStiffness(u);
  EXPECT_EQ(forces.warpedElements(), mesh.elementCount());
  EXPECT_EQ(k_r.nonZeros(), k.nonZeros());
  const Eigen::VectorXd g = forces.correction(u, nullptr, &turn_rad);
  EXPECT_LT(turn_rad, 1e-6);  // the reference has the same turn
  EXPECT_LT((g + k_r * u).norm(), kRelTol * (k_r * u).norm());
  std::vector<char> fixed(static_cast<std::size_t>(3 * mesh.nodeCount()), 0);
  for (int i = 0; i < mesh.nodeCount(); ++i) {
    for (int d = 0; d < 3; ++d) {
      fixed[static_cast<std::size_t>(3 * i + d)] = mesh.node_fixed[static_cast<std::size_t>(i)];
    }
  }
  fem::CondensedCompliance compliance(k, fixed), fresh(k_r, fixed);
  const int dof = 3 * (mesh.nodeCount() - 1) + 1;
  compliance.require({dof});
  compliance.refactor(k_r);
  EXPECT_EQ(compliance.refactorCount(), 1);
  EXPECT_EQ(compliance.cachedColumns(), 0);  // the old columns are dropped
  compliance.require({dof});
  fresh.require({dof});
  EXPECT_LT((compliance.column(dof) - fresh.column(dof)).norm(),
            kRelTol * fresh.column(dof).norm());
  Eigen::VectorXd residual = k_r * compliance.column(dof);
  residual(dof) -= 1.0;
  for (int i = 0; i < residual.size(); ++i) {
    residual(i) = fixed[static_cast<std::size_t>(i)] ? 0.0 : residual(i);
  }
  EXPECT_LT(residual.norm(), kRelTol * k_r.norm());
  // A stiffness of another size is refused, naming both.
  EXPECT_THROW(compliance.refactor(fem::SparseMatrix(3, 3)), std::invalid_argument);
}

TEST(Tissue3dCorotation, SeedDoesNotDependOnTheWarpedReference) {
  // The corotational equilibrium is the fixed point whatever stiffness preconditions it: an
  // insertion on a tissue whose warped stiffness was taken at a rigid turn of the whole block
  // by 0.5 rad (a poor reference, re-warped during the insertion when the updates stall)
  // leaves the seed where the insertion from the linear stiffness does.
  constexpr double kReferenceTol_m = 1e-6;
  constexpr double kTurn_rad = 0.5;
  const Eigen::Vector2d lateral(1e-3, 2e-3);
  constexpr double kDepth_m = 0.036, kStep_m = 5e-4;
  auto insert = [&](TissueModel3& model, const TissueScene3d& scene, int* rewarps) {
    NeedleInsertion3 needle(model, scene.needle, 0.0, 0.04);
    for (double s = 0.0; s < kDepth_m - 1e-12;) {
      s = std::min(s + kStep_m, kDepth_m);
      std::string why;
      EXPECT_TRUE(needle.moveTo(lateral, s, &why)) << why;
      *rewarps += needle.lastMove().rewarps;
    }
    const int seed = needle.implantSeed().value();
    EXPECT_TRUE(needle.moveTo(lateral, -1e-3));
    return needle.seedWorld(seed);
  };
  Fixture a(corotationalScene()), b(corotationalScene());
  Eigen::VectorXd turn(3 * b.model.mesh().nodeCount());
  const Eigen::Matrix3d r = Eigen::AngleAxisd(kTurn_rad, Eigen::Vector3d::UnitY()).matrix();
  for (int i = 0; i < b.model.mesh().nodeCount(); ++i) {
    const Vector3& x = b.model.mesh().nodes[static_cast<std::size_t>(i)];
    turn.segment<3>(3 * i) = r * x - x;
  }
  b.model.embedding().warpReference(turn);
  EXPECT_EQ(b.model.embedding().referenceVersion(), 1);
  int rewarps_a = 0, rewarps_b = 0;
  const Vector3 seed_a = insert(a.model, a.scene, &rewarps_a);
  const Vector3 seed_b = insert(b.model, b.scene, &rewarps_b);
  ASSERT_TRUE(seed_a.allFinite() && seed_b.allFinite());
  EXPECT_LT((seed_a - seed_b).norm(), kReferenceTol_m) << (seed_a - seed_b).transpose();
  EXPECT_GT(rewarps_b, 0);  // the poor reference was replaced
}

TEST(Tissue3dCorotation, LinearModelOfCorotationalTissueIsTheLinearTissue) {
  // A needle moving in the linear model of corotational tissue (useLinearModel: the reference
  // stiffness alone, on the shared factor and columns) goes where a needle in linear tissue of
  // the same mesh goes; once the reference is re-warped its moves are refused, state unchanged.
  constexpr double kSameTol_m = 1e-9;  // round-off of two factorisations of the same K
  const Eigen::Vector2d lateral(1e-3, 2e-3);
  constexpr double kDepth_m = 0.03, kStep_m = 2e-3;
  TissueScene3d linear_scene = corotationalScene();
  linear_scene.corotational = false;
  Fixture corotational(corotationalScene()), linear(linear_scene);
  ASSERT_TRUE(corotational.model.corotational());
  ASSERT_FALSE(linear.model.corotational());
  NeedleInsertion3 a(corotational.model, corotational.scene.needle, 0.0, 0.04);
  NeedleInsertion3 b(linear.model, linear.scene.needle, 0.0, 0.04);
  a.useLinearModel();
  for (double s = 0.0; s < kDepth_m - 1e-12;) {
    s = std::min(s + kStep_m, kDepth_m);
    std::string why;
    ASSERT_TRUE(a.moveTo(lateral, s, &why)) << why;
    ASSERT_TRUE(b.moveTo(lateral, s, &why)) << why;
    EXPECT_EQ(a.lastMove().corotation_updates, 0);
    EXPECT_LT((a.tipReference() - b.tipReference()).norm(), kSameTol_m) << s;
  }
  ASSERT_TRUE(a.punctured());
  corotational.model.embedding().warpReference(
      Eigen::VectorXd::Zero(3 * corotational.model.mesh().nodeCount()));
  const Vector3 before = a.tipReference();
  std::string why;
  EXPECT_FALSE(a.moveTo(lateral, kDepth_m + kStep_m, &why));
  EXPECT_NE(why.find("linear model"), std::string::npos) << why;
  EXPECT_EQ(a.tipReference(), before);
}

}  // namespace
}  // namespace needle_guidance::tissue_3d

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
