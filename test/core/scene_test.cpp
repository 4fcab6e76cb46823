// Scene loading: the embedded defaults, unit conversion, and one refusal per validation rule.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>

#include "needle_guidance/math.h"
#include "needle_guidance/scene/embedded_scenes.h"
#include "needle_guidance/scene/scene.h"

namespace needle_guidance::scene {
namespace {

namespace fs = std::filesystem;

constexpr double kTol_m = 1e-12;
constexpr double kTol_Pa = 1e-9;
constexpr double kTol_rad = 1e-12;

// A small valid tissue scene; each refusal test changes one line of it.
const std::string kBase = R"(scene:
  name: test
workspace:
  min_cm: [0, 0]
  max_cm: [6, 6]
  background_material: fat
models:
  tissue: quasi_static
materials:
  - name: fat
    young_modulus_kPa: 30
    poisson_ratio: 0.49
  - name: prostate
    young_modulus_kPa: 60
    poisson_ratio: 0.49
regions:
  - name: prostate
    material: prostate
    polygon_cm: [[2, 2], [4, 2], [4, 4], [2, 4]]
boundary:
  - name: bottom
    condition: fixed
    from_cm: [0, 0]
    to_cm: [6, 0]
needle:
  min_height_cm: 0.5
  max_height_cm: 5.5
  max_depth_cm: 5.5
targets:
  - name: t1
    position_cm: [3, 3]
    radius_mm: 1
)";

// A small valid steering scene.
const std::string kSteeringBase = R"(scene:
  name: steer
workspace:
  min_cm: [0, 0]
  max_cm: [10, 10]
models:
  tissue: none
  steering: true
needle:
  min_height_cm: 0
  max_height_cm: 10
  max_depth_cm: 10
  radius_of_curvature_cm: 5
targets:
  - name: goal
    position_cm: [8.5, 5]
    radius_cm: 0.5
obstacles:
  - name: block
    polygon_cm: [[4, 4], [6, 4], [6, 6], [4, 6]]
    clearance_mm: 1
steering:
  grid_spacing_cm: 0.1
  orientations: 40
  sigma_insert_deg: 5
  sigma_flip_deg: 10
)";

/// `text` with its unique occurrence of `from` replaced by `to`.
std::string edit(const std::string& text, const std::string& from, const std::string& to) {
  const std::size_t at = text.find(from);
  EXPECT_NE(at, std::string::npos) << "test bug: '" << from << "' not in the base scene";
  EXPECT_EQ(text.find(from, at + 1), std::string::npos) << "test bug: '" << from << "' twice";
  if (at == std::string::npos) {
    return text;
  }
  return text.substr(0, at) + to + text.substr(at + from.size());
}

/// The SceneError that parsing `text` throws (a failure if it throws none).
SceneError parseError(const std::string& text) {
  try {
    parseScene(text, "test.yaml");
  } catch (const SceneError& e) {
    EXPECT_EQ(e.file(), "test.yaml");
    EXPECT_EQ(std::string(e.what()).find('\n'), std::string::npos) << e.what();
    return e;
  }
  ADD_FAILURE() << "expected a SceneError";
  return SceneError("", "", "", "");
}

