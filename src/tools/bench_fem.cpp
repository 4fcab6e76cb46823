// Benchmark of the tissue FEM core (dissertation 2.2.2, 2.3.3-2.3.4): steps per second of each
// integrator on the default prostate scene meshed at ≈1,250 to ≈50,000 triangles, with a
// synthetic needle-like load: a prescribed tip node moving along +x, a shaft y-constraint added
// every few steps (the tip hands over to the next node on the needle line), and a moveNode of
// the tip node every few steps (cutting). Also runs without mesh changes (only the tip value
// changes). Writes fem.csv, summary.json and plot.json to DIR (scripts/bench fem).
// Usage: bench_fem --out DIR [--quick] [--scene SPEC]   (SPEC: a scene file or embedded name)
#include <algorithm>
#include <chrono>
#include <cmath>
#include <iostream>
#include <limits>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/geometry/triangle_mesh.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue/integrator.h"

namespace ng = needle_guidance;
namespace tissue = ng::tissue;
using Clock = std::chrono::steady_clock;

namespace {

constexpr double kNewmarkDt_s = 1e-3;   // haptic-rate step
constexpr int kShaftEverySteps = 5;     // tip hands over to the next node every 5 steps
constexpr int kMoveEverySteps = 3;      // moveNode of the tip every 3 steps
constexpr double kTipSpeed_m_s = 0.01;  // prescribed tip motion along +x

double secondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

struct Problem {
  ng::geometry::TriangleMesh mesh;
  std::vector<tissue::ElementMaterial> materials;
  std::vector<int> fixed_dofs;
  std::vector<int> needle_nodes;  ///< free nodes near the needle line, by increasing x
};

Problem makeProblem(const ng::scene::Scene& scene, double edge_m) {
  Problem p;
  const std::vector<ng::geometry::MeshRegion> regions = scene.meshRegions();
  ng::geometry::MeshingOptions options;
  options.max_edge_m = options.min_edge_m = edge_m;
  options.grading_length_m = scene.mesh.grading_length_m;
  options.min_angle_deg = scene.mesh.min_angle_deg;
  p.mesh = ng::geometry::meshDomain(scene.workspacePolygon(), scene.background_material, regions,
                                    options);
  std::vector<char> fixed_node(p.mesh.nodeCount(), 0);
  for (std::size_t t = 0; t < p.mesh.triangleCount(); ++t) {
    const int region = p.mesh.triangle_region[t];
    const std::string material =
        region == 0 ? scene.background_material : scene.regions[region - 1].material;
    const auto& m = scene.material(material);
    tissue::ElementMaterial em;
    em.young_modulus_Pa = m.young_modulus_Pa;
    em.poisson_ratio = m.poisson_ratio;
    em.density_kg_m3 = m.density_kg_m3;
    em.rayleigh_alpha_per_s = m.rayleigh_alpha_per_s;
    em.rayleigh_beta_s = m.rayleigh_beta_s;
    p.materials.push_back(em);
    if (region > 0 && scene.regions[region - 1].rigid) {
      for (int n : p.mesh.triangles[t])
        fixed_node[n] = 1;
    }
  }
  for (int n : p.mesh.boundaryNodes()) {
    if (scene.boundaryConditionAt(p.mesh.nodes[n]) == ng::scene::BoundaryCondition::kFixed)
      fixed_node[n] = 1;
  }
  for (std::size_t n = 0; n < p.mesh.nodeCount(); ++n) {
    if (fixed_node[n]) {
      p.fixed_dofs.push_back(tissue::dofX(static_cast<int>(n)));
      p.fixed_dofs.push_back(tissue::dofY(static_cast<int>(n)));
    }
  }
  // Needle line: mid insertion height; nodes within half an edge of it, interior, not fixed.
  const double y_needle = 0.5 * (scene.needle.min_height_m + scene.needle.max_height_m);
  const double x_min = scene.workspace_min.x() + 2.0 * edge_m;
  const double x_max = scene.workspace_max.x() - 2.0 * edge_m;
  std::vector<std::pair<double, int>> candidates;
  for (std::size_t n = 0; n < p.mesh.nodeCount(); ++n) {
    const auto& x = p.mesh.nodes[n];
    if (!fixed_node[n] && std::abs(x.y() - y_needle) < 0.5 * edge_m && x.x() > x_min &&
        x.x() < x_max) {
      candidates.emplace_back(x.x(), static_cast<int>(n));
    }
  }
  std::sort(candidates.begin(), candidates.end());
  for (const auto& c : candidates)
    p.needle_nodes.push_back(c.second);
  return p;
}

struct Result {
  double steps_per_s = 0.0;
  double mean_latency_ms = 0.0;
  double max_latency_ms = 0.0;
  int steps = 0;
  int moves = 0;
  tissue::Integrator::SolverCounters counters;
};

Result run(const Problem& problem, tissue::IntegratorKind kind, bool mesh_changes, int steps) {
  tissue::FemModel model(problem.mesh, problem.materials);
  auto integ = tissue::makeIntegrator(kind, model, problem.fixed_dofs);
  const double dt_s = kind == tissue::IntegratorKind::kExplicit
                          ? 0.9 * 0.9 * integ->stableTimeStep()
                          : kNewmarkDt_s;
  const Eigen::VectorXd f = Eigen::VectorXd::Zero(model.dofCount());
  Result result;
  std::size_t tip_index = 0;
  std::vector<int> shaft;
  Eigen::VectorXd reactions;
  double total_s = 0.0;
  for (int s = 0; s < steps; ++s) {
    const auto start = Clock::now();
    const int tip = problem.needle_nodes[tip_index];
    if (mesh_changes) {
      if (s % kShaftEverySteps == kShaftEverySteps - 1 &&
          tip_index + 1 < problem.needle_nodes.size()) {
        shaft.push_back(tip);
        ++tip_index;
      }
      if (s % kMoveEverySteps == 1) {
        // Cutting: nudge the tip node back and forth along x in the reference mesh.
        const double nudge_m = ((s / kMoveEverySteps) % 2 ? -1.0 : 1.0) * 1e-5;
        const ng::geometry::Point2 p_new =
            model.mesh().nodes[tip] + ng::geometry::Point2(nudge_m, 0.0);
        if (model.canMoveNode(tip, p_new, 0.0)) {
          integ->modelChanged(model.moveNode(tip, p_new));
          ++result.moves;
        }
      }
    }
    tissue::Prescribed p;
    const int tip_now = problem.needle_nodes[tip_index];
    p.dofs = {tissue::dofX(tip_now), tissue::dofY(tip_now)};
    p.values = {kTipSpeed_m_s * kNewmarkDt_s * std::min(s + 1, 200), 0.0};  // up to 2 mm
    for (int sn : shaft) {
      p.dofs.push_back(tissue::dofY(sn));
      p.values.push_back(0.0);
    }
    const tissue::StepStatus status = integ->step(dt_s, f, p, reactions);
    if (!status)
      throw std::runtime_error(std::string("step failed: ") + status.message);
    const double step_s = secondsSince(start);
    total_s += step_s;
    result.max_latency_ms = std::max(result.max_latency_ms, 1e3 * step_s);
  }
  result.steps = steps;
  result.steps_per_s = steps / total_s;
  result.mean_latency_ms = 1e3 * total_s / steps;
  result.counters = integ->solverCounters();
  return result;
}

}  // namespace

