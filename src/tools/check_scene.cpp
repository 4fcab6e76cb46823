// Validates scene files of every kind (or embedded scene names) and prints a summary of each;
// with --mesh also meshes a planar scene's tissue. The kind is the file's `scene.kind` (planar
// when absent, steering_3d). A bad scene prints the one-line error "FILE: key 'KEY' value
// 'VALUE': REASON"; the exit status is 1 when any scene was refused, 2 for a usage error.
// Usage: check_scene [--mesh] SCENE...
#include <chrono>
#include <iostream>
#include <string>
#include <vector>

#include "needle_guidance/geometry/triangle_mesh.h"
#include "needle_guidance/needle_model/scene_3d.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue/tissue_simulation.h"
#include "needle_guidance/tissue_3d/tet_mesh_3d.h"

namespace ng = needle_guidance;

namespace {

void checkPlanar(const std::string& spec, bool mesh) {
  const ng::scene::Scene s = ng::scene::loadSceneSpec(spec);
  std::cout << "scene '" << s.name << "' (planar) from " << s.source << ": OK\n"
            << "  workspace " << 1e2 * (s.workspace_max - s.workspace_min).x() << " cm x "
            << 1e2 * (s.workspace_max - s.workspace_min).y() << " cm, tissue model "
            << ng::scene::toString(s.models.tissue) << (s.models.steering ? ", steering" : "")
            << "\n  " << s.materials.size() << " materials, " << s.regions.size() << " regions, "
            << s.boundary.size() << " boundary segments, " << s.targets.size() << " targets, "
            << s.obstacles.size() << " obstacles\n";
  if (mesh && s.hasTissue()) {
    // The mesh tissue_sim builds: the scene's sizes, graded towards targets and needle paths.
    const ng::geometry::MeshingOptions options = ng::tissue::optionsFromScene(s).meshing;
    const auto start = std::chrono::steady_clock::now();
    const ng::geometry::TriangleMesh m = ng::geometry::meshDomain(
        s.workspacePolygon(), s.background_material, s.meshRegions(), options);
    const double ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    std::cout << "  mesh: " << m.nodeCount() << " nodes, " << m.triangleCount() << " triangles in "
              << ms << " ms\n";
  }
}

void checkSteering3d(const std::string& path) {
  const ng::needle_model::Scene3d s = ng::needle_model::loadScene3d(path);
  std::cout << "scene '" << s.name << "' (steering_3d) from " << s.source << ": OK\n"
            << "  tissue " << s.tissue.triangles.size() << " triangles, " << s.obstacles.size()
            << " obstacles, target radius " << 1e3 * s.target.radius_m << " mm, step "
            << 1e3 * s.step_length_m << " mm\n";
  for (const std::string& repair : s.mesh_repairs) {
    std::cout << "  " << repair << "\n";
  }
}

}  // namespace

int main(int argc, char** argv) {
  bool mesh = false;
  std::vector<std::string> specs;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--mesh") {
      mesh = true;
    } else if (arg.rfind("--", 0) == 0) {
      specs.clear();
      break;
    } else {
      specs.push_back(arg);
    }
  }
  if (specs.empty() || ng::report::helpRequested(argc, argv)) {
    std::ostream& out = ng::report::helpRequested(argc, argv) ? std::cout : std::cerr;
    out << "usage: check_scene [--mesh] SCENE...   (YAML files of any kind, or one of:";
    for (const auto& name : ng::scene::defaultSceneNames()) {
      out << ' ' << name;
    }
    out << ")\n";
    return &out == &std::cout ? 0 : 2;
  }
  int refused = 0;
  for (const std::string& spec : specs) {
    try {
      const std::string kind = ng::scene::sceneKind(spec);
      if (kind == ng::scene::kPlanar) {
        checkPlanar(spec, mesh);
      } else if (kind == "steering_3d") {
        checkSteering3d(spec);
      } else if (kind == "tissue_3d") {
        refused += ng::tissue_3d::checkTissueScene3d(spec, mesh, std::cout) != 0 ? 1 : 0;
      } else {
        throw ng::scene::SceneError(spec, "scene.kind", kind,
                                    "unknown scene kind (known: planar, steering_3d, tissue_3d)");
      }
    } catch (const std::exception& e) {
      std::cerr << e.what() << "\n";
      ++refused;
    }
  }
  return refused > 0 ? 1 : 0;
}