bool contains(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

void expectPolygonsEqual(const Polygon& a, const Polygon& b) {
  ASSERT_EQ(a.size(), b.size());
  for (std::size_t i = 0; i < a.size(); ++i) {
    EXPECT_TRUE(a.vertices()[i].isApprox(b.vertices()[i], kTol_m)) << "vertex " << i;
  }
}

void expectScenesEqual(const Scene& a, const Scene& b) {
  EXPECT_EQ(a.name, b.name);
  EXPECT_EQ(a.description, b.description);
  EXPECT_EQ(a.workspace_min, b.workspace_min);
  EXPECT_EQ(a.workspace_max, b.workspace_max);
  EXPECT_EQ(a.background_material, b.background_material);
  EXPECT_EQ(a.models.tissue, b.models.tissue);
  EXPECT_EQ(a.models.corotational, b.models.corotational);
  EXPECT_EQ(a.models.steering, b.models.steering);
  ASSERT_EQ(a.materials.size(), b.materials.size());
  for (std::size_t i = 0; i < a.materials.size(); ++i) {
    EXPECT_EQ(a.materials[i].name, b.materials[i].name);
    EXPECT_EQ(a.materials[i].young_modulus_Pa, b.materials[i].young_modulus_Pa);
    EXPECT_EQ(a.materials[i].poisson_ratio, b.materials[i].poisson_ratio);
    EXPECT_EQ(a.materials[i].density_kg_m3, b.materials[i].density_kg_m3);
    EXPECT_EQ(a.materials[i].rayleigh_alpha_per_s, b.materials[i].rayleigh_alpha_per_s);
    EXPECT_EQ(a.materials[i].rayleigh_beta_s, b.materials[i].rayleigh_beta_s);
  }
  ASSERT_EQ(a.regions.size(), b.regions.size());
  for (std::size_t i = 0; i < a.regions.size(); ++i) {
    EXPECT_EQ(a.regions[i].name, b.regions[i].name);
    EXPECT_EQ(a.regions[i].material, b.regions[i].material);
    EXPECT_EQ(a.regions[i].rigid, b.regions[i].rigid);
    expectPolygonsEqual(a.regions[i].polygon, b.regions[i].polygon);
  }
  ASSERT_EQ(a.boundary.size(), b.boundary.size());
  for (std::size_t i = 0; i < a.boundary.size(); ++i) {
    EXPECT_EQ(a.boundary[i].name, b.boundary[i].name);
    EXPECT_EQ(a.boundary[i].condition, b.boundary[i].condition);
    EXPECT_EQ(a.boundary[i].segment.a, b.boundary[i].segment.a);
    EXPECT_EQ(a.boundary[i].segment.b, b.boundary[i].segment.b);
  }
  EXPECT_EQ(a.needle.min_height_m, b.needle.min_height_m);
  EXPECT_EQ(a.needle.max_height_m, b.needle.max_height_m);
  EXPECT_EQ(a.needle.max_depth_m, b.needle.max_depth_m);
  EXPECT_EQ(a.needle.insertion_velocity_m_s, b.needle.insertion_velocity_m_s);
  EXPECT_EQ(a.needle.cutting_force_N, b.needle.cutting_force_N);
  EXPECT_EQ(a.needle.cut_length_m, b.needle.cut_length_m);
  EXPECT_EQ(a.needle.static_friction_N_per_m, b.needle.static_friction_N_per_m);
  EXPECT_EQ(a.needle.kinetic_friction_N_per_m, b.needle.kinetic_friction_N_per_m);
  EXPECT_EQ(a.needle.stick_velocity_m_s, b.needle.stick_velocity_m_s);
  EXPECT_EQ(a.needle.radius_of_curvature_m, b.needle.radius_of_curvature_m);
  ASSERT_EQ(a.targets.size(), b.targets.size());
  for (std::size_t i = 0; i < a.targets.size(); ++i) {
    EXPECT_EQ(a.targets[i].name, b.targets[i].name);
    EXPECT_EQ(a.targets[i].position, b.targets[i].position);
    EXPECT_EQ(a.targets[i].radius_m, b.targets[i].radius_m);
  }
  ASSERT_EQ(a.obstacles.size(), b.obstacles.size());
  for (std::size_t i = 0; i < a.obstacles.size(); ++i) {
    EXPECT_EQ(a.obstacles[i].name, b.obstacles[i].name);
    EXPECT_EQ(a.obstacles[i].clearance_m, b.obstacles[i].clearance_m);
    expectPolygonsEqual(a.obstacles[i].polygon, b.obstacles[i].polygon);
  }
  EXPECT_EQ(a.imaging.modality, b.imaging.modality);
  EXPECT_EQ(a.imaging.pixel_size_m, b.imaging.pixel_size_m);
  EXPECT_EQ(a.imaging.frame_rate_hz, b.imaging.frame_rate_hz);
  EXPECT_EQ(a.imaging.noise_std, b.imaging.noise_std);
  EXPECT_EQ(a.imaging.blur_sigma_m, b.imaging.blur_sigma_m);
  EXPECT_EQ(a.imaging.drop_probability, b.imaging.drop_probability);
  EXPECT_EQ(a.imaging.reference_image, b.imaging.reference_image);
  EXPECT_EQ(a.mesh.max_edge_m, b.mesh.max_edge_m);
  EXPECT_EQ(a.mesh.min_edge_m, b.mesh.min_edge_m);
  EXPECT_EQ(a.mesh.grading_length_m, b.mesh.grading_length_m);
  EXPECT_EQ(a.mesh.min_angle_deg, b.mesh.min_angle_deg);
  EXPECT_EQ(a.mesh.refine_targets, b.mesh.refine_targets);
  ASSERT_EQ(a.steering.has_value(), b.steering.has_value());
  if (a.steering) {
    EXPECT_EQ(a.steering->grid_spacing_m, b.steering->grid_spacing_m);
    EXPECT_EQ(a.steering->orientations, b.steering->orientations);
    EXPECT_EQ(a.steering->sigma_insert_rad, b.steering->sigma_insert_rad);
    EXPECT_EQ(a.steering->sigma_flip_rad, b.steering->sigma_flip_rad);
    EXPECT_EQ(a.steering->start_x_m, b.steering->start_x_m);
  }
}

/// True if the polygon has a reflex vertex (it is counter-clockwise after loading).
bool isNonConvex(const Polygon& polygon) {
  const std::size_t n = polygon.size();
  for (std::size_t i = 0; i < n; ++i) {
    const Point2& a = polygon.vertices()[i];
    const Point2& b = polygon.vertices()[(i + 1) % n];
    const Point2& c = polygon.vertices()[(i + 2) % n];
    const Point2 u = b - a;
    const Point2 v = c - b;
    if (u.x() * v.y() - u.y() * v.x() < 0.0) {
      return true;
    }
  }
  return false;
}

// ---- valid scenes ------------------------------------------------------------------------------

TEST(SceneTest, BaseScenesParse) {
  const Scene tissue = parseScene(kBase, "base.yaml");
  EXPECT_EQ(tissue.name, "test");
  EXPECT_EQ(tissue.source, "base.yaml");
  EXPECT_TRUE(tissue.hasTissue());
  EXPECT_NEAR(tissue.material("prostate").young_modulus_Pa, 60e3, kTol_Pa);
  EXPECT_THROW(tissue.material("bone"), std::out_of_range);
  EXPECT_NEAR(tissue.target("t1").radius_m, 1e-3, kTol_m);
  EXPECT_THROW(tissue.target("t2"), std::out_of_range);
  EXPECT_FALSE(tissue.steering.has_value());

  const Scene steering = parseScene(kSteeringBase, "steer.yaml");
  EXPECT_FALSE(steering.hasTissue());
  EXPECT_TRUE(steering.materials.empty());
  EXPECT_TRUE(steering.regions.empty());
  ASSERT_TRUE(steering.steering.has_value());
  EXPECT_EQ(steering.steering->start_x_m, 0.0);  // defaults to the workspace's left edge
  EXPECT_EQ(steering.steering->orientation_subdivision, 1);  // 5.4.2 unless asked for
  const Scene finer = parseScene(
      edit(kSteeringBase, "orientations: 40", "orientations: 40\n  orientation_subdivision: 2"),
      "finer.yaml");
  EXPECT_EQ(finer.steering->orientation_subdivision, 2);
  EXPECT_NEAR(steering.steering->ps_tolerance, 0.01, 1e-12);  // the default (docs/scenes.md)
  const Scene fixed = parseScene(
      edit(kSteeringBase, "orientations: 40", "orientations: 40\n  ps_tolerance: 0"), "fixed.yaml");
  EXPECT_EQ(fixed.steering->ps_tolerance, 0.0);
}

TEST(SceneTest, EmbeddedProstateSagittal) {
  const Scene scene = defaultScene("prostate_sagittal");
  EXPECT_EQ(scene.name, "prostate_sagittal");
  EXPECT_EQ(scene.source, "<embedded:prostate_sagittal>");
  EXPECT_TRUE(scene.workspace_min.isApprox(Point2(0.0, 0.0)));
  EXPECT_TRUE(scene.workspace_max.isApprox(Point2(0.06, 0.06), kTol_m));
  EXPECT_EQ(scene.background_material, "fat");
  EXPECT_EQ(scene.models.tissue, TissueModel::kQuasiStatic);
  EXPECT_FALSE(scene.models.corotational);
  EXPECT_FALSE(scene.models.steering);
  EXPECT_FALSE(scene.steering.has_value());

  EXPECT_NEAR(scene.material("prostate").young_modulus_Pa, 60e3, kTol_Pa);
  EXPECT_NEAR(scene.material("fat").young_modulus_Pa, 30e3, kTol_Pa);
  EXPECT_DOUBLE_EQ(scene.material("prostate").poisson_ratio, 0.49);
  EXPECT_DOUBLE_EQ(scene.material("fat").density_kg_m3, 1000.0);

  ASSERT_EQ(scene.regions.size(), 1u);
  const Region& prostate = scene.regions[0];
  EXPECT_EQ(prostate.material, "prostate");
  EXPECT_FALSE(prostate.rigid);
  EXPECT_EQ(prostate.polygon.size(), 20u);
  EXPECT_TRUE(prostate.polygon.isCounterClockwise());
  const double width_m = prostate.polygon.maxCorner().x() - prostate.polygon.minCorner().x();
  EXPECT_NEAR(width_m, 0.03, 0.003);

  ASSERT_EQ(scene.targets.size(), 12u);
  for (std::size_t i = 0; i < scene.targets.size(); ++i) {
    const Target& target = scene.targets[i];
    EXPECT_EQ(target.name, (i < 9 ? "t0" : "t1") + std::to_string((i + 1) % 10));
    EXPECT_TRUE(prostate.polygon.contains(target.position)) << target.name;
    EXPECT_NEAR(target.radius_m, 1e-3, kTol_m);
  }

  ASSERT_EQ(scene.boundary.size(), 4u);
  EXPECT_EQ(scene.boundaryConditionAt(Point2(0.0, 0.03)), BoundaryCondition::kFree);
  EXPECT_EQ(scene.boundaryConditionAt(Point2(0.03, 0.0)), BoundaryCondition::kFixed);
  EXPECT_EQ(scene.boundaryConditionAt(Point2(0.06, 0.03)), BoundaryCondition::kFixed);
  EXPECT_EQ(scene.boundaryConditionAt(Point2(0.03, 0.06)), BoundaryCondition::kFixed);
  EXPECT_EQ(scene.boundaryConditionAt(Point2(0.0, 0.0)), BoundaryCondition::kFixed);

  EXPECT_NEAR(scene.needle.min_height_m, 0.005, kTol_m);
  EXPECT_NEAR(scene.needle.max_height_m, 0.055, kTol_m);
  EXPECT_NEAR(scene.needle.max_depth_m, 0.055, kTol_m);
  EXPECT_NEAR(scene.needle.insertion_velocity_m_s, 0.01, kTol_m);
  EXPECT_NEAR(scene.needle.cut_length_m, 1e-4, kTol_m);
  EXPECT_NEAR(scene.needle.diameter_m, 1.27e-3, kTol_m);
  EXPECT_NEAR(scene.needle.static_friction_N_per_m, 30.0, 1e-9);  // 0.3 N/cm
  EXPECT_NEAR(scene.needle.stick_velocity_m_s, 5e-4, kTol_m);
  EXPECT_DOUBLE_EQ(scene.needle.cutting_force_N, 1.0);
  EXPECT_NEAR(scene.thickness_m, 0.01, kTol_m);  // thickness_cm: 1.0
  EXPECT_EQ(scene.needle.radius_of_curvature_m, 0.0);

  EXPECT_EQ(scene.imaging.modality, "ultrasound");
  EXPECT_NEAR(scene.imaging.pixel_size_m, 2e-4, kTol_m);
  EXPECT_DOUBLE_EQ(scene.imaging.frame_rate_hz, 30.0);
  EXPECT_NEAR(scene.mesh.max_edge_m, 4.5e-3, kTol_m);
  EXPECT_NEAR(scene.mesh.min_edge_m, 1.5e-3, kTol_m);
  EXPECT_TRUE(scene.mesh.refine_targets);
  EXPECT_NEAR(scene.mesh.grading_length_m, 0.01, kTol_m);
  EXPECT_DOUBLE_EQ(scene.mesh.min_angle_deg, 25.0);
}

TEST(SceneTest, EmbeddedSteeringWorkspace) {
  const Scene scene = defaultScene("steering_workspace");
  EXPECT_EQ(scene.models.tissue, TissueModel::kNone);
  EXPECT_TRUE(scene.models.steering);
  EXPECT_TRUE(scene.workspace_max.isApprox(Point2(0.1, 0.1), kTol_m));
  EXPECT_TRUE(scene.materials.empty());
  EXPECT_TRUE(scene.regions.empty());

  ASSERT_EQ(scene.targets.size(), 1u);
  EXPECT_TRUE(scene.targets[0].position.isApprox(Point2(0.085, 0.05), kTol_m));
  EXPECT_NEAR(scene.targets[0].radius_m, 0.005, kTol_m);

  ASSERT_GE(scene.obstacles.size(), 3u);
  ASSERT_LE(scene.obstacles.size(), 5u);
  int non_convex = 0;
  for (const Obstacle& obstacle : scene.obstacles) {
    EXPECT_NEAR(obstacle.clearance_m, 1e-3, kTol_m);
    EXPECT_TRUE(obstacle.polygon.isCounterClockwise());
    non_convex += isNonConvex(obstacle.polygon) ? 1 : 0;
  }
  EXPECT_GE(non_convex, 1);

  // Figure 5.5: a narrow gap between two obstacles, open even after both clearances.
  double narrowest_gap_m = 1.0;
  for (const Obstacle& a : scene.obstacles) {
    for (const Obstacle& b : scene.obstacles) {
      if (&a == &b) {
        continue;
      }
      for (const Point2& v : a.polygon.vertices()) {
        narrowest_gap_m = std::min(narrowest_gap_m, b.polygon.distanceToBoundary(v));
      }
    }
  }
  EXPECT_LT(narrowest_gap_m, 0.01);
  EXPECT_GT(narrowest_gap_m, 2 * 1e-3);

  EXPECT_NEAR(scene.needle.radius_of_curvature_m, 0.05, kTol_m);
  EXPECT_NEAR(scene.needle.max_depth_m, 0.1, kTol_m);
  EXPECT_NEAR(scene.needle.min_height_m, 0.0, kTol_m);
  EXPECT_NEAR(scene.needle.max_height_m, 0.1, kTol_m);

  ASSERT_TRUE(scene.steering.has_value());
  EXPECT_NEAR(scene.steering->grid_spacing_m, 1.4e-3, kTol_m);  // the coarsest of the ladder
  EXPECT_NEAR(scene.steering->ps_tolerance, 0.005, 1e-12);
  EXPECT_EQ(scene.steering->orientations, 40);
  EXPECT_EQ(scene.steering->orientation_subdivision, 3);
  EXPECT_EQ(scene.steering->transition_model, "interpolated");
  EXPECT_NEAR(scene.steering->sigma_insert_rad, 5.0 * kPi / 180.0, kTol_rad);
  EXPECT_NEAR(scene.steering->sigma_flip_rad, 10.0 * kPi / 180.0, kTol_rad);
  EXPECT_EQ(scene.steering->start_x_m, 0.0);

  EXPECT_EQ(scene.imaging.modality, "fluoroscopy");
  EXPECT_NEAR(scene.imaging.pixel_size_m, 2e-4, kTol_m);
  EXPECT_DOUBLE_EQ(scene.imaging.frame_rate_hz, 15.0);
}

TEST(SceneTest, DefaultSceneNamesAndUnknownName) {
  const std::vector<std::string> names = defaultSceneNames();
  EXPECT_NE(std::find(names.begin(), names.end(), "prostate_sagittal"), names.end());
  EXPECT_NE(std::find(names.begin(), names.end(), "steering_workspace"), names.end());
  EXPECT_THROW(defaultScene("no_such_scene"), std::invalid_argument);
}

TEST(SceneTest, ConfigFilesEqualEmbeddedScenes) {
  for (const auto& [name, text] : embeddedSceneFiles()) {
    SCOPED_TRACE(name);
    const Scene from_file = loadScene("config/scenes/" + name + ".yaml");
    EXPECT_EQ(from_file.source, "config/scenes/" + name + ".yaml");
    expectScenesEqual(from_file, defaultScene(name));
  }
}

TEST(SceneTest, LoadSceneSpecByNameAndByPath) {
  EXPECT_EQ(loadSceneSpec("prostate_sagittal").source, "<embedded:prostate_sagittal>");
  const std::string relative = "config/scenes/steering_workspace.yaml";
  EXPECT_EQ(loadSceneSpec(relative).source, relative);
  const std::string absolute = std::string(NG_SOURCE_DIR) + "/" + relative;
  const Scene scene = loadSceneSpec(absolute);
  EXPECT_EQ(scene.source, absolute);
  EXPECT_EQ(scene.name, "steering_workspace");
  EXPECT_THROW(loadSceneSpec("not_a_scene"), SceneError);
  EXPECT_THROW(loadSceneSpec("missing/dir/scene.yaml"), SceneError);
}

TEST(SceneTest, UnitVariantsGiveTheSameSiValues) {
  const Scene cm = parseScene(kBase, "cm.yaml");
  std::string mm_text = edit(kBase, "position_cm: [3, 3]", "position_mm: [30, 30]");
  mm_text = edit(mm_text, "radius_mm: 1", "radius_cm: 0.1");
  mm_text = edit(mm_text, "max_depth_cm: 5.5", "max_depth_mm: 55");
  mm_text = edit(mm_text, "min_height_cm: 0.5", "min_height_m: 0.005");
  mm_text = edit(mm_text, "young_modulus_kPa: 60", "young_modulus_Pa: 60000");
  mm_text = edit(mm_text, "polygon_cm: [[2, 2], [4, 2], [4, 4], [2, 4]]",
                 "polygon_mm: [[20, 20], [40, 20], [40, 40], [20, 40]]");
  const Scene mm = parseScene(mm_text, "mm.yaml");
  EXPECT_TRUE(mm.targets[0].position.isApprox(cm.targets[0].position, kTol_m));
  EXPECT_TRUE(mm.targets[0].position.isApprox(Point2(0.03, 0.03), kTol_m));
  EXPECT_NEAR(mm.targets[0].radius_m, cm.targets[0].radius_m, kTol_m);
  EXPECT_NEAR(mm.needle.max_depth_m, cm.needle.max_depth_m, kTol_m);
  EXPECT_NEAR(mm.needle.min_height_m, cm.needle.min_height_m, kTol_m);
  EXPECT_NEAR(mm.material("prostate").young_modulus_Pa, cm.material("prostate").young_modulus_Pa,
              kTol_Pa);
  for (std::size_t i = 0; i < 4; ++i) {
    EXPECT_TRUE(
        mm.regions[0].polygon.vertices()[i].isApprox(cm.regions[0].polygon.vertices()[i], kTol_m));
  }

  std::string rad_text =
      edit(kSteeringBase, "sigma_insert_deg: 5", "sigma_insert_rad: 0.08726646259971647");
  rad_text = edit(rad_text, "grid_spacing_cm: 0.1", "grid_spacing_mm: 1");
  const Scene deg = parseScene(kSteeringBase, "deg.yaml");
  const Scene rad = parseScene(rad_text, "rad.yaml");
  EXPECT_NEAR(deg.steering->sigma_insert_rad, rad.steering->sigma_insert_rad, kTol_rad);
  EXPECT_NEAR(deg.steering->grid_spacing_m, rad.steering->grid_spacing_m, kTol_m);

  const Scene velocity = parseScene(
      edit(kBase, "  max_depth_cm: 5.5\n", "  max_depth_cm: 5.5\n  insertion_velocity_mm_s: 10\n"),
      "v.yaml");
  EXPECT_NEAR(velocity.needle.insertion_velocity_m_s, 0.01, kTol_m);
}

TEST(SceneTest, ClosingVertexIsAcceptedAndPolygonsBecomeCounterClockwise) {
  const Scene scene = parseScene(edit(kBase, "polygon_cm: [[2, 2], [4, 2], [4, 4], [2, 4]]",
                                      "polygon_cm: [[2, 2], [2, 4], [4, 4], [4, 2], [2, 2]]"),
                                 "closed.yaml");
  EXPECT_EQ(scene.regions[0].polygon.size(), 4u);
  EXPECT_TRUE(scene.regions[0].polygon.isCounterClockwise());
}

TEST(SceneTest, ReferenceImageIsResolvedRelativeToTheSceneFile) {
  const fs::path dir = fs::temp_directory_path() / "ng_scene_test_reference_image";
  fs::create_directories(dir / "images");
  std::ofstream(dir / "images" / "slice.png") << "not really a png";
  std::ofstream(dir / "scene.yaml") << kBase << "imaging:\n  reference_image: images/slice.png\n";
  const Scene scene = loadScene((dir / "scene.yaml").string());
  EXPECT_EQ(scene.imaging.reference_image, (dir / "images" / "slice.png").string());

  std::ofstream(dir / "missing.yaml") << kBase << "imaging:\n  reference_image: images/none.png\n";
  try {
    loadScene((dir / "missing.yaml").string());
    ADD_FAILURE() << "expected a SceneError";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.key(), "imaging.reference_image");
    EXPECT_EQ(e.value(), "images/none.png");
  }
  fs::remove_all(dir);
}

