// Benchmark of the tissue simulation: a real needle insertion on the default prostate
// scene (cutting, shaft friction, node promotion), seed implant at the target, retraction, for
// each integrator on graded meshes from ~1k to ~50k triangles. Reports steps per second and
// per-step latency against seed position error (vs. the finest quasi-static run), and memory.
// Usage: bench_tissue --out DIR [--quick] [--scene SPEC]   (SPEC: a scene file or embedded name)

#include <algorithm>
#include <chrono>
#include <cmath>
#include <iostream>
#include <map>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/process_usage.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue/tissue_simulation.h"

namespace ng = needle_guidance;
using needle_guidance::report::peakMb;
using ng::tissue::IntegratorKind;
using Clock = std::chrono::steady_clock;

namespace {

constexpr double kDt_s = 1e-3;          // haptic rate
constexpr double kVelocity_m_s = 0.02;  // insertion and retraction speed
constexpr double kStart_m = -0.002;     // tip just outside the entry face
constexpr double kSettle_s = 2.0;  // dynamic integrators settle with the needle out (alpha = 1/s)
constexpr double kMaxRunSteps = 400000;   // skip a full run that would take more steps
constexpr double kMaxRunSeconds = 150.0;  // ... or longer than this (estimated)

struct RunResult {
  int triangles = 0;
  long steps = 0;
  double steps_per_s = 0.0;
  double p50_ms = 0.0, p99_ms = 0.0;
  double dt_s = 0.0;
  bool complete = false;  ///< full insertion-implant-retraction run (else timing only)
  ng::geometry::Point2 seed = {NAN, NAN};
  ng::geometry::Point2 tip_ref = {NAN, NAN};  ///< material point at the tip at full depth
  double tip_force_N = 0.0;
  double peak_mb = 0.0;
  std::string note;
};

/// Runs the insertion. With timing_steps > 0 only that many steps are timed (no seed).
RunResult run(const ng::scene::Scene& scene, const ng::tissue::TissueSimOptions& options,
              const ng::geometry::Point2& target, long timing_steps) {
  ng::tissue::TissueSimulation sim(scene, options);
  RunResult r;
  r.triangles = static_cast<int>(sim.mesh().triangleCount());
  r.dt_s = sim.needleModel() == ng::tissue::NeedleModel::kNodeMoving
               ? std::min(kDt_s, 0.9 * sim.integrator().stableTimeStep())
               : kDt_s;
  const double dx = kVelocity_m_s * r.dt_s;
  std::vector<double> step_ms;
  double x = kStart_m;
  const double h = target.y();
  auto step = [&](double next_x) {
    const auto start = Clock::now();
    const ng::tissue::StepStatus status = sim.step(r.dt_s, h, next_x);
    step_ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - start).count());
    if (!status) {
      throw std::runtime_error("step refused at x = " + std::to_string(next_x) + ": " +
                               status.toString());
    }
    x = next_x;
  };
  const auto wall = Clock::now();
  while (x < target.x() - 1e-12 &&
         (timing_steps <= 0 || static_cast<long>(step_ms.size()) < timing_steps)) {
    step(std::min(target.x(), x + dx));
  }
  if (timing_steps <= 0) {
    r.tip_ref = *sim.tipReference();
    r.tip_force_N = sim.lastStep().tip_force_N;
    const std::optional<int> id = sim.implantSeed();
    if (!id) {
      throw std::runtime_error("seed not implanted");
    }
    while (x > kStart_m + 1e-12) {
      step(std::max(kStart_m, x - dx));
    }
    for (double t = 0.0; options.integrator != IntegratorKind::kQuasiStatic && t < kSettle_s;
         t += r.dt_s) {
      step(kStart_m);
    }
    r.seed = sim.seedPosition(sim.seeds().at(static_cast<std::size_t>(*id)));
    r.complete = true;
  }
  const double wall_s = std::chrono::duration<double>(Clock::now() - wall).count();
  r.steps = static_cast<long>(step_ms.size());
  r.steps_per_s = r.steps / wall_s;
  std::sort(step_ms.begin(), step_ms.end());
  r.p50_ms = step_ms[step_ms.size() / 2];
  r.p99_ms = step_ms[std::min(step_ms.size() - 1, (step_ms.size() * 99) / 100)];
  r.peak_mb = peakMb();
  return r;
}

}  // namespace

