// Benchmark of 3-D tissue: tetrahedral FEM needle insertion and the 3-D rigid seed implant.
// Reports insertion steps per second (CPU, one core) and peak memory against the tetrahedron
// count (5k to 200k; --quick: 5k to 50k), and per scene and target the planned seed error
// measured by an independent full simulation, the planning CPU time, the step convergence
// (halving the step) and the unplanned error (aiming straight at the target).
// Usage: bench_tissue_3d --out DIR [--quick] [--scene FILE ...]

#include <algorithm>
#include <cmath>
#include <ctime>
#include <filesystem>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/package_paths.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/process_usage.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/tissue_3d/offset_planner_3d.h"

namespace ng = needle_guidance;
using needle_guidance::report::peakMb;
namespace t3 = ng::tissue_3d;
using ng::report::jsonNumber;

namespace {

/// A length in mm for the CSV, empty when undefined (< 0: never computed).
ng::report::Cell mmOrUndefined(double m) {
  return m < 0.0 ? ng::report::Cell(std::string()) : ng::report::Cell(m * 1e3);
}

double cpuNow() {
  return static_cast<double>(std::clock()) / CLOCKS_PER_SEC;
}

std::vector<std::string> defaultScenes() {
  std::vector<std::string> files;
  for (const auto& e :
       std::filesystem::directory_iterator(needle_guidance::configDir() / "scenes" / "tissue_3d")) {
    if (e.path().extension() == ".yaml") {
      files.push_back(e.path().string());
    }
  }
  std::sort(files.begin(), files.end());
  return files;
}

struct ScalingRow {
  int tets = 0;
  double steps_per_s = 0.0;
  double factor_cpu_s = 0.0;
  double mesh_cpu_s = 0.0;
  double peak_mb = 0.0;
  double columns_mb = 0.0;
};

/// One insertion to the scene's first target at its step; CPU per step.
ScalingRow scalingRun(const t3::TissueScene3d& scene, double scale) {
  ScalingRow row;
  t3::TetMeshReport report;
  t3::TetMesh3 mesh = t3::meshTissue3d(scene, {}, scale, &report);
  row.tets = mesh.elementCount();
  row.mesh_cpu_s = report.cpu_s;
  t3::TissueModel3 model(std::move(mesh), scene.materialTable());
  row.factor_cpu_s = model.assemblyCpuSeconds();
  const t3::Target3& target = scene.targets.front();
  t3::NeedleInsertion3 needle(model, scene.needle, scene.block_min_m.x(), target.position_m.x());
  const double step = scene.needle.insertion_velocity_m_s * scene.needle.step_s;
  const double start = cpuNow();
  int steps = 0;
  std::string why;
  for (double s = scene.block_min_m.x() - step; s < target.position_m.x();) {
    s = std::min(s + step, target.position_m.x());
    if (!needle.moveTo(target.position_m.tail<2>(), s, &why)) {
      throw std::runtime_error("scaling run: " + why);
    }
    ++steps;
  }
  const double cpu = cpuNow() - start;
  row.steps_per_s = steps / std::max(cpu, 1e-9);
  row.peak_mb = peakMb();
  row.columns_mb = model.compliance().memoryBytes() / 1048576.0;
  return row;
}

}  // namespace