// ---- refusals: one per rule --------------------------------------------------------------------

TEST(SceneErrorTest, WhatIsOneLineWithFileKeyValueAndReason) {
  const SceneError e = parseError(edit(kBase, "poisson_ratio: 0.49\n  - name: prostate",
                                       "poisson_ratio: 0.5\n  - name: prostate"));
  EXPECT_EQ(e.key(), "materials[0].poisson_ratio");
  EXPECT_EQ(e.value(), "0.5");
  EXPECT_EQ(std::string(e.what()),
            "test.yaml: key 'materials[0].poisson_ratio' value '0.5': " + e.reason());
}

TEST(SceneErrorTest, FileCannotBeOpened) {
  try {
    loadScene("/nonexistent/dir/scene.yaml");
    ADD_FAILURE() << "expected a SceneError";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.file(), "/nonexistent/dir/scene.yaml");
    EXPECT_EQ(e.key(), "");
    EXPECT_TRUE(contains(e.reason(), "/nonexistent/dir/scene.yaml")) << e.what();
  }
}

TEST(SceneErrorTest, YamlSyntaxErrorReportsTheLine) {
  const SceneError e = parseError("scene:\n  name: test\nworkspace: [1, 2\nmodels: {}\n");
  EXPECT_EQ(e.key(), "");
  EXPECT_TRUE(contains(e.reason(), "YAML syntax error")) << e.what();
  EXPECT_TRUE(contains(e.reason(), "line ")) << e.what();
}

