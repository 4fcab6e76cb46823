// Benchmark of the geometry core: CGAL meshing of the default prostate scene from coarse to
// fine (≈1k to ≈50k triangles) and point location. Speed against mesh quality and area error.
// Usage: bench_meshing --out DIR [--quick] [--scene SPEC]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <iostream>
#include <optional>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/geometry/triangle_mesh.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/scene/scene.h"

namespace ng = needle_guidance;
using Clock = std::chrono::steady_clock;

namespace {

double secondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

double minAngleDeg(const ng::geometry::TriangleMesh& mesh) {
  double min_angle = 180.0;
  for (const auto& t : mesh.triangles) {
    for (int k = 0; k < 3; ++k) {
      const auto& a = mesh.nodes[static_cast<std::size_t>(t[k])];
      const auto& b = mesh.nodes[static_cast<std::size_t>(t[(k + 1) % 3])];
      const auto& c = mesh.nodes[static_cast<std::size_t>(t[(k + 2) % 3])];
      const double cosine = (b - a).normalized().dot((c - a).normalized());
      min_angle = std::min(min_angle, std::acos(std::clamp(cosine, -1.0, 1.0)) * 180.0 / M_PI);
    }
  }
  return min_angle;
}

}  // namespace

int main(int argc, char** argv) {
  const std::optional<ng::report::BenchArgs> args =
      ng::report::parseBenchArgs(argc, argv, "bench_meshing");
  if (!args) {
    return 2;
  }
  const std::string& out_dir = args->out_dir;
  const bool quick = args->quick;
  const std::string& scene_spec = args->scene;
  try {
    const ng::scene::Scene scene = ng::scene::loadSceneSpec(scene_spec);
    const std::vector<ng::geometry::MeshRegion> regions = scene.meshRegions();
    const ng::geometry::Polygon domain = scene.workspacePolygon();
    const double domain_area = domain.area();

    // Uniform size sweep (max = min edge) from coarse to fine, plus the scene's graded default.
    std::vector<double> edges_mm = quick ? std::vector<double>{4.0, 1.0, 0.5}
                                         : std::vector<double>{4.0, 2.5, 1.6, 1.0, 0.7, 0.5, 0.36};
    ng::report::Table table({"mesh", "max_edge_mm", "triangles", "nodes", "mesh_ms",
                             "min_angle_deg", "area_rel_error", "locate_ns"},
                            6);
    struct Row {
      double triangles, mesh_ms, locate_ns, area_err, min_angle;
    };
    std::vector<Row> rows;
    auto run = [&](const std::string& label, const ng::geometry::MeshingOptions& options) {
      const int repeats = quick ? 1 : 3;
      double best_s = 1e30;
      ng::geometry::TriangleMesh mesh;
      for (int r = 0; r < repeats; ++r) {
        const auto start = Clock::now();
        mesh = ng::geometry::meshDomain(domain, scene.background_material, regions, options);
        best_s = std::min(best_s, secondsSince(start));
      }
      const double area_err = std::abs(mesh.totalArea() - domain_area) / domain_area;
      const ng::geometry::PointLocator locator(mesh);
      std::mt19937 rng(42);
      std::uniform_real_distribution<double> ux(scene.workspace_min.x(), scene.workspace_max.x());
      std::uniform_real_distribution<double> uy(scene.workspace_min.y(), scene.workspace_max.y());
      constexpr int kQueries = 200000;
      std::vector<ng::geometry::Point2> queries(kQueries);
      for (auto& q : queries) {
        q = {ux(rng), uy(rng)};
      }
      int found = 0;
      const auto start = Clock::now();
      for (const auto& q : queries) {
        found += locator.locate(q).has_value() ? 1 : 0;
      }
      const double locate_ns = 1e9 * secondsSince(start) / kQueries;
      if (found != kQueries) {
        throw std::runtime_error("point location missed " + std::to_string(kQueries - found) +
                                 " points inside the domain");
      }
      const double min_angle = minAngleDeg(mesh);
      table.addRow({label, 1e3 * options.max_edge_m, double(mesh.triangleCount()),
                    double(mesh.nodeCount()), 1e3 * best_s, min_angle, area_err, locate_ns});
      rows.push_back({double(mesh.triangleCount()), 1e3 * best_s, locate_ns, area_err, min_angle});
      std::cout << label << ": " << mesh.triangleCount() << " triangles in " << 1e3 * best_s
                << " ms, min angle " << min_angle << " deg, locate " << locate_ns << " ns\n";
    };
    for (double e : edges_mm) {
      ng::geometry::MeshingOptions options;
      options.max_edge_m = options.min_edge_m = e * 1e-3;
      options.grading_length_m = scene.mesh.grading_length_m;
      options.min_angle_deg = scene.mesh.min_angle_deg;
      run("uniform", options);
    }
    ng::geometry::MeshingOptions graded;
    graded.max_edge_m = scene.mesh.max_edge_m;
    graded.min_edge_m = scene.mesh.min_edge_m;
    graded.grading_length_m = scene.mesh.grading_length_m;
    graded.min_angle_deg = scene.mesh.min_angle_deg;
    for (const auto& t : scene.targets) {
      graded.refine_points.push_back(t.position);
    }
    run("scene_default", graded);

    // Headline figures: interpolate mesh time at 1,250 and 50,000 triangles (log-log).
    std::vector<Row> uniform(rows.begin(), rows.end() - 1);
    std::sort(uniform.begin(), uniform.end(),
              [](const Row& a, const Row& b) { return a.triangles < b.triangles; });
    auto at = [&](double n, double Row::*field) {
      for (std::size_t i = 1; i < uniform.size(); ++i) {
        if (n <= uniform[i].triangles || i + 1 == uniform.size()) {
          const Row& a = uniform[i - 1];
          const Row& b = uniform[i];
          const double s = std::log(n / a.triangles) / std::log(b.triangles / a.triangles);
          return std::exp(std::log(a.*field) + s * (std::log(b.*field) - std::log(a.*field)));
        }
      }
      return uniform.front().*field;
    };
    double max_area_err = 0.0, min_angle = 180.0;
    for (const Row& r : rows) {
      max_area_err = std::max(max_area_err, r.area_err);
      min_angle = std::min(min_angle, r.min_angle);
    }
    std::ostringstream json;
    json.precision(6);
    json << "{\n  \"benchmark\": \"meshing\",\n  \"scene\": \"" << scene.name << "\",\n"
         << "  \"quick\": " << (quick ? "true" : "false") << ",\n"
         << "  \"mesh_ms_1250\": " << at(1250.0, &Row::mesh_ms) << ",\n"
         << "  \"mesh_ms_50k\": " << at(50000.0, &Row::mesh_ms) << ",\n"
         << "  \"locate_ns_50k\": " << at(50000.0, &Row::locate_ns) << ",\n"
         << "  \"scene_default_triangles\": " << rows.back().triangles << ",\n"
         << "  \"scene_default_mesh_ms\": " << rows.back().mesh_ms << ",\n"
         << "  \"area_rel_error_max\": " << max_area_err << ",\n"
         << "  \"min_angle_deg\": " << min_angle << "\n}\n";
    table.writeCsv(out_dir + "/meshing.csv");
    ng::report::writeTextFile(out_dir + "/summary.json", json.str());
    ng::report::writeTextFile(
        out_dir + "/plot.json",
        R"json([{"csv": "meshing.csv", "x": "triangles", "y": "mesh_ms", "group": "mesh",
  "title": "CGAL meshing time vs triangles (prostate scene)", "logx": true, "logy": true,
  "png": "meshing_time.png"},
 {"csv": "meshing.csv", "x": "triangles", "y": "locate_ns", "group": "mesh",
  "title": "point location time per query", "logx": true, "png": "locate_time.png"}])json");
    std::cout << table.toText();
  } catch (const std::exception& e) {
    std::cerr << "bench_meshing: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
