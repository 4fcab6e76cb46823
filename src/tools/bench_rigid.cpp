// Benchmark of rigid-needle offset planning (dissertation 4.4): 12 targets in the
// prostate, golden section over y_t +- 0.2 cm to 0.01 cm, needle at 0.5 cm/s. For each target:
// unplanned, depth-only and planned release points, their predicted errors, the error measured
// by an independent full simulation (insert to the release point, implant, retract), and the
// planning time (one plan at a time, and the batch of all targets on every core); then planning
// speed against placement error over mesh size and time step. Usage: bench_rigid --out DIR
// [--quick]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <iostream>
#include <limits>
#include <numeric>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "needle_guidance/calibration/calibration.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/statistics.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/rigid_planning/rigid_planner.h"

namespace ng = needle_guidance;
using ng::geometry::Point2;

namespace {

/// Inserts at the release height to the release depth, implants, retracts, and returns where
/// the seed ends up: the ground truth a plan is checked against, in a simulation of its own
/// (fresh mesh and model, the procedure's step schedule).
Point2 simulateImplant(const ng::scene::Scene& scene, const ng::tissue::TissueSimOptions& options,
                       const Point2& release, const Point2& target,
                       const ng::rigid_planning::ImplantSchedule& schedule) {
  ng::tissue::TissueSimOptions o = options;  // meshed as the live tissue_sim meshes the scene
  if (std::find(o.meshing.refine_points.begin(), o.meshing.refine_points.end(), target) ==
      o.meshing.refine_points.end()) {
    o.meshing.refine_points.push_back(target);
    o.meshing.refine_lines.push_back({Point2(scene.workspace_min.x(), target.y()), target});
  }
  ng::tissue::TissueSimulation sim(scene, o);
  return ng::rigid_planning::simulateImplant(sim, release, schedule);
}

/// The liver interaction preset's force error on its held-out trials against the spread
/// between those trials (scripts/bench calibration has the details), as JSON members.
std::string calibrationJson() {
  std::string source;
  const auto trials = ng::calibration::liverHeldOutTrials(&source);
  const auto check =
      ng::calibration::checkPreset(ng::calibration::loadPreset("liver_de_jong_2017"), trials);
  std::ostringstream j;
  j << ",\n  \"calibration_force_rmse_N\": " << ng::report::jsonNumber(check.summary.rmse_median_N)
    << ",\n  \"calibration_trial_spread_N\": "
    << ng::report::jsonNumber(check.summary.spread_median_N) << ",\n  \"calibration_source\": \""
    << trials.size() << " held-out trials in " << source << "\"";
  return j.str();
}

/// Heights of the window study of a target refused out of tolerance: scans at this spacing
/// over the planner's whole height window show whether a release on the procedure's depth grid
/// lands within the tolerance (the planner's search missed it) or none does on this grid of
/// heights (evidence, not proof: a height between two of them may do better).
constexpr double kWindowStudySpacing_m = 5e-5;

/// The smallest error of a release on the depth grid over every height of the planner's window,
/// scanned kWindowStudySpacing_m apart (no search, no verification) [m].
double windowStudyBestError(const ng::scene::Scene& scene, const Point2& target) {
  ng::rigid_planning::PlannerOptions o;
  o.secant_iterations = 0;  // every height of the grid, no shortcut
  o.grid_points =
      static_cast<int>(std::lround(2.0 * o.height_window_m / kWindowStudySpacing_m)) + 1;
  o.error_goal_m = 1e-12;
  o.height_tolerance_m = 1.0;  // no golden section after the grid
  o.work_budget = 0.0;
  o.verify = false;
  o.refuse_over_tolerance = false;
  const ng::rigid_planning::RigidPlan plan =
      ng::rigid_planning::RigidPlanner(scene, o).plan(target, 0.0);
  double best = std::numeric_limits<double>::infinity();
  for (const auto& scan : plan.scans) {
    best = std::min(best, scan.best_error_m);
  }
  return best;
}

/// Per-scene figures of the multi-scene part of the bench.
struct SceneFigures {
  std::string name, spec;
  int targets = 0, planned = 0, refused = 0, over_tolerance = 0;
  int unreachable = 0;  ///< refused for physics: outside the tissue, in bone, out of range
  /// Of the targets refused out of tolerance: the window study's best error [mm]
  std::vector<double> window_best_mm;
  std::vector<double> halving_mm;  ///< seed change when the depth grid step is halved [mm]
  std::vector<double> predicted_cm, verified_cm, measured_cm, unplanned_cm, legacy_gap_cm, pvm_cm,
      live_cm, seconds, cpu_seconds, simulations, fem_steps, solver_work;
};

double maxOf(const std::vector<double>& v) {
  return v.empty() ? 0.0 : *std::max_element(v.begin(), v.end());
}

using ng::report::mean;
using ng::report::quantile;
using ng::report::sampleSd;

/// Plans every target of one scene and measures each plan in an independent full simulation;
/// rows go to `rows`. The O(1) prediction of the dissertation's scan (coarser approach steps,
/// release interpolated between steps) is measured at the same release point (legacy_gap).
SceneFigures evaluateScene(const std::string& spec, bool quick, ng::report::Table& rows) {
  const ng::scene::Scene scene = ng::scene::loadSceneSpec(spec);
  const ng::rigid_planning::RigidPlanner planner(scene, ng::rigid_planning::PlannerOptions{});
  ng::rigid_planning::PlannerOptions legacy_options;
  legacy_options.procedure_grid = false;
  legacy_options.verify = false;
  const ng::rigid_planning::RigidPlanner legacy(scene, legacy_options);
  SceneFigures f;
  f.name = scene.name;
  f.spec = spec;
  const std::size_t count =
      quick ? std::min<std::size_t>(4, scene.targets.size()) : scene.targets.size();
  double previous_offset = 0.0;
  for (std::size_t i = 0; i < count; ++i) {
    const auto& target = scene.targets[i];
    ++f.targets;
    const auto plan = planner.plan(target.position, previous_offset);
    if (!plan) {
      ++f.refused;
      f.unreachable += plan.code == ng::rigid_planning::PlanCode::kOutOfTolerance ||
                               plan.code == ng::rigid_planning::PlanCode::kSimulationFailed
                           ? 0
                           : 1;
      f.seconds.push_back(plan.seconds);  // a refusal's planning time counts too
      f.fem_steps.push_back(static_cast<double>(plan.fem_steps));
      f.solver_work.push_back(plan.solver_work);
      f.cpu_seconds.push_back(plan.cpu_seconds);
      const ng::report::Cell none{std::string()};  // never inserted: no error figures
      const bool over = plan.code == ng::rigid_planning::PlanCode::kOutOfTolerance;
      const double window_mm = over ? 1e3 * windowStudyBestError(scene, target.position) : NAN;
      if (over) {
        f.window_best_mm.push_back(window_mm);
      }
      // Out of tolerance: the best plan's verified error says by how much.
      const ng::report::Cell verified = std::isfinite(plan.verified_error_m)
                                            ? ng::report::Cell(1e3 * plan.verified_error_m)
                                            : none;
      rows.addRow({scene.name,
                   target.name,
                   1e3 * target.position.x(),
                   1e3 * target.position.y(),
                   std::string("refused"),
                   none,
                   none,
                   verified,
                   none,
                   none,
                   none,
                   none,
                   none,
                   none,
                   double(plan.simulations),
                   plan.seconds,
                   plan.cpu_seconds,
                   double(plan.fem_steps),
                   plan.solver_work,
                   over ? ng::report::Cell(window_mm) : none,
                   std::string(plan.message)});
      std::cout << scene.name << "/" << target.name << ": refused: " << plan.message
                << (over ? " (window study: best grid release " + std::to_string(window_mm) + " mm)"
                         : std::string())
                << "\n"
                << std::flush;
      continue;
    }
    previous_offset = plan.release.y() - target.position.y();  // warm start for the next target
    ++f.planned;
    const auto sim_options = ng::tissue::optionsFromScene(scene);
    const Point2 seed =
        simulateImplant(scene, sim_options, plan.release, target.position, planner.schedule());
    const Point2 unplanned_seed =
        simulateImplant(scene, sim_options, target.position, target.position, planner.schedule());
    const double measured = (seed - target.position).norm();
    // The live loop commands the tissue on its own clock (tissue_sim at 200 Hz: 0.05 mm samples
    // at 1 cm/s, from the robot's retract depth of -5 mm); the depth grid must make that land
    // where the planner's schedule did: the gap should be 0.
    ng::rigid_planning::ImplantSchedule live = planner.schedule();
    live.sample_m = 5e-5;
    live.start_x_m = scene.workspace_min.x() - 0.005;
    const double live_gap =
        (simulateImplant(scene, sim_options, plan.release, target.position, live) - seed).norm();
    f.live_cm.push_back(1e2 * live_gap);
    // The same release with the depth grid's step halved: converged in the step.
    ng::tissue::TissueSimOptions halved = sim_options;
    halved.depth_grid.step_m *= 0.5;
    f.halving_mm.push_back(
        1e3 *
        (simulateImplant(scene, halved, plan.release, target.position, planner.schedule()) - seed)
            .norm());
    // The dissertation's scan (0.5 mm approach steps) may be refused where the grid is not (a
    // step needing more cuts than a step allows): its gap is then undefined, not a failure of
    // the plan.
    double legacy_gap = NAN;
    try {
      const auto legacy_scan = legacy.scanHeight(target.position, plan.release.y());
      legacy_gap = (legacy_scan.implantAt(plan.release.x()) - seed).norm();
    } catch (const std::exception& e) {
      std::cout << scene.name << "/" << target.name
                << ": O(1)-interpolated scan refused: " << e.what() << "\n";
    }
    const double pvm = (plan.predicted_implant - seed).norm();
    const bool placed = measured <= plan.tolerance_m;
    f.over_tolerance += placed ? 0 : 1;
    f.predicted_cm.push_back(1e2 * plan.predicted_error_m);
    f.verified_cm.push_back(1e2 * plan.verified_error_m);
    f.measured_cm.push_back(1e2 * measured);
    f.unplanned_cm.push_back(1e2 * (unplanned_seed - target.position).norm());
    if (std::isfinite(legacy_gap)) {
      f.legacy_gap_cm.push_back(1e2 * legacy_gap);
    }
    f.pvm_cm.push_back(1e2 * pvm);
    f.seconds.push_back(plan.seconds);
    f.fem_steps.push_back(static_cast<double>(plan.fem_steps));
    f.solver_work.push_back(plan.solver_work);
    f.cpu_seconds.push_back(plan.cpu_seconds);
    f.simulations.push_back(plan.simulations);
    rows.addRow({scene.name,
                 target.name,
                 1e3 * target.position.x(),
                 1e3 * target.position.y(),
                 std::string(placed ? "placed" : "missed"),
                 1e3 * (unplanned_seed - target.position).norm(),
                 1e3 * plan.predicted_error_m,
                 1e3 * plan.verified_error_m,
                 1e3 * measured,
                 1e3 * live_gap,
                 1e3 * pvm,
                 std::isfinite(legacy_gap) ? ng::report::Cell(1e3 * legacy_gap)
                                           : ng::report::Cell{std::string()},
                 1e3 * plan.release.x(),
                 1e3 * plan.release.y(),
                 double(plan.simulations),
                 plan.seconds,
                 plan.cpu_seconds,
                 double(plan.fem_steps),
                 plan.solver_work,
                 ng::report::Cell{std::string()},
                 std::string(plan.message)});
    std::cout << scene.name << "/" << target.name << ": " << (placed ? "placed" : "MISSED")
              << " measured " << 1e3 * measured << " mm (predicted " << 1e3 * plan.predicted_error_m
              << ", verified " << 1e3 * plan.verified_error_m << ", O(1)-interpolated gap "
              << 1e3 * legacy_gap << " mm), " << plan.simulations << " simulations, "
              << plan.seconds << " s, " << plan.fem_steps << " FEM steps\n"
              << std::flush;
  }
  return f;
}

/// The shipped scene's figures: unplanned, depth-only and planned errors per target,
/// robust against nominal plans on patients with other stiffnesses (another seed).
struct ShippedFigures {
  std::vector<double> unplanned_cm, depth_cm, planned_cm, measured_cm, seconds, simulations;
  std::vector<double> nominal_patient_cm, robust_patient_cm, robust_seconds;
  std::vector<Point2> releases;
  ng::rigid_planning::StiffnessUncertainty uncertainty;  // +-30 %, seed 1
  int patients = 0;
};

ShippedFigures shippedScene(const ng::scene::Scene& scene,
                            const ng::rigid_planning::RigidPlanner& planner, std::size_t count,
                            bool quick, const std::string& out_dir, ng::report::Table& table) {
  ShippedFigures f;
  ng::rigid_planning::StiffnessUncertainty patients = f.uncertainty;
  patients.samples = f.patients = quick ? 4 : 8;
  patients.seed = 2026;
  patients.corners_first = false;  // true patients: uniform over the box
  const auto patient_factors = ng::rigid_planning::drawStiffnessFactors(scene, patients);
  ng::report::Table seed_map({"kind", "x_mm", "y_mm"}, 6);  // figure 4.7
  ng::report::Table robust_table({"target", "patient", "nominal_error_mm", "robust_error_mm"}, 6);
  const auto options = ng::tissue::optionsFromScene(scene);
  for (std::size_t i = 0; i < count; ++i) {
    const auto& target = scene.targets[i];
    const auto unplanned = planner.unplanned(target.position);
    const auto depth_only = planner.planDepthOnly(target.position);
    const auto plan = planner.plan(target.position);
    const auto robust = planner.planRobust(target.position, f.uncertainty);
    if (!unplanned || !depth_only || !plan || !robust) {
      throw std::runtime_error(target.name + ": " + plan.toString() + " / " + robust.toString());
    }
    const Point2 seed =
        simulateImplant(scene, options, plan.release, target.position, planner.schedule());
    const double measured = (seed - target.position).norm();
    seed_map.addRow({std::string("target"), 1e3 * target.position.x(), 1e3 * target.position.y()});
    seed_map.addRow({std::string("unplanned seed"), 1e3 * unplanned.predicted_implant.x(),
                     1e3 * unplanned.predicted_implant.y()});
    seed_map.addRow({std::string("planned seed"), 1e3 * seed.x(), 1e3 * seed.y()});
    f.robust_seconds.push_back(robust.seconds);
    for (std::size_t k = 0; k < patient_factors.size(); ++k) {
      const ng::scene::Scene patient =
          ng::rigid_planning::withStiffnessFactors(scene, patient_factors[k]);
      const auto options_k = ng::tissue::optionsFromScene(patient);
      auto error = [&](const Point2& release) {
        return (simulateImplant(patient, options_k, release, target.position, planner.schedule()) -
                target.position)
            .norm();
      };
      const double e_nominal = error(plan.release), e_robust = error(robust.release);
      f.nominal_patient_cm.push_back(1e2 * e_nominal);
      f.robust_patient_cm.push_back(1e2 * e_robust);
      robust_table.addRow({target.name, double(k), 1e3 * e_nominal, 1e3 * e_robust});
    }
    f.unplanned_cm.push_back(1e2 * unplanned.predicted_error_m);
    f.depth_cm.push_back(1e2 * depth_only.predicted_error_m);
    f.planned_cm.push_back(1e2 * plan.predicted_error_m);
    f.measured_cm.push_back(1e2 * measured);
    f.seconds.push_back(plan.seconds);
    f.simulations.push_back(plan.simulations);
    f.releases.push_back(plan.release);
    table.addRow({target.name, 1e3 * target.position.x(), 1e3 * target.position.y(),
                  1e3 * unplanned.predicted_error_m, 1e3 * depth_only.predicted_error_m,
                  1e3 * plan.predicted_error_m, 1e3 * measured, 1e3 * plan.release.x(),
                  1e3 * plan.release.y(), double(plan.simulations), plan.seconds,
                  std::string(plan.unimodal ? "yes" : "no")});
    std::cout << target.name << ": unplanned " << 1e3 * unplanned.predicted_error_m
              << " mm, planned " << 1e3 * plan.predicted_error_m << " mm (measured "
              << 1e3 * measured << " mm), " << plan.seconds << " s; robust " << robust.seconds
              << " s, patients nominal/robust p95 so far "
              << 10.0 * quantile(f.nominal_patient_cm, 0.95) << "/"
              << 10.0 * quantile(f.robust_patient_cm, 0.95) << " mm\n"
              << std::flush;
  }
  robust_table.writeCsv(out_dir + "/robust.csv");
  seed_map.writeCsv(out_dir + "/seed_map.csv");
  return f;
}

/// Plans with a model of another mesh size or depth step and measures the plans on the scene's
/// own model (the procedure's): speed against error.
void speedSweep(const ng::scene::Scene& scene, const ng::rigid_planning::RigidPlanner& planner,
                bool quick, const std::string& out_dir) {
  ng::report::Table sweep({"mesh_scale", "nodes", "dz_mm", "seconds_per_plan", "predicted_error_mm",
                           "measured_error_mm", "model"},
                          6);
  const std::vector<double> mesh_scales =
      quick ? std::vector<double>{1.0, 2.0} : std::vector<double>{0.75, 1.0, 1.5, 2.0};
  const std::vector<double> steps_mm =
      quick ? std::vector<double>{0.1, 0.2} : std::vector<double>{0.05, 0.1, 0.2, 0.5};
  const std::vector<std::size_t> sweep_targets =
      quick ? std::vector<std::size_t>{0} : std::vector<std::size_t>{0, 5, 10};
  for (double scale : mesh_scales) {
    ng::tissue::TissueSimOptions sim_options = ng::tissue::optionsFromScene(scene);
    sim_options.meshing.max_edge_m *= scale;
    sim_options.meshing.min_edge_m *= scale;
    const std::size_t nodes = ng::tissue::TissueSimulation(scene, sim_options).mesh().nodeCount();
    for (double dz_mm : steps_mm) {
      ng::rigid_planning::PlannerOptions o = planner.options();
      o.depth_step_m = 1e-3 * dz_mm;
      const ng::rigid_planning::RigidPlanner model(scene, sim_options, o);
      std::vector<double> secs, predicted, measured_mm;
      for (std::size_t i : sweep_targets) {
        const Point2 t = scene.targets[std::min(i, scene.targets.size() - 1)].position;
        const auto p = model.plan(t);
        if (!p) {
          throw std::runtime_error("sweep: " + p.toString());
        }
        secs.push_back(p.seconds);
        predicted.push_back(1e3 * p.predicted_error_m);
        measured_mm.push_back(1e3 * (simulateImplant(scene, ng::tissue::optionsFromScene(scene),
                                                     p.release, t, planner.schedule()) -
                                     t)
                                        .norm());
      }
      const std::string label =
          "mesh x" + std::to_string(scale).substr(0, 4) + " (" + std::to_string(nodes) + " nodes)";
      sweep.addRow(
          {scale, double(nodes), dz_mm, mean(secs), mean(predicted), mean(measured_mm), label});
      std::cout << "sweep: " << label << ", dz " << dz_mm << " mm: " << mean(secs)
                << " s per plan, measured " << mean(measured_mm) << " mm\n"
                << std::flush;
    }
  }
  sweep.writeCsv(out_dir + "/speed_vs_error.csv");
}

/// Convergence in the step: the seed of one insert-release-retract (target t06 released at the
/// target) with every command one FEM step (depth grid off), for steps from 0.8 mm down to
/// 0.025 mm, with events located and with events at the end of the step crossing them. Returns
/// the JSON members: the located model's largest change from the finest step, and the
/// step-end model's observed order (log2 of the change ratio between successive halvings;
/// null when the changes are at rounding level and cannot show an order).
std::string convergenceStudy(const ng::scene::Scene& scene, bool quick,
                             const std::string& out_dir) {
  const Point2 t = scene.targets[std::min<std::size_t>(5, scene.targets.size() - 1)].position;
  std::vector<double> steps_mm{0.8, 0.4, 0.2, 0.1, 0.05};
  if (!quick) {
    steps_mm.push_back(0.025);
  }
  ng::report::Table table({"model", "step_mm", "seed_x_mm", "seed_y_mm", "change_vs_finest_mm"}, 9);
  std::ostringstream json;
  json.precision(6);
  for (const bool located : {true, false}) {
    ng::tissue::TissueSimOptions options = ng::tissue::optionsFromScene(scene);
    options.depth_grid.step_m = 0.0;
    options.locate_events = located;
    if (!located) {  // events at the step end: the node-moving model, which can place them so
      options.needle_model = ng::tissue::NeedleModel::kNodeMoving;
    }
    std::vector<Point2> seeds;
    for (double step_mm : steps_mm) {
      ng::rigid_planning::ImplantSchedule schedule;
      schedule.sample_m = 1e-3 * step_mm;
      schedule.dt_s = schedule.sample_m / scene.needle.insertion_velocity_m_s;
      seeds.push_back(simulateImplant(scene, options, t, t, schedule));
    }
    std::vector<double> change;
    for (std::size_t i = 0; i < seeds.size(); ++i) {
      change.push_back(1e3 * (seeds[i] - seeds.back()).norm());
      table.addRow({std::string(located ? "events located" : "events at step end"), steps_mm[i],
                    1e3 * seeds[i].x(), 1e3 * seeds[i].y(), change.back()});
    }
    if (located) {
      json << ",\n  \"convergence_located_change_mm_max\": " << maxOf(change);
      continue;
    }
    // Observed order from the successive differences |s(h) - s(h/2)| (no reference needed).
    std::vector<double> orders;
    for (std::size_t i = 0; i + 2 < seeds.size(); ++i) {
      const double d1 = (seeds[i] - seeds[i + 1]).norm(), d2 = (seeds[i + 1] - seeds[i + 2]).norm();
      if (d1 > 1e-9 && d2 > 1e-9) {
        orders.push_back(std::log2(d1 / d2));
      }
    }
    json << ",\n  \"convergence_step_end_change_mm_max\": " << maxOf(change)
         << ",\n  \"convergence_step_end_observed_order\": ";
    if (orders.empty()) {
      json << "null";
    } else {
      json << ng::report::quantile(orders, 0.5);
    }
  }
  table.writeCsv(out_dir + "/convergence.csv");
  std::cout << table.toText();
  return json.str();
}

/// Figures 4.5 and 4.6 for one target: error vs depth at its height, best depth and error vs
/// height over y_t +- 3 mm.
void depthAndHeightCurves(const ng::scene::Scene& scene,
                          const ng::rigid_planning::RigidPlanner& planner,
                          const std::string& out_dir) {
  const Point2 t = scene.targets[std::min<std::size_t>(5, scene.targets.size() - 1)].position;
  ng::report::Table by_depth({"depth_mm", "error_mm"}, 6);
  const auto at_height = planner.scanHeight(t, t.y());
  for (std::size_t i = 0; i < at_height.depth_m.size(); ++i) {
    by_depth.addRow({1e3 * at_height.depth_m[i], 1e3 * (at_height.implant[i] - t).norm()});
  }
  by_depth.writeCsv(out_dir + "/error_vs_depth.csv");
  ng::report::Table by_height({"height_mm", "best_depth_mm", "error_mm"}, 6);
  for (int k = -6; k <= 6; ++k) {
    const double y = t.y() + 0.5e-3 * k;
    const auto s = planner.scanHeight(t, y);
    by_height.addRow({1e3 * y, 1e3 * s.best_depth_m, 1e3 * s.best_error_m});
  }
  by_height.writeCsv(out_dir + "/error_vs_height.csv");
}

/// Placed over reachable targets (those not refused for physics); "null" when none is reachable.
std::string placedFraction(const SceneFigures& f) {
  const int reachable = f.targets - f.unreachable;
  return reachable > 0
             ? std::to_string(static_cast<double>(f.planned - f.over_tolerance) / reachable)
             : std::string("null");
}

/// Per-scene and overall figures of the multi-scene evaluation, as JSON members.
std::string scenesJson(const std::vector<SceneFigures>& figures) {
  std::ostringstream json;
  json.precision(6);
  SceneFigures all;
  json << ",\n  \"scenes\": [";
  for (std::size_t k = 0; k < figures.size(); ++k) {
    const SceneFigures& f = figures[k];
    json << (k ? "," : "") << "\n    {\"scene\": \"" << f.name << "\", \"spec\": \"" << f.spec
         << "\", \"targets\": " << f.targets << ", \"placed\": " << f.planned - f.over_tolerance
         << ", \"refused\": " << f.refused << ", \"targets_over_tolerance\": " << f.over_tolerance
         << ", \"planned_error_cm_max\": " << maxOf(f.measured_cm)
         << ", \"planned_error_cm_mean\": " << mean(f.measured_cm)
         << ", \"predicted_error_cm_max\": " << maxOf(f.predicted_cm)
         << ", \"verified_error_cm_max\": " << maxOf(f.verified_cm)
         << ", \"predicted_vs_measured_cm_max\": " << maxOf(f.pvm_cm)
         << ", \"o1_interpolated_vs_measured_cm_max\": " << maxOf(f.legacy_gap_cm)
         << ", \"live_schedule_vs_measured_cm_max\": " << maxOf(f.live_cm)
         << ", \"reachable_placed_fraction\": " << placedFraction(f)
         << ", \"step_halving_change_mm_max\": " << maxOf(f.halving_mm)
         << ", \"unplanned_error_cm_mean\": " << mean(f.unplanned_cm)
         << ", \"seconds_per_target_mean\": " << mean(f.seconds)
         << ", \"seconds_per_target_max\": " << maxOf(f.seconds)
         << ", \"simulations_per_plan_mean\": " << mean(f.simulations)
         << ", \"cpu_seconds_per_target_mean\": " << mean(f.cpu_seconds)
         << ", \"cpu_seconds_per_target_max\": " << maxOf(f.cpu_seconds)
         << ", \"fem_steps_per_plan_mean\": " << mean(f.fem_steps)
         << ", \"fem_steps_per_plan_max\": " << maxOf(f.fem_steps)
         << ", \"solver_work_per_plan_mean\": " << mean(f.solver_work)
         << ", \"solver_work_per_plan_max\": " << maxOf(f.solver_work)
         << ", \"refused_window_study_best_error_mm_min\": "
         << (f.window_best_mm.empty() ? std::string("null")
                                      : ng::report::jsonNumber(*std::min_element(
                                            f.window_best_mm.begin(), f.window_best_mm.end())))
         << "}";
    all.planned += f.planned;
    all.targets += f.targets;
    all.refused += f.refused;
    all.over_tolerance += f.over_tolerance;
    all.unreachable += f.unreachable;
    all.halving_mm.insert(all.halving_mm.end(), f.halving_mm.begin(), f.halving_mm.end());
    all.window_best_mm.insert(all.window_best_mm.end(), f.window_best_mm.begin(),
                              f.window_best_mm.end());
    for (std::vector<double> SceneFigures::*v :
         {&SceneFigures::predicted_cm, &SceneFigures::verified_cm, &SceneFigures::measured_cm,
          &SceneFigures::unplanned_cm, &SceneFigures::legacy_gap_cm, &SceneFigures::pvm_cm,
          &SceneFigures::seconds, &SceneFigures::simulations, &SceneFigures::live_cm,
          &SceneFigures::fem_steps, &SceneFigures::cpu_seconds, &SceneFigures::solver_work}) {
      (all.*v).insert((all.*v).end(), (f.*v).begin(), (f.*v).end());
    }
  }
  json << "\n  ],\n  \"all_scenes_targets\": " << all.targets
       << ",\n  \"targets_placed\": " << all.planned - all.over_tolerance
       << ",\n  \"targets_refused\": " << all.refused
       << ",\n  \"targets_over_tolerance\": " << all.over_tolerance
       << ",\n  \"planned_error_cm_max\": " << maxOf(all.measured_cm)
       << ",\n  \"predicted_error_cm_max\": " << maxOf(all.predicted_cm)
       << ",\n  \"verified_error_cm_max\": " << maxOf(all.verified_cm)
       << ",\n  \"predicted_vs_measured_cm_max\": " << maxOf(all.pvm_cm)
       << ",\n  \"o1_interpolated_vs_measured_cm_max\": " << maxOf(all.legacy_gap_cm)
       << ",\n  \"live_schedule_vs_measured_cm_max\": " << maxOf(all.live_cm)
       << ",\n  \"targets_unreachable\": " << all.unreachable
       << ",\n  \"reachable_placed_fraction\": " << placedFraction(all)
       << ",\n  \"live_vs_plan_mm_max\": " << 10.0 * maxOf(all.live_cm)
       << ",\n  \"step_halving_change_mm_max\": " << maxOf(all.halving_mm)
       << ",\n  \"cpu_seconds_per_target_mean\": " << mean(all.cpu_seconds)
       << ",\n  \"unplanned_measured_error_cm_mean\": " << mean(all.unplanned_cm)
       << ",\n  \"seconds_per_target_max\": " << maxOf(all.seconds)
       << ",\n  \"seconds_per_target_mean_all_scenes\": " << mean(all.seconds)
       << ",\n  \"simulations_per_plan_mean\": " << mean(all.simulations)
       << ",\n  \"cpu_seconds_per_target_max\": " << maxOf(all.cpu_seconds)
       << ",\n  \"cpu_seconds_per_target_mean_all_scenes\": " << mean(all.cpu_seconds)
       << ",\n  \"fem_steps_per_plan_mean\": " << mean(all.fem_steps)
       << ",\n  \"fem_steps_per_plan_max\": " << maxOf(all.fem_steps)
       << ",\n  \"solver_work_per_plan_mean\": " << mean(all.solver_work)
       << ",\n  \"solver_work_per_plan_max\": " << maxOf(all.solver_work)
       << ",\n  \"refused_window_study_best_error_mm_min\": "
       << (all.window_best_mm.empty() ? std::string("null")
                                      : ng::report::jsonNumber(*std::min_element(
                                            all.window_best_mm.begin(), all.window_best_mm.end())))
       << ",\n  \"work_budget\": " << ng::rigid_planning::PlannerOptions{}.work_budget;
  return json.str();
}

constexpr const char* kPlots =
    R"json([{"csv": "speed_vs_error.csv", "x": "seconds_per_plan", "y": "measured_error_mm", "group": "model",
  "annotate": "dz_mm", "logx": true, "logy": true, "points": true,
  "title": "Plan time vs seed error: mesh size (colour), dz in mm (label)",
  "png": "speed_vs_error.png"},
 {"csv": "targets.csv", "x": "plan_s", "y": "measured_error_mm", "group": "scene", "points": true, "filter": {"status": "placed"},
  "logy": true, "title": "Measured seed error vs planning time, every scene", "png": "scenes_error_vs_time.png"},
 {"csv": "rigid.csv", "x": "plan_s", "y": "planned_error_mm", "annotate": "target",
  "title": "Planned error vs planning time per target", "logy": true, "png": "planned_error_vs_time.png"},
 {"csv": "robust.csv", "x": "nominal_error_mm", "y": "robust_error_mm", "annotate": "target",
  "title": "Seed error on patients with +-30 % stiffness: nominal vs robust plan", "points": true,
  "png": "robust_vs_nominal.png"},
 {"csv": "error_vs_depth.csv", "x": "depth_mm", "y": "error_mm", "logy": true,
  "title": "Placement error vs release depth at the target height (fig. 4.5)", "png": "error_vs_depth.png"},
 {"csv": "error_vs_height.csv", "x": "height_mm", "y": "error_mm", "logy": true,
  "title": "Best-depth error vs insertion height (fig. 4.6)", "png": "error_vs_height.png"},
 {"csv": "convergence.csv", "x": "step_mm", "y": "change_vs_finest_mm", "group": "model",
  "logx": true, "points": true, "title": "Seed change vs step size (finest step 0.025 mm)",
  "png": "convergence.png"},
 {"csv": "seed_map.csv", "x": "x_mm", "y": "y_mm", "group": "kind", "points": true,
  "title": "Targets and final seeds, unplanned vs planned (fig. 4.7)", "png": "seed_map.png"}])json";

}  // namespace