TEST(SceneErrorTest, MissingRequiredKey) {
  EXPECT_EQ(parseError(edit(kBase, "  max_depth_cm: 5.5\n", "")).key(), "needle.max_depth");
  EXPECT_EQ(parseError(edit(kBase, "  - name: t1\n", "  - \n")).key(), "targets[0].name");
  EXPECT_EQ(parseError(edit(kBase, "models:\n  tissue: quasi_static\n", "")).key(), "models");
  EXPECT_EQ(
      parseError(edit(kBase, "    poisson_ratio: 0.49\n  - name: prostate", "  - name: prostate"))
          .key(),
      "materials[0].poisson_ratio");
  // A misspelt required key is named in the reason.
  const SceneError typo = parseError(edit(kBase, "max_depth_cm: 5.5", "max_dept_cm: 5.5"));
  EXPECT_EQ(typo.key(), "needle.max_depth");
  EXPECT_TRUE(contains(typo.reason(), "max_dept_cm")) << typo.what();
}

TEST(SceneErrorTest, WrongType) {
  SceneError e = parseError(edit(kBase, "young_modulus_kPa: 30", "young_modulus_kPa: soft"));
  EXPECT_EQ(e.key(), "materials[0].young_modulus_kPa");
  EXPECT_EQ(e.value(), "soft");
  e = parseError(edit(kBase, "polygon_cm: [[2, 2], [4, 2], [4, 4], [2, 4]]", "polygon_cm: 5"));
  EXPECT_EQ(e.key(), "regions[0].polygon_cm");
  e = parseError(edit(kBase, "position_cm: [3, 3]", "position_cm: [3, 3, 3]"));
  EXPECT_EQ(e.key(), "targets[0].position_cm");
  e = parseError(edit(kBase, "max_depth_cm: 5.5", "max_depth_cm: \"5.5\""));
  EXPECT_EQ(e.key(), "needle.max_depth_cm");
  e = parseError(edit(kBase, "models:\n  tissue: quasi_static\n", "models: quasi_static\n"));
  EXPECT_EQ(e.key(), "models");
  e = parseError(edit(kBase, "polygon_cm: [[2, 2], [4, 2], [4, 4], [2, 4]]",
                      "polygon_cm: [[2, 2], [4, x], [4, 4], [2, 4]]"));
  EXPECT_EQ(e.key(), "regions[0].polygon_cm[1][1]");
  e = parseError(edit(kBase, "targets:\n", "targets: t1\nunused:\n"));
  EXPECT_EQ(e.key(), "targets");
  e = parseError(edit(kSteeringBase, "orientations: 40", "orientations: 40.5"));
  EXPECT_EQ(e.key(), "steering.orientations");
  e = parseError(edit(kBase, "tissue: quasi_static", "tissue: quasi_static\n  corotational: 3"));
  EXPECT_EQ(e.key(), "models.corotational");
}