int main(int argc, char** argv) {
  const std::optional<ng::report::BenchArgs> args =
      ng::report::parseBenchArgs(argc, argv, "bench_tissue");
  if (!args) {
    return 2;
  }
  const std::string& out_dir = args->out_dir;
  const bool quick = args->quick;
  try {
    const ng::scene::Scene scene = ng::scene::loadSceneSpec(args->scene);
    const ng::geometry::Point2 target = scene.target("t06").position;
    // Graded meshes: the scene's sizes (fine at the targets) scaled down; scale 1 is the default.
    const std::vector<double> scales =
        quick ? std::vector<double>{1.0, 0.5} : std::vector<double>{1.0, 0.5, 0.3, 0.185};
    const std::vector<IntegratorKind> kinds{IntegratorKind::kQuasiStatic, IntegratorKind::kNewmark,
                                            IntegratorKind::kExplicit};
    std::map<std::pair<int, double>, RunResult> results;
    for (double scale : scales) {
      for (IntegratorKind kind : kinds) {
        ng::tissue::TissueSimOptions options = ng::tissue::optionsFromScene(scene);
        options.integrator = kind;
        // The integrators are compared on one interaction model: the node-moving cut, the one
        // the dynamic integrators run.
        options.needle_model = ng::tissue::NeedleModel::kNodeMoving;
        options.meshing.max_edge_m *= scale;
        options.meshing.min_edge_m *= scale;
        // Estimate the full run from a short timed run; skip runs that would be too long.
        RunResult probe = run(scene, options, target, 60);
        const double full_steps =
            2.0 * (target.x() - kStart_m) / (kVelocity_m_s * probe.dt_s) +
            (kind == IntegratorKind::kQuasiStatic ? 0.0 : kSettle_s / probe.dt_s);
        const double full_s = full_steps / probe.steps_per_s;
        RunResult r = probe;
        if (full_steps <= kMaxRunSteps && full_s <= kMaxRunSeconds) {
          r = run(scene, options, target, 0);
        } else {
          r.note = "timing only: a full run needs " + std::to_string(long(full_steps)) +
                   " steps (dt " + std::to_string(probe.dt_s) + " s), ~" +
                   std::to_string(long(full_s)) + " s";
        }
        std::cout << ng::tissue::toString(kind) << " scale " << scale << ": " << r.triangles
                  << " triangles, dt " << r.dt_s << " s, " << r.steps_per_s << " steps/s, p99 "
                  << r.p99_ms << " ms"
                  << (r.complete ? ", seed short of target " +
                                       std::to_string(1e3 * (target - r.seed).norm()) + " mm"
                                 : " (" + r.note + ")")
                  << "\n"
                  << std::flush;
        results[{static_cast<int>(kind), scale}] = r;
      }
    }
    // Errors of each run against the finest complete run of the same integrator (numerical
    // error), and against the finest quasi-static run (numerical + modelling difference).
    const RunResult& reference =
        results.at({static_cast<int>(IntegratorKind::kQuasiStatic), scales.back()});
    auto finest = [&](int kind) -> const RunResult* {
      for (auto it = scales.rbegin(); it != scales.rend(); ++it) {
        const RunResult& r = results.at({kind, *it});
        if (r.complete)
          return &r;
      }
      return nullptr;
    };
    ng::report::Table table(
        {"integrator", "mesh_scale", "triangles", "dt_s", "steps", "steps_per_s", "p50_ms",
         "p99_ms", "seed_error_mm", "tip_ref_error_mm", "seed_vs_quasi_static_mm", "seed_short_mm",
         "tip_force_N", "peak_mb", "note"},
        6);
    for (const auto& [key, r] : results) {
      const RunResult* own = finest(key.first);
      const bool has = r.complete && own != nullptr && own != &r;
      const double seed_error = has ? 1e3 * (r.seed - own->seed).norm() : NAN;
      const double tip_error = has ? 1e3 * (r.tip_ref - own->tip_ref).norm() : NAN;
      const double vs_qs = r.complete ? 1e3 * (r.seed - reference.seed).norm() : NAN;
      const double short_mm = r.complete ? 1e3 * (target - r.seed).norm() : NAN;
      table.addRow({std::string(ng::tissue::toString(static_cast<IntegratorKind>(key.first))),
                    key.second, double(r.triangles), r.dt_s, double(r.steps), r.steps_per_s,
                    r.p50_ms, r.p99_ms, seed_error, tip_error, vs_qs, short_mm, r.tip_force_N,
                    r.peak_mb,
                    r.note.empty() ? std::string(own == &r ? "reference" : "") : r.note});
    }
    auto get = [&](IntegratorKind kind, double scale) -> const RunResult& {
      return results.at({static_cast<int>(kind), scale});
    };
    const RunResult& default_qs = get(IntegratorKind::kQuasiStatic, 1.0);
    const RunResult& default_nm = get(IntegratorKind::kNewmark, 1.0);
    std::ostringstream json;
    json.precision(6);
    json << "{\n  \"benchmark\": \"tissue\",\n  \"scene\": \"" << scene.name << "\",\n"
         << "  \"quick\": " << (quick ? "true" : "false") << ",\n"
         << "  \"insertion\": \"target t06, " << 1e3 * kVelocity_m_s << " mm/s, dt " << kDt_s
         << " s, seed implant, retraction\",\n"
         << "  \"reference\": \"quasi_static, " << reference.triangles << " triangles\",\n"
         << "  \"triangles_default\": " << default_qs.triangles << ",\n"
         << "  \"steps_per_s_1250_implicit\": " << default_nm.steps_per_s << ",\n"
         << "  \"steps_per_s_1250_quasi_static\": " << default_qs.steps_per_s << ",\n"
         << "  \"p99_ms_1250_implicit\": " << default_nm.p99_ms << ",\n";
    if (!quick) {
      const RunResult& big = get(IntegratorKind::kNewmark, scales.back());
      json << "  \"triangles_50k\": " << big.triangles << ",\n"
           << "  \"steps_per_s_50k_implicit\": " << big.steps_per_s << ",\n"
           << "  \"steps_per_s_50k_quasi_static\": "
           << get(IntegratorKind::kQuasiStatic, scales.back()).steps_per_s << ",\n"
           << "  \"peak_mb_50k\": " << get(IntegratorKind::kExplicit, scales.back()).peak_mb
           << ",\n";
    }
    json << "  \"seed_error_mm_default\": " << 1e3 * (default_qs.seed - reference.seed).norm()
         << ",\n"
         << "  \"seed_error_mm_default_implicit\": "
         << (default_nm.complete && finest(static_cast<int>(IntegratorKind::kNewmark))
                 ? 1e3 *
                       (default_nm.seed - finest(static_cast<int>(IntegratorKind::kNewmark))->seed)
                           .norm()
                 : -1.0)
         << ",\n"
         << "  \"seed_short_of_target_mm_reference\": " << 1e3 * (target - reference.seed).norm()
         << "\n}\n";
    table.writeCsv(out_dir + "/tissue.csv");
    ng::report::writeTextFile(out_dir + "/summary.json", json.str());
    ng::report::writeTextFile(
        out_dir + "/plot.json",
        R"json([{"csv": "tissue.csv", "x": "steps_per_s", "y": "seed_error_mm", "group": "integrator",
  "annotate": "triangles", "title": "Speed vs seed error (reference: finest run of the same integrator)",
  "logx": true, "logy": true, "png": "pareto_speed_vs_seed_error.png"},
 {"csv": "tissue.csv", "x": "triangles", "y": "steps_per_s", "group": "integrator",
  "title": "Steps per second vs mesh size (one core)", "logx": true, "logy": true,
  "png": "steps_per_s_vs_triangles.png"}])json");
    std::cout << table.toText();
  } catch (const std::exception& e) {
    std::cerr << "bench_tissue: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