int main(int argc, char** argv) {
  const std::optional<ng::report::BenchArgs> args =
      ng::report::parseBenchArgs(argc, argv, "bench_rigid");
  if (!args) {
    return 2;
  }
  try {
    const std::vector<std::string> specs =
        args->scenes.empty() ? std::vector<std::string>{args->scene} : args->scenes;
    ng::report::Table per_target({"scene",
                                  "target",
                                  "target_x_mm",
                                  "target_y_mm",
                                  "status",
                                  "unplanned_error_mm",
                                  "predicted_error_mm",
                                  "verified_error_mm",
                                  "measured_error_mm",
                                  "live_schedule_vs_measured_mm",
                                  "predicted_vs_measured_mm",
                                  "o1_interpolated_vs_measured_mm",
                                  "release_x_mm",
                                  "release_y_mm",
                                  "simulations",
                                  "plan_s",
                                  "plan_cpu_s",
                                  "fem_steps",
                                  "solver_work",
                                  "window_study_best_error_mm",
                                  "message"},
                                 6);
    std::vector<SceneFigures> figures;
    for (const std::string& spec : specs) {
      figures.push_back(evaluateScene(spec, args->quick, per_target));
    }
    per_target.writeCsv(args->out_dir + "/targets.csv");
    const ng::scene::Scene scene = ng::scene::loadSceneSpec(specs.front());
    ng::rigid_planning::PlannerOptions options;  // the robust and sweep figures need every plan
    options.refuse_over_tolerance = false;
    const ng::rigid_planning::RigidPlanner planner(scene, options);
    const std::size_t count =
        args->quick ? std::min<std::size_t>(3, scene.targets.size()) : scene.targets.size();
    ng::report::Table table({"target", "target_x_mm", "target_y_mm", "unplanned_error_mm",
                             "depth_only_error_mm", "planned_error_mm", "planned_measured_error_mm",
                             "release_x_mm", "release_y_mm", "simulations", "plan_s", "unimodal"},
                            6);
    const ShippedFigures f = shippedScene(scene, planner, count, args->quick, args->out_dir, table);
    // The batch the procedure may plan: every target, on every core, as planned one at a time
    // (unless a time budget cut either search short: the budget depends on the machine's load).
    std::vector<Point2> positions;
    for (std::size_t i = 0; i < count; ++i) {
      positions.push_back(scene.targets[i].position);
    }
    const int threads = static_cast<int>(std::max(1U, std::thread::hardware_concurrency()));
    const auto batch_start = std::chrono::steady_clock::now();
    const auto batch = planner.planAll(positions, threads);
    const double batch_seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - batch_start).count();
    int batch_differing = 0;
    for (std::size_t i = 0; i < count; ++i) {
      batch_differing += !batch[i] || (batch[i].release - f.releases[i]).norm() > 1e-12 ? 1 : 0;
    }
    speedSweep(scene, planner, args->quick, args->out_dir);
    depthAndHeightCurves(scene, planner, args->out_dir);
    const std::string convergence = convergenceStudy(scene, args->quick, args->out_dir);
    std::ostringstream json;
    json.precision(6);
    json << "{\n  \"benchmark\": \"rigid\",\n  \"scene\": \"" << scene.name << "\",\n"
         << "  \"quick\": " << (args->quick ? "true" : "false") << ",\n  \"targets\": " << count
         << ",\n  \"unplanned_error_cm_mean\": " << mean(f.unplanned_cm)
         << ",\n  \"unplanned_error_cm_sd\": " << sampleSd(f.unplanned_cm)
         << ",\n  \"depth_only_error_cm_mean\": " << mean(f.depth_cm)
         << ",\n  \"planned_error_cm_mean\": " << mean(f.planned_cm)
         << ",\n  \"planned_error_cm_sd\": " << sampleSd(f.planned_cm)
         << ",\n  \"planned_measured_error_cm_mean\": " << mean(f.measured_cm)
         << ",\n  \"planned_measured_error_cm_max\": " << maxOf(f.measured_cm)
         << ",\n  \"seconds_per_target_mean\": " << batch_seconds / count
         << ",\n  \"seconds_per_target_note\": \"wall time of planning all targets on " << threads
         << " threads, divided by the targets\""
         << ",\n  \"plan_latency_seconds_mean\": " << mean(f.seconds)
         << ",\n  \"plan_latency_seconds_max\": " << maxOf(f.seconds)
         << ",\n  \"simulations_per_target_mean\": " << mean(f.simulations)
         << ",\n  \"stiffness_uncertainty\": " << f.uncertainty.relative
         << ",\n  \"patients_per_target\": " << f.patients
         << ",\n  \"nominal_p95_error_cm\": " << quantile(f.nominal_patient_cm, 0.95)
         << ",\n  \"robust_p95_error_cm\": " << quantile(f.robust_patient_cm, 0.95)
         << ",\n  \"nominal_mean_error_cm_patients\": " << mean(f.nominal_patient_cm)
         << ",\n  \"robust_mean_error_cm_patients\": " << mean(f.robust_patient_cm)
         << ",\n  \"robust_seconds_per_target_mean\": " << mean(f.robust_seconds)
         << ",\n  \"batch_plans_differing_from_sequential\": " << batch_differing << convergence
         << scenesJson(figures) << calibrationJson() << "\n}\n";
    table.writeCsv(args->out_dir + "/rigid.csv");
    ng::report::writeTextFile(args->out_dir + "/summary.json", json.str());
    ng::report::writeTextFile(args->out_dir + "/plot.json", kPlots);
    std::cout << table.toText() << json.str();
  } catch (const std::exception& e) {
    std::cerr << "bench_rigid: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
