// Benchmark of the needle–tissue interaction calibrated to measured liver forces: the shipped
// preset's force error on held-out trials of de Jong et al. 2017 against the spread between the
// trials, the FEM force curve's convergence in the depth step with its CPU time, and the
// unplanned seed error of the prostate scene with the scene's own and with the calibrated
// interaction. Usage: bench_calibration --out DIR [--quick] [--scene SPEC]

#include <cmath>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/calibration/calibration.h"
#include "needle_guidance/cpu_time.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/process_usage.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/rigid_planning/rigid_planner.h"
#include "needle_guidance/scene/interaction_preset.h"

namespace ng = needle_guidance;
using needle_guidance::processCpuSeconds;
namespace cal = needle_guidance::calibration;
using ng::report::jsonNumber;

namespace {

constexpr const char* kPreset = "liver_de_jong_2017";
/// Points of the 0.5 mm compare grid averaged into one trend point (2 mm).
constexpr std::size_t kTrendWindow = 4;

/// Unplanned error (release at the target, dissertation 4.4) of every target [cm].
std::vector<double> unplannedErrors(const ng::scene::Scene& scene, std::size_t count) {
  const ng::rigid_planning::RigidPlanner planner(scene, ng::rigid_planning::PlannerOptions{});
  std::vector<double> errors;
  for (std::size_t i = 0; i < count && i < scene.targets.size(); ++i) {
    const auto plan = planner.unplanned(scene.targets[i].position);
    errors.push_back(plan ? 1e2 * plan.predicted_error_m : std::nan(""));
  }
  return errors;
}

/// Means over consecutive windows of `width` points: the curve's trend without the jitter of
/// single cuts.
std::vector<double> windowMeans(const std::vector<double>& v, std::size_t width) {
  std::vector<double> means;
  for (std::size_t i = 0; i + width <= v.size(); i += width) {
    double s = 0.0;
    for (std::size_t k = i; k < i + width; ++k) {
      s += v[k];
    }
    means.push_back(s / static_cast<double>(width));
  }
  return means;
}

double mean(const std::vector<double>& v) {
  double s = 0.0;
  for (double x : v) {
    s += x;
  }
  return v.empty() ? std::nan("") : s / static_cast<double>(v.size());
}

}  // namespace

