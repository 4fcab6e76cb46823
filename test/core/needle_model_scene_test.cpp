// Tests for the 3-D steering scenes (scene_3d.h), their meshes (mesh_3d.h) and the
// sphere-traced collision checks (collision_3d.h): closed-form distances against boxes, mesh
// formats, refusals naming the file, and the shipped scenes' geometric claims (the straight
// needle cannot reach the prostate target behind the arch).
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <utility>

#include "needle_guidance/math.h"
#include "needle_guidance/needle_model/collision_3d.h"
#include "needle_guidance/needle_model/mesh_3d.h"
#include "needle_guidance/needle_model/scene_3d.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue_3d/scene_tissue_3d.h"

namespace needle_guidance::needle_model {
namespace {

constexpr double kMm = 1e-3;
constexpr double kDistanceTol_m = 1e-9;  // AABB distances to planar faces, in double
constexpr double kTolerance_m = 5e-5;    // the collision world's contact tolerance

std::string sceneDir() {
  return std::string(NG_SOURCE_DIR) + "/config/scenes/steering_3d";
}

std::filesystem::path tempDir() {
  const auto dir = std::filesystem::temp_directory_path() / "ng_needle_model_scene_test";
  std::filesystem::create_directories(dir);
  return dir;
}

void writeText(const std::filesystem::path& path, const std::string& text) {
  std::ofstream(path) << text;
}

/// readMesh3's refusal of a file (in m), "" if it accepted it.
std::string meshError(const std::filesystem::path& path) {
  try {
    readMesh3(path.string(), 1.0);
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "";
}

TEST(Mesh3d, BoxDistanceAndInsideAreExact) {
  const MeshDistance box(boxMesh(Vector3(0, 0, 0), Vector3(0.01, 0.02, 0.03)));
  EXPECT_NEAR(box.distance(Vector3(0.015, 0.01, 0.01)), 0.005, kDistanceTol_m);
  EXPECT_NEAR(box.distance(Vector3(0.005, 0.01, 0.01)), 0.005, kDistanceTol_m);
  EXPECT_TRUE(box.insideOrOn(Vector3(0.005, 0.01, 0.01)));
  EXPECT_TRUE(box.insideOrOn(Vector3(0.0, 0.01, 0.01)));  // on the boundary counts
  EXPECT_FALSE(box.insideOrOn(Vector3(-1e-6, 0.01, 0.01)));
}

TEST(Mesh3d, ReadsOffStlAndObjThroughCgal) {
  const Mesh3 box = boxMesh(Vector3(0, 0, 0), Vector3(1, 2, 3));  // in mm below
  for (const char* ext : {".off", ".stl", ".obj"}) {
    const std::string path = (tempDir() / (std::string("box") + ext)).string();
    writeMesh3(path, box, 1.0);
    const Mesh3 read = readMesh3(path, kMm);
    EXPECT_EQ(read.vertices.size(), 8u) << ext;  // STL's repeated corners merged
    EXPECT_EQ(read.triangles.size(), 12u) << ext;
    const MeshDistance d(read);
    EXPECT_NEAR(d.distance(Vector3(0.5, 1, 4) * kMm), 1.0 * kMm, kDistanceTol_m) << ext;
  }
}

TEST(Mesh3d, RefusesOpenDegenerateAndNonTriangleMeshesNamingTheFile) {
  const auto open = tempDir() / "open_box.off";
  {
    Mesh3 box = boxMesh(Vector3(0, 0, 0), Vector3(1, 1, 1));
    box.triangles.pop_back();
    writeMesh3(open.string(), box, 1.0);
  }
  std::string error = meshError(open);
  EXPECT_NE(error.find(open.string()), std::string::npos) << error;
  EXPECT_NE(error.find("not closed"), std::string::npos) << error;
  EXPECT_NE(error.find("(face "), std::string::npos) << error;  // the faces at the open edge

  const auto degenerate = tempDir() / "degenerate.off";
  writeText(degenerate,
            "OFF\n4 4 0\n0 0 0\n1 0 0\n2 0 0\n0 1 0\n3 0 1 2\n3 0 1 3\n3 1 2 3\n"
            "3 0 2 3\n");
  error = meshError(degenerate);
  EXPECT_NE(error.find(degenerate.string()), std::string::npos) << error;
  EXPECT_NE(error.find("degenerate"), std::string::npos) << error;

  const auto quads = tempDir() / "quads.off";
  writeText(quads, "OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n");
  error = meshError(quads);
  EXPECT_NE(error.find("only triangles"), std::string::npos) << error;

  error = meshError(tempDir() / "missing.off");
  EXPECT_NE(error.find("missing.off"), std::string::npos) << error;
}

/// A closed box with what an exported organ mesh often carries: vertices no face uses (SOFA's
/// liver.obj has 42), a face written twice, and faces in the wrong order.
Mesh3 untidyBox(int unreferenced, int reversed_faces) {
  Mesh3 m = boxMesh(Vector3(0, 0, 0), Vector3(10, 20, 30));
  for (int i = 0; i < unreferenced; ++i) {
    m.vertices.emplace_back(50.0 + i, 50.0, 50.0);
  }
  for (int f = 0; f < reversed_faces; ++f) {
    std::swap(m.triangles[static_cast<std::size_t>(f)][1],
              m.triangles[static_cast<std::size_t>(f)][2]);
  }
  m.triangles.push_back(m.triangles.back());
  return m;
}

TEST(Mesh3d, RepairsUnreferencedVerticesDuplicateFacesAndOrientationAndSaysSo) {
  for (const int reversed : {3, 12}) {  // some faces against the rest; every face inwards
    const auto path = tempDir() / ("untidy_box_" + std::to_string(reversed) + ".obj");
    writeMesh3(path.string(), untidyBox(42, reversed), 1.0);
    MeshRepairs3 repairs;
    const Mesh3 read = readMesh3(path.string(), kMm, &repairs);
    EXPECT_EQ(repairs.unreferenced_vertices_removed, 42u) << reversed;
    EXPECT_EQ(repairs.duplicate_faces_removed, 1u) << reversed;
    EXPECT_EQ(repairs.duplicate_vertices_merged, 0u) << reversed;
    EXPECT_EQ(repairs.faces_reoriented, static_cast<std::size_t>(reversed));
    EXPECT_NE(repairs.toString().find("42 unreferenced vertices removed"), std::string::npos)
        << repairs.toString();
    EXPECT_EQ(read.vertices.size(), 8u);
    EXPECT_EQ(read.triangles.size(), 12u);
    const MeshDistance d(read);  // outward: the inside test holds inside the box
    EXPECT_TRUE(d.insideOrOn(Vector3(5, 10, 15) * kMm));
    EXPECT_FALSE(d.insideOrOn(Vector3(5, 10, 31) * kMm));
    EXPECT_NEAR(d.distance(Vector3(5, 10, 35) * kMm), 5 * kMm, kDistanceTol_m);
  }
  MeshRepairs3 clean;
  const auto tidy = tempDir() / "tidy_box.off";
  writeMesh3(tidy.string(), boxMesh(Vector3(0, 0, 0), Vector3(1, 1, 1)), 1.0);
  readMesh3(tidy.string(), kMm, &clean);
  EXPECT_TRUE(clean.empty()) << clean.toString();
}

TEST(Mesh3d, RefusesASelfIntersectingMeshNamingTheFileAndTheFaces) {
  Mesh3 two = boxMesh(Vector3(0, 0, 0), Vector3(2, 2, 2));
  const Mesh3 other = boxMesh(Vector3(1, 1, 1), Vector3(3, 3, 3));
  const int offset = static_cast<int>(two.vertices.size());
  two.vertices.insert(two.vertices.end(), other.vertices.begin(), other.vertices.end());
  for (auto t : other.triangles) {
    two.triangles.push_back({t[0] + offset, t[1] + offset, t[2] + offset});
  }
  const auto path = tempDir() / "overlapping_boxes.off";
  writeMesh3(path.string(), two, 1.0);
  const std::string error = meshError(path);
  EXPECT_NE(error.find(path.string()), std::string::npos) << error;
  EXPECT_NE(error.find("self-intersecting"), std::string::npos) << error;
  EXPECT_NE(error.find("first faces"), std::string::npos) << error;
}

TEST(Collision3d, SegmentsStopAtTheExpandedObstacle) {
  const Mesh3 tissue = boxMesh(Vector3(-0.1, -0.1, -0.1), Vector3(0.1, 0.1, 0.1));
  ObstacleMesh3 block{"block", boxMesh(Vector3(0.02, -0.01, -0.01), Vector3(0.03, 0.01, 0.01)),
                      2e-3};
  const CollisionWorld3 world(tissue, {block}, kTolerance_m);
  // Head-on along +x: contact where the margin falls below the tolerance, 2 mm before the face.
  const PathCheck hit = world.checkPolyline({Vector3(0, 0, 0), Vector3(0.05, 0, 0)});
  ASSERT_FALSE(hit.free());
  EXPECT_EQ(hit.contact, Contact3::kObstacle);
  EXPECT_EQ(hit.obstacle, "block");
  EXPECT_NEAR(hit.contact_s_m, 0.018, kTolerance_m);
  EXPECT_LT(hit.queries, 40);  // sphere tracing: few queries in open tissue
  // Passing above the block: free at clearance + 2 tolerances, contact at clearance - tolerance.
  const double clear_y = 0.01 + 2e-3;
  EXPECT_TRUE(world
                  .checkPolyline({Vector3(0, clear_y + 2 * kTolerance_m, 0),
                                  Vector3(0.05, clear_y + 2 * kTolerance_m, 0)})
                  .free());
  EXPECT_FALSE(world
                   .checkPolyline({Vector3(0, clear_y - kTolerance_m, 0),
                                   Vector3(0.05, clear_y - kTolerance_m, 0)})
                   .free());
  // Leaving the tissue.
  const PathCheck out = world.checkPolyline({Vector3(0, 0.05, 0), Vector3(0, 0.2, 0)});
  EXPECT_EQ(out.contact, Contact3::kOutsideTissue);
  EXPECT_NEAR(out.contact_s_m, 0.05, kTolerance_m);
  // Point classification with inside tests.
  EXPECT_EQ(world.classify(Vector3(0.025, 0, 0)).contact, Contact3::kObstacle);
  EXPECT_EQ(world.classify(Vector3(0.019, 0, 0)).contact, Contact3::kObstacle);  // clearance
  EXPECT_EQ(world.classify(Vector3(0.3, 0, 0)).contact, Contact3::kOutsideTissue);
  EXPECT_EQ(world.classify(Vector3(-0.1, 0, 0)).contact, Contact3::kFree);  // on the boundary
}

TEST(Scene3d, ShippedScenesLoadAndTheirTargetsAreFree) {
  for (const char* name : {"prostate_3d", "liver_3d", "prostate_heldout_3d"}) {
    const Scene3d s = loadScene3d(sceneDir() + "/" + name + ".yaml");
    EXPECT_EQ(s.name, name);
    const CollisionWorld3 world = s.collisionWorld();
    const PointCheck target = world.classify(s.target.center_m);
    EXPECT_EQ(target.contact, Contact3::kFree) << name << " " << target.obstacle;
    EXPECT_GT(target.margin_m, s.target.radius_m) << name;
    EXPECT_NE(world.classify(s.entry.center_m).contact, Contact3::kOutsideTissue) << name;
  }
}

/// Every straight needle from a grid of entry points on the disc to a grid of points of the
/// target ball either leaves the entry cone or touches an expanded obstacle.
TEST(Scene3d, StraightNeedleCannotReachTheTargetBehindTheArch) {
  for (const char* name : {"prostate_3d", "prostate_heldout_3d"}) {
    const Scene3d s = loadScene3d(sceneDir() + "/" + name + ".yaml");
    const CollisionWorld3 world = s.collisionWorld();
    const Vector3 u = s.entry.direction.unitOrthogonal();
    const Vector3 w = s.entry.direction.cross(u);
    int feasible = 0, in_cone = 0;
    for (int i = -6; i <= 6; ++i) {
      for (int j = -6; j <= 6; ++j) {
        const Vector3 offset = (i * u + j * w) * (s.entry.radius_m / 6.0);
        if (offset.norm() > s.entry.radius_m) {
          continue;
        }
        const Vector3 p0 = s.entry.center_m + offset;
        for (int k = 0; k < 7; ++k) {  // target centre and six points on its surface
          Vector3 q = s.target.center_m;
          if (k > 0) {
            q[(k - 1) / 2] += ((k % 2) ? 1.0 : -1.0) * s.target.radius_m;
          }
          if (!s.entry.allows(p0, q - p0)) {
            continue;
          }
          ++in_cone;
          feasible += world.checkPolyline({p0, q}).free() ? 1 : 0;
        }
      }
    }
    EXPECT_EQ(feasible, 0) << name << ": " << in_cone << " lines within the cone";
  }
}

std::string prostateText() {
  std::ifstream in(sceneDir() + "/prostate_3d.yaml");
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

std::string replaced(std::string text, const std::string& from, const std::string& to) {
  const auto at = text.find(from);
  EXPECT_NE(at, std::string::npos) << from;
  return at == std::string::npos ? text : text.replace(at, from.size(), to);
}

TEST(Scene3d, BadFilesAreRefusedNamingFileKeyAndValue) {
  const std::string dir = sceneDir();
  const auto refuse = [&](const std::string& text, const std::string& key,
                          const std::string& detail) {
    try {
      parseScene3d(text, "bad.yaml", dir);
      ADD_FAILURE() << "accepted a scene with a bad " << key;
    } catch (const scene::SceneError& e) {
      EXPECT_EQ(e.file(), "bad.yaml");
      EXPECT_EQ(e.key(), key) << e.what();
      EXPECT_NE(std::string(e.what()).find(detail), std::string::npos) << e.what();
    }
  };
  const std::string good = prostateText();
  refuse(replaced(good, "kind: steering_3d", "kind: steering"), "scene.kind", "steering_3d");
  refuse(replaced(good, "radius_of_curvature_mm: 50", "radius_of_curvature_mm: -5"),
         "needle.radius_of_curvature_mm", "> 0");
  refuse(replaced(good, "step_length_mm: 5", "step_length_mm: 1"), "needle.step_length_mm",
         "duty_cycle_length");
  refuse(replaced(good, "spin_rate_max_rev_s: 5", "spin_rate_max_rev_s: 0.1"),
         "needle.spin_rate_max", "cannot turn");
  refuse(replaced(good, "sigma_roll_deg: 5", "sigma_roll_deg: abc"), "noise.sigma_roll_deg",
         "finite number");
  refuse(replaced(good, "radius_mm: 2.5", "radius_mm: 0"), "target.radius_mm", "> 0");
  refuse(replaced(good, "cone_half_angle_deg: 10", "cone_half_angle_deg: 95"),
         "entry.cone_half_angle_deg", "[0, 90)");
  refuse(replaced(good, "center_mm: [62, 19, 4]", "center_mm: [62, 19]"), "target.center_mm",
         "[x, y, z]");
  refuse(replaced(good, "  radius_mm: 2.5", "  radius_mm: 2.5\n  colour: red"), "target.colour",
         "unknown key");
  refuse(replaced(good, "meshes/urethra.off", "meshes/no_such.off"), "obstacles[1].mesh",
         "no_such.off");
  refuse(replaced(good, "center_mm: [0, 0, 0]", "center_mm: [-20, 0, 0]"), "entry.center",
         "outside the tissue");
  // A non-closed obstacle mesh names the scene key and the mesh file.
  Mesh3 box = boxMesh(Vector3(40, -5, -5), Vector3(45, 5, 5));
  box.triangles.pop_back();
  const std::string open = (tempDir() / "open_obstacle.off").string();
  writeMesh3(open, box, 1.0);
  refuse(replaced(good, "meshes/urethra.off", open), "obstacles[1].mesh", "not closed");
}

TEST(Scene3d, AMeshRepairIsReportedWithTheSceneKeyAndTheFile) {
  Mesh3 tissue = readMesh3(sceneDir() + "/meshes/prostate_tissue.off", 1.0);
  for (int i = 0; i < 42; ++i) {
    tissue.vertices.emplace_back(500.0 + i, 0.0, 0.0);
  }
  const auto path = tempDir() / "tissue_with_stray_vertices.off";
  writeMesh3(path.string(), tissue, 1.0);
  const Scene3d s =
      parseScene3d(replaced(prostateText(), "meshes/prostate_tissue.off", path.string()),
                   "repair.yaml", sceneDir());
  ASSERT_EQ(s.mesh_repairs.size(), 1u);
  EXPECT_NE(s.mesh_repairs[0].find("tissue.mesh"), std::string::npos) << s.mesh_repairs[0];
  EXPECT_NE(s.mesh_repairs[0].find("42 unreferenced vertices removed"), std::string::npos)
      << s.mesh_repairs[0];
  EXPECT_TRUE(loadScene3d(sceneDir() + "/prostate_3d.yaml").mesh_repairs.empty());
}

/// One scene system: every shipped scene file names its kind (planar when absent) and loads
/// through the reader of that kind; the planar reader refuses a 3-D scene naming its kind.
TEST(Scene3d, EveryShippedSceneOfEveryKindLoadsThroughItsKind) {
  int planar = 0, steering = 0, tissue = 0;
  const std::filesystem::path root = std::string(NG_SOURCE_DIR) + "/config/scenes";
  for (const auto& entry : std::filesystem::recursive_directory_iterator(root)) {
    if (entry.path().extension() != ".yaml") {
      continue;
    }
    const std::string path = entry.path().string();
    const std::string kind = scene::sceneKind(path);
    if (kind == scene::kPlanar) {
      EXPECT_NO_THROW(scene::loadScene(path)) << path;
      ++planar;
    } else if (kind == "steering_3d") {
      EXPECT_NO_THROW(loadScene3d(path)) << path;
      ++steering;
    } else if (kind == "tissue_3d") {
      EXPECT_NO_THROW(tissue_3d::loadTissueScene3d(path)) << path;
      ++tissue;
    } else {
      ADD_FAILURE() << path << ": unknown kind " << kind;
    }
  }
  EXPECT_GE(planar, 9);
  EXPECT_GE(steering, 3);
  EXPECT_GE(tissue, 3);
  EXPECT_EQ(scene::sceneKind("steering_workspace"), scene::kPlanar);  // embedded names
  try {
    scene::loadScene(sceneDir() + "/prostate_3d.yaml");
    ADD_FAILURE() << "the planar reader accepted a steering_3d scene";
  } catch (const scene::SceneError& e) {
    EXPECT_EQ(e.key(), "scene.kind");
    EXPECT_NE(std::string(e.what()).find("steering_3d"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace needle_guidance::needle_model

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