TEST(SceneErrorTest, PolygonWithTooFewVertices) {
  const SceneError e = parseError(
      edit(kBase, "polygon_cm: [[2, 2], [4, 2], [4, 4], [2, 4]]", "polygon_cm: [[2, 2], [4, 2]]"));
  EXPECT_EQ(e.key(), "regions[0].polygon_cm");
  EXPECT_TRUE(contains(e.reason(), "at least 3")) << e.what();
}

TEST(SceneErrorTest, DegeneratePolygon) {
  SceneError e = parseError(edit(kBase, "polygon_cm: [[2, 2], [4, 2], [4, 4], [2, 4]]",
                                 "polygon_cm: [[2, 2], [3, 2], [4, 2]]"));
  EXPECT_EQ(e.key(), "regions[0].polygon_cm");
  EXPECT_TRUE(contains(e.reason(), "zero area")) << e.what();
  e = parseError(edit(kBase, "polygon_cm: [[2, 2], [4, 2], [4, 4], [2, 4]]",
                      "polygon_cm: [[2, 2], [4, 2], [4, 2], [4, 4], [2, 4]]"));
  EXPECT_EQ(e.key(), "regions[0].polygon_cm[2]");
  EXPECT_TRUE(contains(e.reason(), "zero-length edge")) << e.what();
}