int main(int argc, char** argv) {
  const auto args = ng::report::parseBenchArgs(argc, argv, "bench_calibration");
  if (!args) {
    return 2;
  }
  try {
    const cal::InteractionModel preset = cal::loadPreset(kPreset);
    std::string source;
    const std::vector<cal::ForceTrial> trials = cal::liverHeldOutTrials(&source);
    double t0 = processCpuSeconds();
    const cal::PresetCheck check = cal::checkPreset(preset, trials);
    const double check_cpu_s = processCpuSeconds() - t0;

    // Convergence of the FEM's force curve in the depth step: RMSE against the finest step.
    const std::vector<double> steps_mm =
        args->quick ? std::vector<double>{0.4, 0.2, 0.1} : std::vector<double>{0.4, 0.2, 0.1, 0.05};
    std::vector<std::vector<double>> curves;
    std::vector<double> cpu;
    for (double step_mm : steps_mm) {
      cal::InteractionModel m = preset;
      m.block.depth_step_m = 1e-3 * step_mm;
      t0 = processCpuSeconds();
      curves.push_back(cal::femInsertionForce(m.block, m.needle, check.depths_m));
      cpu.push_back(processCpuSeconds() - t0);
    }
    ng::report::Table convergence(
        {"depth_step_mm", "rmse_vs_finest_N", "trend_rmse_vs_finest_N", "cpu_s"}, 6);
    auto trend = [](const std::vector<double>& c) { return windowMeans(c, kTrendWindow); };
    for (std::size_t i = 0; i + 1 < steps_mm.size(); ++i) {
      convergence.addRow({steps_mm[i], cal::rmse(curves[i], curves.back()),
                          cal::rmse(trend(curves[i]), trend(curves.back())), cpu[i]});
    }
    convergence.writeCsv(args->out_dir + "/convergence.csv");

    // Unplanned seed error on the prostate scene: its own interaction against the preset's.
    const ng::scene::Scene own = ng::scene::loadSceneSpec(args->scene);
    ng::scene::Scene calibrated = own;
    const ng::scene::Needle keys = ng::scene::loadInteractionPreset(kPreset);
    calibrated.needle.cutting_force_N = keys.cutting_force_N;
    calibrated.needle.cut_length_m = keys.cut_length_m;
    calibrated.needle.static_friction_N_per_m = keys.static_friction_N_per_m;
    calibrated.needle.kinetic_friction_N_per_m = keys.kinetic_friction_N_per_m;
    calibrated.needle.stick_velocity_m_s = keys.stick_velocity_m_s;
    calibrated.needle.diameter_m = keys.diameter_m;
    const std::size_t count = args->quick ? 4 : own.targets.size();
    const std::vector<double> own_cm = unplannedErrors(own, count);
    const std::vector<double> calibrated_cm = unplannedErrors(calibrated, count);
    ng::report::Table seeds({"target", "unplanned_error_own_cm", "unplanned_error_preset_cm"}, 6);
    for (std::size_t i = 0; i < own_cm.size(); ++i) {
      seeds.addRow({own.targets[i].name, own_cm[i], calibrated_cm[i]});
    }
    seeds.writeCsv(args->out_dir + "/unplanned.csv");

    ng::report::Table scores({"trial", "rmse_N", "trial_spread_N"}, 6);
    for (const auto& s : check.scores) {
      scores.addRow({s.name, s.rmse_N, s.spread_N});
    }
    scores.writeCsv(args->out_dir + "/held_out.csv");
    ng::report::Table curve({"curve", "depth_mm", "force_N"}, 6);
    for (std::size_t t = 0; t < trials.size(); ++t) {
      for (std::size_t i = 0; i < check.depths_m.size(); ++i) {
        curve.addRow({trials[t].name, 1e3 * check.depths_m[i], check.measured[t][i]});
      }
    }
    for (std::size_t i = 0; i < check.depths_m.size(); ++i) {
      curve.addRow({std::string("FEM, preset"), 1e3 * check.depths_m[i], check.simulated_N[i]});
    }
    curve.writeCsv(args->out_dir + "/force_depth.csv");

    std::ostringstream j;
    j << "{\n  \"benchmark\": \"calibration\",\n  \"preset\": \"" << kPreset << "\",\n"
      << "  \"held_out_trials\": " << trials.size() << ",\n  \"held_out_source\": \"" << source
      << "\",\n  \"calibration_force_rmse_N\": " << jsonNumber(check.summary.rmse_median_N)
      << ",\n  \"calibration_force_rmse_N_p90\": " << jsonNumber(check.summary.rmse_p90_N)
      << ",\n  \"calibration_trial_spread_N\": " << jsonNumber(check.summary.spread_median_N)
      << ",\n  \"calibration_trial_spread_N_p90\": " << jsonNumber(check.summary.spread_p90_N)
      << ",\n  \"calibration_rmse_within_spread\": "
      << (check.summary.rmse_median_N <= check.summary.spread_median_N ? "true" : "false")
      << ",\n  \"check_cpu_s\": " << jsonNumber(check_cpu_s)
      << ",\n  \"fem_curve_rmse_step_halving_N\": "
      << jsonNumber(cal::rmse(curves[curves.size() - 2], curves.back()))
      << ",\n  \"fem_curve_trend_rmse_step_halving_N\": "
      << jsonNumber(cal::rmse(trend(curves[curves.size() - 2]), trend(curves.back())))
      << ",\n  \"fem_curve_cpu_s\": " << jsonNumber(cpu[cpu.size() - 2]) << ",\n  \"scene\": \""
      << own.name << "\",\n  \"unplanned_error_cm_mean_scene\": " << jsonNumber(mean(own_cm))
      << ",\n  \"unplanned_error_cm_mean_preset\": " << jsonNumber(mean(calibrated_cm))
      << ",\n  \"unplanned_error_cm_dissertation\": 0.59\n}\n";
    ng::report::writeTextFile(args->out_dir + "/summary.json", j.str());
    ng::report::writeTextFile(
        args->out_dir + "/plot.json",
        R"json([{"csv": "force_depth.csv", "x": "depth_mm", "y": "force_N", "group": "curve",
  "title": "Held-out liver insertions (de Jong 2017) and the calibrated FEM", "png": "force_depth.png"},
 {"csv": "convergence.csv", "x": "cpu_s", "y": "trend_rmse_vs_finest_N", "logx": true, "logy": true,
  "annotate": "depth_step_mm", "title": "FEM force trend (2 mm means): change against CPU time over the depth step",
  "png": "convergence.png"}])json");
    std::cout << convergence.toText() << seeds.toText() << j.str();
  } catch (const std::exception& e) {
    std::cerr << "bench_calibration: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