int main(int argc, char** argv) {
  const std::optional<ng::report::BenchArgs> args =
      ng::report::parseBenchArgs(argc, argv, "bench_fem");
  if (!args) {
    return 2;
  }
  const std::string& out_dir = args->out_dir;
  const bool quick = args->quick;
  try {
    const ng::scene::Scene scene = ng::scene::loadSceneSpec(args->scene);
    const double area_m2 = scene.workspacePolygon().area();
    const std::vector<double> targets =
        quick ? std::vector<double>{1250, 12000} : std::vector<double>{1250, 3000, 12000, 50000};
    ng::report::Table table({"triangles", "nodes", "integrator", "mesh_changes", "steps",
                             "steps_per_s", "mean_latency_ms", "max_latency_ms", "moves",
                             "factorizations", "row_deletions", "row_additions", "rank_updates"},
                            6);
    std::ostringstream json;
    json.precision(6);
    json << "{\n  \"benchmark\": \"fem\",\n  \"quick\": " << (quick ? "true" : "false");
    for (double target : targets) {
      // Uniform edge for ≈target triangles (equilateral area sqrt(3)/4 h^2), corrected once.
      double edge_m = std::sqrt(area_m2 / (target * std::sqrt(3.0) / 4.0));
      Problem problem = makeProblem(scene, edge_m);
      edge_m *= std::sqrt(problem.mesh.triangleCount() / target);
      problem = makeProblem(scene, edge_m);
      const double n_tri = static_cast<double>(problem.mesh.triangleCount());
      const int steps = static_cast<int>(std::clamp(2.0e6 / n_tri, 60.0, quick ? 600.0 : 3000.0));
      std::cout << "mesh: " << problem.mesh.triangleCount() << " triangles, "
                << problem.mesh.nodeCount() << " nodes, " << problem.needle_nodes.size()
                << " needle-line nodes, edge " << 1e3 * edge_m << " mm\n";
      for (auto kind : {tissue::IntegratorKind::kQuasiStatic, tissue::IntegratorKind::kNewmark,
                        tissue::IntegratorKind::kExplicit}) {
        for (bool changes : {false, true}) {
          const Result r = run(problem, kind, changes, steps);
          table.addRow({n_tri, double(problem.mesh.nodeCount()),
                        std::string(tissue::toString(kind)), std::string(changes ? "yes" : "no"),
                        double(r.steps), r.steps_per_s, r.mean_latency_ms, r.max_latency_ms,
                        double(r.moves), double(r.counters.factorizations),
                        double(r.counters.row_deletions), double(r.counters.row_additions),
                        double(r.counters.rank_updates)});
          std::cout << "  " << tissue::toString(kind)
                    << (changes ? " +mesh changes" : "               ") << ": " << r.steps_per_s
                    << " steps/s (mean " << r.mean_latency_ms << " ms, max " << r.max_latency_ms
                    << " ms), factorizations " << r.counters.factorizations << "\n";
          const std::string size_key = target == 1250 ? "1250" : target == 50000 ? "50k" : "";
          if (!size_key.empty()) {
            json << ",\n  \"steps_per_s_" << size_key << "_" << tissue::toString(kind)
                 << (changes ? "_mesh_changes" : "") << "\": " << r.steps_per_s;
            if (kind == tissue::IntegratorKind::kNewmark && changes) {
              json << ",\n  \"steps_per_s_" << size_key << "_implicit\": " << r.steps_per_s;
            }
          }
        }
      }
    }
    json << "\n}\n";
    table.writeCsv(out_dir + "/fem.csv");
    ng::report::writeTextFile(out_dir + "/summary.json", json.str());
    ng::report::writeTextFile(
        out_dir + "/plot.json",
        R"json([{"csv": "fem.csv", "x": "triangles", "y": "steps_per_s", "group": "integrator",
  "title": "FEM solver steps per second, synthetic needle load (one core)", "logx": true,
  "logy": true, "png": "fem_steps_per_s.png"}])json");
    std::cout << table.toText();
  } catch (const std::exception& e) {
    std::cerr << "bench_fem: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