TEST(SceneErrorTest, SelfIntersectingPolygonNamesTheEdges) {
  const SceneError e = parseError(edit(kBase, "polygon_cm: [[2, 2], [4, 2], [4, 4], [2, 4]]",
                                       "polygon_cm: [[2, 2], [4, 4], [4, 2], [2, 4]]"));
  EXPECT_EQ(e.key(), "regions[0].polygon_cm");
  EXPECT_TRUE(contains(e.reason(), "self-intersects")) << e.what();
  EXPECT_TRUE(contains(e.reason(), "edge 0")) << e.what();
  EXPECT_TRUE(contains(e.reason(), "edge 2")) << e.what();
  const SceneError obstacle =
      parseError(edit(kSteeringBase, "polygon_cm: [[4, 4], [6, 4], [6, 6], [4, 6]]",
                      "polygon_cm: [[4, 4], [6, 6], [6, 4], [4, 6]]"));
  EXPECT_EQ(obstacle.key(), "obstacles[0].polygon_cm");
}

TEST(SceneErrorTest, OverlappingRegionsNameBoth) {
  const SceneError e = parseError(edit(kBase, "boundary:\n",
                                       "  - name: lesion\n"
                                       "    material: fat\n"
                                       "    polygon_cm: [[3.5, 3.5], [5, 3.5], [5, 5], [3.5, 5]]\n"
                                       "boundary:\n"));
  EXPECT_EQ(e.key(), "regions[1].polygon_cm");
  EXPECT_TRUE(contains(e.reason(), "'lesion'")) << e.what();
  EXPECT_TRUE(contains(e.reason(), "'prostate'")) << e.what();
}

TEST(SceneErrorTest, RegionOutsideTheWorkspace) {
  const SceneError e = parseError(edit(kBase, "polygon_cm: [[2, 2], [4, 2], [4, 4], [2, 4]]",
                                       "polygon_cm: [[2, 2], [7, 2], [4, 4], [2, 4]]"));
  EXPECT_EQ(e.key(), "regions[0].polygon_cm[1]");
  EXPECT_EQ(e.value(), "[7, 2]");
}

