// Validates a scene file (or embedded scene name) and prints a summary; with --mesh also meshes
// its tissue. A bad scene prints the one-line error "FILE: key 'KEY' value 'VALUE': REASON" and
// exits 1. Usage: check_scene [--mesh] SCENE
#include <chrono>
#include <iostream>
#include <string>

#include "needle_guidance/geometry/triangle_mesh.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue/tissue_simulation.h"
#include "needle_guidance/tissue_3d/tet_mesh_3d.h"

namespace ng = needle_guidance;

int main(int argc, char** argv) {
  bool mesh = false;
  std::string spec;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--mesh") {
      mesh = true;
    } else if (spec.empty() && arg.rfind("--", 0) != 0) {
      spec = arg;
    } else {
      spec.clear();
      break;
    }
  }
  if (spec.empty()) {
    std::cerr << "usage: check_scene [--mesh] SCENE   (a YAML file or one of:";
    for (const auto& name : ng::scene::defaultSceneNames()) {
      std::cerr << ' ' << name;
    }
    std::cerr << ")\n";
    return 2;
  }
  try {
    if (ng::tissue_3d::isTissueScene3dFile(spec)) {
      return ng::tissue_3d::checkTissueScene3d(spec, mesh, std::cout);
    }
    const ng::scene::Scene s = ng::scene::loadSceneSpec(spec);
    std::cout << "scene '" << s.name << "' from " << s.source << ": OK\n"
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
          std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
              .count();
      std::cout << "  mesh: " << m.nodeCount() << " nodes, " << m.triangleCount()
                << " triangles in " << ms << " ms\n";
    }
  } catch (const std::exception& e) {
    std::cerr << e.what() << "\n";
    return 1;
  }
  return 0;
}