int main(int argc, char** argv) {
  const auto args = ng::report::parseBenchArgs(argc, argv, "bench_tissue_3d");
  if (!args) {
    return 2;
  }
  try {
    const std::vector<std::string> files = args->scenes.empty() ? defaultScenes() : args->scenes;
    // ---- steps/s and memory against the tetrahedron count --------------------------------
    const t3::TissueScene3d base = t3::loadTissueScene3d(files.front());
    const t3::TetMesh3 probe = t3::meshTissue3d(base, {}, 1.0);
    const std::vector<double> wanted = args->quick ? std::vector<double>{5e3, 2e4, 5e4}
                                                   : std::vector<double>{5e3, 2e4, 5e4, 1e5, 2e5};
    ng::report::Table scaling(
        {"tets", "steps_per_s", "factor_cpu_s", "mesh_cpu_s", "peak_mb", "columns_mb"});
    std::vector<ScalingRow> rows;
    for (double n : wanted) {
      // Element count ~ scale^-3: one correction from a trial mesh at the first guess.
      double scale = std::cbrt(probe.elementCount() / n);
      scale *= std::cbrt(t3::meshTissue3d(base, {}, scale).elementCount() / n);
      const ScalingRow r = scalingRun(base, scale);
      rows.push_back(r);
      scaling.addRow(
          {double(r.tets), r.steps_per_s, r.factor_cpu_s, r.mesh_cpu_s, r.peak_mb, r.columns_mb});
      std::cout << "  " << r.tets << " tets: " << r.steps_per_s << " steps/s, factor "
                << r.factor_cpu_s << " s, peak " << r.peak_mb << " MB\n";
    }
    auto nearestRow = [&](double n) {
      return *std::min_element(rows.begin(), rows.end(), [&](const auto& a, const auto& b) {
        return std::abs(std::log(a.tets / n)) < std::abs(std::log(b.tets / n));
      });
    };
    // ---- planning per scene ---------------------------------------------------------------
    ng::report::Table plans({"scene", "target", "placed", "predicted_mm", "verified_mm",
                             "unplanned_mm", "step_halving_mm", "plan_cpu_s", "simulations", "tets",
                             "refusal"});
    double worst_error = 0.0, worst_cpu = 0.0, worst_halving = 0.0;
    int reachable = 0, placed = 0;
    for (const std::string& file : files) {
      const t3::TissueScene3d scene = t3::loadTissueScene3d(file);
      t3::TetMesh3 mesh = t3::meshTissue3d(scene, {}, 1.0);
      const int tets = mesh.elementCount();
      t3::TissueModel3 model(std::move(mesh), scene.materialTable());
      t3::OffsetPlanner3 planner(scene, model);
      for (const t3::Target3& target : scene.targets) {
        const t3::PlanResult3 r = planner.plan(target);
        double halving = -1.0;
        if (!r.unreachable) {
          ++reachable;
        }
        if (r.placed) {
          ++placed;
          const t3::Vector3 half = planner.simulateImplant(r.lateral_m, r.tip_x_m, 0.5);
          halving = (half - r.verified_seed_m).norm();
          worst_halving = std::max(worst_halving, halving);
          worst_error = std::max(worst_error, r.verified_error_m);
          worst_cpu = std::max(worst_cpu, r.plan_cpu_s);
        }
        model.compliance().clearCache();
        plans.addRow({scene.name, target.name,
                      std::string(r.placed        ? "yes"
                                  : r.unreachable ? "unreachable"
                                                  : "no"),
                      mmOrUndefined(r.predicted_error_m), mmOrUndefined(r.verified_error_m),
                      mmOrUndefined(r.unplanned_error_m), mmOrUndefined(halving), r.plan_cpu_s,
                      double(r.simulations), double(tets), r.refusal});
        std::cout << "  " << scene.name << "/" << target.name << ": "
                  << (r.placed ? "placed" : "not placed") << ", " << r.plan_cpu_s << " s CPU "
                  << r.refusal << "\n";
      }
    }
    scaling.writeCsv(args->out_dir + "/scaling.csv");
    plans.writeCsv(args->out_dir + "/plans.csv");
    const ScalingRow r50 = nearestRow(5e4);
    const ScalingRow r200 = nearestRow(2e5);
    std::ostringstream json;
    json << "{\n  \"benchmark\": \"tissue_3d\",\n  \"quick\": " << (args->quick ? "true" : "false")
         << ",\n  \"tets_50k\": " << r50.tets
         << ",\n  \"steps_per_s_50k_tets\": " << jsonNumber(r50.steps_per_s)
         << ",\n  \"tets_200k\": "
         << (args->quick ? std::string("null") : std::to_string(r200.tets))
         << ",\n  \"peak_mb_200k_tets\": "
         << (args->quick ? std::string("null") : jsonNumber(r200.peak_mb))
         << ",\n  \"planned_error_mm_max_3d\": "
         << (placed > 0 ? jsonNumber(worst_error * 1e3) : "null")
         << ",\n  \"reachable_placed_fraction_3d\": "
         << (reachable > 0 ? jsonNumber(double(placed) / reachable) : "null")
         << ",\n  \"reachable_targets_3d\": " << reachable
         << ",\n  \"placed_targets_3d\": " << placed
         << ",\n  \"plan_cpu_s_max_3d\": " << (placed > 0 ? jsonNumber(worst_cpu) : "null")
         << ",\n  \"step_halving_change_mm_max_3d\": "
         << (placed > 0 ? jsonNumber(worst_halving * 1e3) : "null") << "\n}\n";
    ng::report::writeTextFile(args->out_dir + "/summary.json", json.str());
    ng::report::writeTextFile(args->out_dir + "/plot.json",
                              R"json([{"csv": "scaling.csv", "x": "tets", "y": "steps_per_s",
  "title": "Insertion steps per second (CPU, one core) vs tetrahedra", "logx": true, "logy": true,
  "png": "steps_per_s_vs_tets.png"},
 {"csv": "scaling.csv", "x": "tets", "y": "peak_mb", "title": "Peak memory vs tetrahedra",
  "logx": true, "logy": true, "png": "peak_mb_vs_tets.png"},
 {"csv": "plans.csv", "x": "plan_cpu_s", "y": "verified_mm", "group": "scene", "filter": {"placed": "yes"},
  "title": "Planned seed error (independent simulation) vs planning CPU time",
  "points": true, "logy": true, "png": "plan_error_vs_cpu.png"}])json");
    std::cout << plans.toText();
  } catch (const std::exception& e) {
    std::cerr << "bench_tissue_3d: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