TEST(SceneErrorTest, TargetOutsideTheWorkspace) {
  const SceneError e = parseError(edit(kBase, "position_cm: [3, 3]", "position_cm: [6.5, 3]"));
  EXPECT_EQ(e.key(), "targets[0].position_cm");
  EXPECT_TRUE(contains(e.reason(), "outside the workspace")) << e.what();
}

TEST(SceneErrorTest, TargetInsideARigidRegion) {
  const SceneError e = parseError(
      edit(kBase, "    material: prostate\n", "    material: prostate\n    rigid: true\n"));
  EXPECT_EQ(e.key(), "targets[0].position_cm");
  EXPECT_TRUE(contains(e.reason(), "rigid region 'prostate'")) << e.what();
}

TEST(SceneErrorTest, TargetInsideAnObstacle) {
  SceneError e = parseError(edit(kSteeringBase, "position_cm: [8.5, 5]", "position_cm: [5, 5]"));
  EXPECT_EQ(e.key(), "targets[0].position_cm");
  EXPECT_TRUE(contains(e.reason(), "obstacle 'block'")) << e.what();
  // Outside the polygon but within its clearance.
  e = parseError(edit(kSteeringBase, "position_cm: [8.5, 5]", "position_cm: [6.05, 5]"));
  EXPECT_EQ(e.key(), "targets[0].position_cm");
}

TEST(SceneErrorTest, NonPositiveStiffness) {
  EXPECT_EQ(parseError(edit(kBase, "young_modulus_kPa: 30", "young_modulus_kPa: 0")).key(),
            "materials[0].young_modulus_kPa");
  EXPECT_EQ(parseError(edit(kBase, "young_modulus_kPa: 60", "young_modulus_kPa: -60")).key(),
            "materials[1].young_modulus_kPa");
}

TEST(SceneErrorTest, PoissonRatioOutOfRange) {
  const std::string first = "poisson_ratio: 0.49\n  - name: prostate";
  EXPECT_EQ(parseError(edit(kBase, first, "poisson_ratio: 0.5\n  - name: prostate")).key(),
            "materials[0].poisson_ratio");
  EXPECT_EQ(parseError(edit(kBase, first, "poisson_ratio: -1\n  - name: prostate")).key(),
            "materials[0].poisson_ratio");
  EXPECT_NO_THROW(parseScene(edit(kBase, first, "poisson_ratio: -0.5\n  - name: prostate"), "ok"));
}

TEST(SceneErrorTest, NanAndInfAreRefused) {
  SceneError e = parseError(edit(kBase, "young_modulus_kPa: 30", "young_modulus_kPa: .nan"));
  EXPECT_EQ(e.key(), "materials[0].young_modulus_kPa");
  EXPECT_EQ(e.value(), ".nan");
  e = parseError(edit(kBase, "position_cm: [3, 3]", "position_cm: [.inf, 3]"));
  EXPECT_EQ(e.key(), "targets[0].position_cm[0]");
  e = parseError(edit(kBase, "max_depth_cm: 5.5", "max_depth_cm: -.inf"));
  EXPECT_EQ(e.key(), "needle.max_depth_cm");
}

TEST(SceneErrorTest, NegativeRadiusOrClearance) {
  EXPECT_EQ(parseError(edit(kBase, "radius_mm: 1", "radius_mm: -1")).key(), "targets[0].radius_mm");
  EXPECT_EQ(parseError(edit(kSteeringBase, "clearance_mm: 1", "clearance_mm: -1")).key(),
            "obstacles[0].clearance_mm");
}

TEST(SceneErrorTest, UnknownMaterialReference) {
  SceneError e = parseError(edit(kBase, "    material: prostate\n", "    material: bone\n"));
  EXPECT_EQ(e.key(), "regions[0].material");
  EXPECT_EQ(e.value(), "bone");
  e = parseError(edit(kBase, "background_material: fat", "background_material: muscle"));
  EXPECT_EQ(e.key(), "workspace.background_material");
}

TEST(SceneErrorTest, DuplicateNames) {
  SceneError e = parseError(kBase + "  - name: t1\n    position_cm: [3.5, 3.5]\n");
  EXPECT_EQ(e.key(), "targets[1].name");
  EXPECT_TRUE(contains(e.reason(), "targets[0].name")) << e.what();
  e = parseError(edit(kBase, "  - name: prostate\n    young_modulus_kPa: 60",
                      "  - name: fat\n    young_modulus_kPa: 60"));
  EXPECT_EQ(e.key(), "materials[1].name");
}

TEST(SceneErrorTest, DuplicateYamlKey) {
  const SceneError e =
      parseError(edit(kBase, "max_depth_cm: 5.5", "max_depth_cm: 5.5\n  max_depth_cm: 4"));
  EXPECT_EQ(e.key(), "needle.max_depth_cm");
  EXPECT_TRUE(contains(e.reason(), "duplicate key")) << e.what();
}

TEST(SceneErrorTest, UnknownTissueModel) {
  const SceneError e = parseError(edit(kBase, "tissue: quasi_static", "tissue: fem"));
  EXPECT_EQ(e.key(), "models.tissue");
  EXPECT_EQ(e.value(), "fem");
  EXPECT_TRUE(contains(e.reason(), "newmark")) << e.what();
}

TEST(SceneErrorTest, OrientationsNotAMultipleOfFour) {
  EXPECT_EQ(parseError(edit(kSteeringBase, "orientations: 40", "orientations: 42")).key(),
            "steering.orientations");
  EXPECT_EQ(parseError(edit(kSteeringBase, "orientations: 40", "orientations: 0")).key(),
            "steering.orientations");
}

TEST(SceneErrorTest, OrientationSubdivisionOutOfRange) {
  for (const std::string bad : {"0", "65", "1.5", "two"}) {
    const SceneError e = parseError(edit(kSteeringBase, "orientations: 40",
                                         "orientations: 40\n  orientation_subdivision: " + bad));
    EXPECT_EQ(e.key(), "steering.orientation_subdivision") << bad;
    EXPECT_EQ(e.value(), bad);
  }
}

TEST(SceneErrorTest, PsToleranceOutOfRange) {
  for (const std::string bad : {"-0.01", "1", "1.5", "tight"}) {
    const SceneError e = parseError(
        edit(kSteeringBase, "orientations: 40", "orientations: 40\n  ps_tolerance: " + bad));
    EXPECT_EQ(e.key(), "steering.ps_tolerance") << bad;
  }
}

TEST(SceneErrorTest, NeedleHeightRange) {
  EXPECT_EQ(parseError(edit(kBase, "max_height_cm: 5.5", "max_height_cm: 7")).key(),
            "needle.max_height_cm");
  EXPECT_EQ(parseError(edit(kBase, "min_height_cm: 0.5", "min_height_cm: -1")).key(),
            "needle.min_height_cm");
  const SceneError e = parseError(edit(kBase, "min_height_cm: 0.5", "min_height_cm: 5.6"));
  EXPECT_EQ(e.key(), "needle.min_height_cm");
  EXPECT_TRUE(contains(e.reason(), "above max_height")) << e.what();
  EXPECT_EQ(parseError(edit(kBase, "max_depth_cm: 5.5", "max_depth_cm: 6.5")).key(),
            "needle.max_depth_cm");
}

TEST(SceneErrorTest, TwoUnitVariantsOfOneKey) {
  const SceneError e = parseError(edit(kBase, "radius_mm: 1", "radius_mm: 1\n    radius_cm: 0.1"));
  EXPECT_EQ(e.key(), "targets[0].radius_mm");
  EXPECT_TRUE(contains(e.reason(), "radius_cm")) << e.what();
}

TEST(SceneErrorTest, UnknownKey) {
  SceneError e = parseError(edit(kBase, "radius_mm: 1", "radius_mn: 1"));
  EXPECT_EQ(e.key(), "targets[0].radius_mn");
  EXPECT_TRUE(contains(e.reason(), "did you mean 'radius_mm'")) << e.what();
  e = parseError(edit(kBase, "regions:", "regoins:"));
  EXPECT_EQ(e.key(), "regoins");
  e = parseError(edit(kBase, "  name: test\n", "  name: test\n  author: me\n"));
  EXPECT_EQ(e.key(), "scene.author");
  e = parseError(edit(kBase, "radius_mm: 1", "radius_km: 1"));
  EXPECT_EQ(e.key(), "targets[0].radius_km");
}

// ---- other refusals ----------------------------------------------------------------------------

TEST(SceneErrorTest, TissueSceneNeedsBackgroundOrCoveringRegions) {
  const SceneError e = parseError(edit(kBase, "  background_material: fat\n", ""));
  EXPECT_EQ(e.key(), "workspace.background_material");
  // Regions that tile the workspace need no background.
  std::string tiled = edit(kBase, "  background_material: fat\n", "");
  tiled = edit(tiled, "polygon_cm: [[2, 2], [4, 2], [4, 4], [2, 4]]",
               "polygon_cm: [[0, 0], [6, 0], [6, 3], [0, 3]]\n"
               "  - name: upper\n    material: fat\n"
               "    polygon_cm: [[0, 3], [6, 3], [6, 6], [0, 6]]");
  EXPECT_NO_THROW(parseScene(tiled, "tiled.yaml"));
}

TEST(SceneErrorTest, ModelConsistency) {
  EXPECT_EQ(parseError(edit(kSteeringBase, "steering: true", "steering: false")).key(), "steering");
  EXPECT_EQ(
      parseError(edit(kBase, "tissue: quasi_static", "tissue: quasi_static\n  steering: true"))
          .key(),
      "steering");
  EXPECT_EQ(
      parseError(edit(kSteeringBase, "steering: true", "steering: true\n  corotational: true"))
          .key(),
      "models.corotational");
  EXPECT_EQ(parseError(edit(kSteeringBase, "  radius_of_curvature_cm: 5\n", "")).key(),
            "needle.radius_of_curvature");
}

TEST(SceneErrorTest, BoundarySegmentMustLieOnTheWorkspaceBoundary) {
  EXPECT_EQ(parseError(edit(kBase, "to_cm: [6, 0]", "to_cm: [6, 1]")).key(), "boundary[0].to_cm");
  EXPECT_EQ(parseError(edit(kBase, "condition: fixed", "condition: sliding")).key(),
            "boundary[0].condition");
}

TEST(SceneErrorTest, ImagingAndMeshRanges) {
  EXPECT_EQ(parseError(kBase + "imaging:\n  drop_probability: 1\n").key(),
            "imaging.drop_probability");
  EXPECT_EQ(parseError(kBase + "imaging:\n  modality: mri\n").key(), "imaging.modality");
  EXPECT_EQ(parseError(kBase + "imaging:\n  pixel_size_mm: 0\n").key(), "imaging.pixel_size_mm");
  EXPECT_EQ(parseError(kBase + "mesh:\n  min_angle_deg: 40\n").key(), "mesh.min_angle_deg");
  EXPECT_EQ(parseError(kBase + "mesh:\n  max_edge_mm: 2\n  min_edge_mm: 3\n").key(),
            "mesh.min_edge_mm");
}

TEST(SceneErrorTest, WorkspaceMaxMustExceedMin) {
  EXPECT_EQ(parseError(edit(kBase, "max_cm: [6, 6]", "max_cm: [6, 0]")).key(), "workspace.max_cm");
}

}  // namespace
}  // namespace needle_guidance::scene

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
