// Benchmark of rigid-needle offset planning (issue 4, dissertation 4.4): 12 targets in the
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
#include <numeric>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

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
  ng::tissue::TissueSimOptions o = options;
  o.meshing.refine_points.push_back(target);
  o.meshing.refine_lines.push_back({Point2(scene.workspace_min.x(), target.y()), target});
  ng::tissue::TissueSimulation sim(scene, o);
  return ng::rigid_planning::simulateImplant(sim, release, schedule);
}

/// Per-scene figures of the multi-scene part of the bench.
struct SceneFigures {
  std::string name, spec;
  int targets = 0, planned = 0, refused = 0, over_tolerance = 0;
  std::vector<double> predicted_cm, verified_cm, measured_cm, unplanned_cm, legacy_gap_cm, pvm_cm,
      live_cm, seconds, simulations;
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
      const ng::report::Cell none{std::string()};  // never inserted: no error figures
      rows.addRow({scene.name, target.name, 1e3 * target.position.x(), 1e3 * target.position.y(),
                   std::string("refused"), none, none, none, none, none, none, none, none, none,
                   none, plan.seconds, std::string(plan.message)});
      std::cout << scene.name << "/" << target.name << ": refused: " << plan.message << "\n"
                << std::flush;
      continue;
    }
    previous_offset = plan.release.y() - target.position.y();  // warm start for the next target
    ++f.planned;
    const auto sim_options = ng::tissue::optionsFromScene(scene);
    const Point2 seed = simulateImplant(scene, sim_options, plan.release, target.position,
                                        planner.schedule(target.position));
    const Point2 unplanned_seed = simulateImplant(
        scene, sim_options, target.position, target.position, planner.schedule(target.position));
    const double measured = (seed - target.position).norm();
    // The live loop steps the tissue on its own clock (tissue_sim at 200 Hz: 0.05 mm steps at
    // 1 cm/s, from the robot's retract depth of -5 mm): the same release on that schedule shows
    // how much the outcome depends on the step history the plan cannot know.
    ng::rigid_planning::ImplantSchedule live = planner.schedule(target.position);
    live.approach_step_m = 0.0;
    live.step_m = 5e-5;
    live.start_x_m = scene.workspace_min.x() - 0.005;
    const double live_error =
        (simulateImplant(scene, sim_options, plan.release, target.position, live) - target.position)
            .norm();
    f.live_cm.push_back(1e2 * live_error);
    const auto legacy_scan = legacy.scanHeight(target.position, plan.release.y());
    const double legacy_gap = (legacy_scan.implantAt(plan.release.x()) - seed).norm();
    const double pvm = (plan.predicted_implant - seed).norm();
    const bool placed = measured <= plan.tolerance_m;
    f.over_tolerance += placed ? 0 : 1;
    f.predicted_cm.push_back(1e2 * plan.predicted_error_m);
    f.verified_cm.push_back(1e2 * plan.verified_error_m);
    f.measured_cm.push_back(1e2 * measured);
    f.unplanned_cm.push_back(1e2 * (unplanned_seed - target.position).norm());
    f.legacy_gap_cm.push_back(1e2 * legacy_gap);
    f.pvm_cm.push_back(1e2 * pvm);
    f.seconds.push_back(plan.seconds);
    f.simulations.push_back(plan.simulations);
    rows.addRow({scene.name, target.name, 1e3 * target.position.x(), 1e3 * target.position.y(),
                 std::string(placed ? "placed" : "missed"),
                 1e3 * (unplanned_seed - target.position).norm(), 1e3 * plan.predicted_error_m,
                 1e3 * plan.verified_error_m, 1e3 * measured, 1e3 * live_error, 1e3 * pvm,
                 1e3 * legacy_gap, 1e3 * plan.release.x(), 1e3 * plan.release.y(),
                 double(plan.simulations), plan.seconds, std::string(plan.message)});
    std::cout << scene.name << "/" << target.name << ": " << (placed ? "placed" : "MISSED")
              << " measured " << 1e3 * measured << " mm (predicted " << 1e3 * plan.predicted_error_m
              << ", verified " << 1e3 * plan.verified_error_m << ", O(1)-interpolated gap "
              << 1e3 * legacy_gap << " mm), " << plan.simulations << " simulations, "
              << plan.seconds << " s\n"
              << std::flush;
  }
  return f;
}

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
    ng::report::Table per_target(
        {"scene", "target", "target_x_mm", "target_y_mm", "status", "unplanned_error_mm",
         "predicted_error_mm", "verified_error_mm", "measured_error_mm", "live_schedule_error_mm",
         "predicted_vs_measured_mm", "o1_interpolated_vs_measured_mm", "release_x_mm",
         "release_y_mm", "simulations", "plan_s", "message"},
        6);
    std::vector<SceneFigures> figures;
    for (const std::string& spec : specs) {
      figures.push_back(evaluateScene(spec, args->quick, per_target));
    }
    per_target.writeCsv(args->out_dir + "/targets.csv");
    const ng::scene::Scene scene = ng::scene::loadSceneSpec(specs.front());
    ng::rigid_planning::PlannerOptions options;  // dissertation 4.4: +-0.2 cm, 0.01 cm, 0.5 cm/s
    const ng::rigid_planning::RigidPlanner planner(scene, options);
    const std::size_t count =
        args->quick ? std::min<std::size_t>(3, scene.targets.size()) : scene.targets.size();
    ng::report::Table table({"target", "target_x_mm", "target_y_mm", "unplanned_error_mm",
                             "depth_only_error_mm", "planned_error_mm", "planned_measured_error_mm",
                             "release_x_mm", "release_y_mm", "simulations", "plan_s", "unimodal"},
                            6);
    std::vector<double> unplanned_cm, depth_cm, planned_cm, measured_cm, seconds, simulations;
    std::vector<Point2> releases;
    // Robustness: plans made on the nominal model or robustly over +-30 % stiffness, executed on
    // "true patients" whose stiffness differs from the model (another seed).
    ng::rigid_planning::StiffnessUncertainty uncertainty;  // +-30 %, 5 samples, seed 1
    ng::rigid_planning::StiffnessUncertainty patients = uncertainty;
    patients.samples = args->quick ? 4 : 8;
    patients.seed = 2026;
    patients.corners_first = false;  // true patients: uniform over the box
    const auto patient_factors = ng::rigid_planning::drawStiffnessFactors(scene, patients);
    std::vector<double> nominal_patient_cm, robust_patient_cm, robust_seconds;
    ng::report::Table seed_map({"kind", "x_mm", "y_mm"}, 6);  // figure 4.7
    ng::report::Table robust_table({"target", "patient", "nominal_error_mm", "robust_error_mm"}, 6);
    for (std::size_t i = 0; i < count; ++i) {
      const auto& target = scene.targets[i];
      const auto unplanned = planner.unplanned(target.position);
      const auto depth_only = planner.planDepthOnly(target.position);
      const auto plan = planner.plan(target.position);
      if (!unplanned || !depth_only || !plan) {
        throw std::runtime_error(target.name + ": " + plan.toString());
      }
      const Point2 seed = simulateImplant(scene, ng::tissue::optionsFromScene(scene), plan.release,
                                          target.position, planner.schedule(target.position));
      const double measured = (seed - target.position).norm();
      seed_map.addRow(
          {std::string("target"), 1e3 * target.position.x(), 1e3 * target.position.y()});
      seed_map.addRow({std::string("unplanned seed"), 1e3 * unplanned.predicted_implant.x(),
                       1e3 * unplanned.predicted_implant.y()});
      seed_map.addRow({std::string("planned seed"), 1e3 * seed.x(), 1e3 * seed.y()});
      const auto robust = planner.planRobust(target.position, uncertainty);
      if (!robust) {
        throw std::runtime_error(target.name + " robust: " + robust.toString());
      }
      robust_seconds.push_back(robust.seconds);
      for (std::size_t k = 0; k < patient_factors.size(); ++k) {
        const ng::scene::Scene patient =
            ng::rigid_planning::withStiffnessFactors(scene, patient_factors[k]);
        const auto options_k = ng::tissue::optionsFromScene(patient);
        const double e_nominal = (simulateImplant(patient, options_k, plan.release, target.position,
                                                  planner.schedule(target.position)) -
                                  target.position)
                                     .norm();
        const double e_robust =
            (simulateImplant(patient, options_k, robust.release, target.position,
                             planner.schedule(target.position)) -
             target.position)
                .norm();
        nominal_patient_cm.push_back(1e2 * e_nominal);
        robust_patient_cm.push_back(1e2 * e_robust);
        robust_table.addRow({target.name, double(k), 1e3 * e_nominal, 1e3 * e_robust});
      }
      unplanned_cm.push_back(1e2 * unplanned.predicted_error_m);
      depth_cm.push_back(1e2 * depth_only.predicted_error_m);
      planned_cm.push_back(1e2 * plan.predicted_error_m);
      measured_cm.push_back(1e2 * measured);
      seconds.push_back(plan.seconds);
      simulations.push_back(plan.simulations);
      releases.push_back(plan.release);
      table.addRow({target.name, 1e3 * target.position.x(), 1e3 * target.position.y(),
                    1e3 * unplanned.predicted_error_m, 1e3 * depth_only.predicted_error_m,
                    1e3 * plan.predicted_error_m, 1e3 * measured, 1e3 * plan.release.x(),
                    1e3 * plan.release.y(), double(plan.simulations), plan.seconds,
                    std::string(plan.unimodal ? "yes" : "no")});
      std::cout << target.name << ": unplanned " << 1e3 * unplanned.predicted_error_m
                << " mm, depth-only " << 1e3 * depth_only.predicted_error_m << " mm, planned "
                << 1e3 * plan.predicted_error_m << " mm (measured " << 1e3 * measured << " mm), "
                << plan.simulations << " simulations, " << plan.seconds << " s; robust plan "
                << robust.seconds << " s, patients nominal/robust p95 so far "
                << 10.0 * quantile(nominal_patient_cm, 0.95) << "/"
                << 10.0 * quantile(robust_patient_cm, 0.95) << " mm\n"
                << std::flush;
    }
    // The batch the procedure plans: every target, on every core.
    std::vector<Point2> positions;
    for (std::size_t i = 0; i < count; ++i) {
      positions.push_back(scene.targets[i].position);
    }
    const int threads = static_cast<int>(std::max(1U, std::thread::hardware_concurrency()));
    const auto batch_start = std::chrono::steady_clock::now();
    const auto batch = planner.planAll(positions, threads);
    int batch_differing = 0;
    const double batch_seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - batch_start).count();
    for (std::size_t i = 0; i < count; ++i) {
      if (!batch[i]) {
        throw std::runtime_error(scene.targets[i].name +
                                 ": the batch plan failed: " + batch[i].message);
      }
      // As planned one at a time above, unless a time budget cut either search short (the
      // budget makes a plan depend on the machine's load).
      batch_differing += (batch[i].release - releases[i]).norm() > 1e-12 ? 1 : 0;
    }

    // Speed against error over mesh size and time step: plan with a coarser or finer model, then
    // implant in the patient simulated as the procedure does (scene mesh, dz = 0.1 mm).
    ng::report::Table sweep({"mesh_scale", "nodes", "dz_mm", "seconds_per_plan",
                             "predicted_error_mm", "measured_error_mm", "model"},
                            6);
    const std::vector<double> mesh_scales =
        args->quick ? std::vector<double>{1.0, 2.0} : std::vector<double>{0.75, 1.0, 1.5, 2.0};
    const std::vector<double> steps_mm =
        args->quick ? std::vector<double>{0.1, 0.5} : std::vector<double>{0.05, 0.1, 0.2, 0.5};
    const std::vector<std::size_t> sweep_targets =
        args->quick ? std::vector<std::size_t>{0} : std::vector<std::size_t>{0, 5, 10};
    for (double scale : mesh_scales) {
      ng::tissue::TissueSimOptions sim_options = ng::tissue::optionsFromScene(scene);
      sim_options.meshing.max_edge_m *= scale;
      sim_options.meshing.min_edge_m *= scale;
      const std::size_t nodes =
          ng::tissue::TissueSimulation(scene, sim_options).model().mesh().nodeCount();
      for (double dz_mm : steps_mm) {
        ng::rigid_planning::PlannerOptions o = options;
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
                                                       p.release, t, planner.schedule(t)) -
                                       t)
                                          .norm());
        }
        const std::string label = "mesh x" + std::to_string(scale).substr(0, 4) + " (" +
                                  std::to_string(nodes) + " nodes)";
        sweep.addRow(
            {scale, double(nodes), dz_mm, mean(secs), mean(predicted), mean(measured_mm), label});
        std::cout << "sweep: mesh x" << scale << " (" << nodes << " nodes), dz " << dz_mm
                  << " mm: " << mean(secs) << " s per plan, predicted " << mean(predicted)
                  << " mm, measured " << mean(measured_mm) << " mm\n"
                  << std::flush;
      }
    }
    // The approach step (coarser dz until approach_zone_m before the target) on the scene's mesh.
    for (double approach_mm :
         args->quick ? std::vector<double>{0.0} : std::vector<double>{0.0, 0.3, 0.5, 1.0}) {
      ng::rigid_planning::PlannerOptions o = options;
      o.approach_step_m = 1e-3 * approach_mm;
      const ng::rigid_planning::RigidPlanner model(scene, o);
      std::vector<double> secs, predicted, measured_mm;
      for (std::size_t i : sweep_targets) {
        const Point2 t = scene.targets[std::min(i, scene.targets.size() - 1)].position;
        const auto p = model.plan(t);
        if (!p)
          throw std::runtime_error("sweep: " + p.toString());
        secs.push_back(p.seconds);
        predicted.push_back(1e3 * p.predicted_error_m);
        measured_mm.push_back(1e3 * (simulateImplant(scene, ng::tissue::optionsFromScene(scene),
                                                     p.release, t, planner.schedule(t)) -
                                     t)
                                        .norm());
      }
      const std::string label =
          approach_mm > 0.0 ? "approach dz " + std::to_string(approach_mm).substr(0, 3) + " mm"
                            : "uniform dz";
      sweep.addRow({1.0,
                    double(ng::tissue::TissueSimulation(scene, ng::tissue::optionsFromScene(scene))
                               .model()
                               .mesh()
                               .nodeCount()),
                    1e3 * options.depth_step_m, mean(secs), mean(predicted), mean(measured_mm),
                    label});
      std::cout << "sweep: " << label << ": " << mean(secs) << " s per plan, measured "
                << mean(measured_mm) << " mm\n"
                << std::flush;
    }
    sweep.writeCsv(args->out_dir + "/speed_vs_error.csv");

    std::ostringstream json;
    json.precision(6);
    json << "{\n  \"benchmark\": \"rigid\",\n  \"scene\": \"" << scene.name << "\",\n"
         << "  \"quick\": " << (args->quick ? "true" : "false") << ",\n  \"targets\": " << count
         << ",\n"
         << "  \"unplanned_error_cm_mean\": " << mean(unplanned_cm) << ",\n"
         << "  \"unplanned_error_cm_sd\": " << sampleSd(unplanned_cm) << ",\n"
         << "  \"depth_only_error_cm_mean\": " << mean(depth_cm) << ",\n"
         << "  \"planned_error_cm_mean\": " << mean(planned_cm) << ",\n"
         << "  \"planned_error_cm_sd\": " << sampleSd(planned_cm) << ",\n"
         << "  \"planned_measured_error_cm_mean\": " << mean(measured_cm) << ",\n"
         << "  \"planned_measured_error_cm_max\": "
         << *std::max_element(measured_cm.begin(), measured_cm.end())
         << ",\n  \"seconds_per_target_mean\": " << batch_seconds / count
         << ",\n  \"seconds_per_target_note\": \"wall time of planning all targets on " << threads
         << " threads, divided by the targets\""
         << ",\n  \"plan_latency_seconds_mean\": " << mean(seconds)
         << ",\n  \"plan_latency_seconds_max\": "
         << *std::max_element(seconds.begin(), seconds.end())
         << ",\n  \"simulations_per_target_mean\": " << mean(simulations)
         << ",\n  \"stiffness_uncertainty\": " << uncertainty.relative
         << ",\n  \"patients_per_target\": " << patients.samples
         << ",\n  \"nominal_p95_error_cm\": " << quantile(nominal_patient_cm, 0.95)
         << ",\n  \"robust_p95_error_cm\": " << quantile(robust_patient_cm, 0.95)
         << ",\n  \"nominal_mean_error_cm_patients\": " << mean(nominal_patient_cm)
         << ",\n  \"robust_mean_error_cm_patients\": " << mean(robust_patient_cm)
         << ",\n  \"robust_seconds_per_target_mean\": " << mean(robust_seconds)
         << ",\n  \"batch_plans_differing_from_sequential\": " << batch_differing;
    // Every scene: measured (independent full simulation) planned error, the planner's
    // prediction and verification, the unplanned error, planning time and simulations.
    SceneFigures all;
    json << ",\n  \"scenes\": [";
    for (std::size_t k = 0; k < figures.size(); ++k) {
      const SceneFigures& f = figures[k];
      json << (k ? "," : "") << "\n    {\"scene\": \"" << f.name << "\", \"spec\": \"" << f.spec
           << "\", \"targets\": " << f.targets << ", \"refused\": " << f.refused
           << ", \"targets_over_tolerance\": " << f.over_tolerance
           << ", \"planned_error_cm_max\": " << maxOf(f.measured_cm)
           << ", \"planned_error_cm_mean\": " << mean(f.measured_cm)
           << ", \"predicted_error_cm_max\": " << maxOf(f.predicted_cm)
           << ", \"verified_error_cm_max\": " << maxOf(f.verified_cm)
           << ", \"predicted_vs_measured_cm_max\": " << maxOf(f.pvm_cm)
           << ", \"o1_interpolated_vs_measured_cm_max\": " << maxOf(f.legacy_gap_cm)
           << ", \"live_schedule_error_cm_max\": " << maxOf(f.live_cm)
           << ", \"unplanned_error_cm_mean\": " << mean(f.unplanned_cm)
           << ", \"seconds_per_target_mean\": " << mean(f.seconds)
           << ", \"seconds_per_target_max\": " << maxOf(f.seconds)
           << ", \"simulations_per_plan_mean\": " << mean(f.simulations) << "}";
      all.targets += f.targets;
      all.refused += f.refused;
      all.over_tolerance += f.over_tolerance;
      for (std::vector<double> SceneFigures::*v :
           {&SceneFigures::predicted_cm, &SceneFigures::verified_cm, &SceneFigures::measured_cm,
            &SceneFigures::unplanned_cm, &SceneFigures::legacy_gap_cm, &SceneFigures::pvm_cm,
            &SceneFigures::seconds, &SceneFigures::simulations, &SceneFigures::live_cm}) {
        (all.*v).insert((all.*v).end(), (f.*v).begin(), (f.*v).end());
      }
    }
    json << "\n  ],\n  \"all_scenes_targets\": " << all.targets
         << ",\n  \"targets_refused\": " << all.refused
         << ",\n  \"targets_over_tolerance\": " << all.over_tolerance
         << ",\n  \"planned_error_cm_max\": " << maxOf(all.measured_cm)
         << ",\n  \"predicted_error_cm_max\": " << maxOf(all.predicted_cm)
         << ",\n  \"verified_error_cm_max\": " << maxOf(all.verified_cm)
         << ",\n  \"predicted_vs_measured_cm_max\": " << maxOf(all.pvm_cm)
         << ",\n  \"o1_interpolated_vs_measured_cm_max\": " << maxOf(all.legacy_gap_cm)
         << ",\n  \"live_schedule_error_cm_max\": " << maxOf(all.live_cm)
         << ",\n  \"unplanned_measured_error_cm_mean\": " << mean(all.unplanned_cm)
         << ",\n  \"seconds_per_target_max\": " << maxOf(all.seconds)
         << ",\n  \"seconds_per_target_mean_all_scenes\": " << mean(all.seconds)
         << ",\n  \"simulations_per_plan_mean\": " << mean(all.simulations) << "\n}\n";
    robust_table.writeCsv(args->out_dir + "/robust.csv");
    seed_map.writeCsv(args->out_dir + "/seed_map.csv");
    // Figures 4.5 and 4.6 for one target: error vs depth at its height, best depth and error vs
    // height over y_t +- 3 mm.
    const Point2 t = scene.targets[std::min<std::size_t>(5, scene.targets.size() - 1)].position;
    ng::report::Table by_depth({"depth_mm", "error_mm"}, 6);
    const auto at_height = planner.scanHeight(t, t.y());
    for (std::size_t i = 0; i < at_height.depth_m.size(); ++i) {
      by_depth.addRow({1e3 * at_height.depth_m[i], 1e3 * (at_height.implant[i] - t).norm()});
    }
    by_depth.writeCsv(args->out_dir + "/error_vs_depth.csv");
    ng::report::Table by_height({"height_mm", "best_depth_mm", "error_mm"}, 6);
    for (int k = -6; k <= 6; ++k) {
      const double y = t.y() + 0.5e-3 * k;
      const auto s = planner.scanHeight(t, y);
      by_height.addRow({1e3 * y, 1e3 * s.best_depth_m, 1e3 * s.best_error_m});
    }
    by_height.writeCsv(args->out_dir + "/error_vs_height.csv");
    table.writeCsv(args->out_dir + "/rigid.csv");
    ng::report::writeTextFile(args->out_dir + "/summary.json", json.str());
    ng::report::writeTextFile(
        args->out_dir + "/plot.json",
        R"json([{"csv": "speed_vs_error.csv", "x": "seconds_per_plan", "y": "measured_error_mm", "group": "model",
  "annotate": "dz_mm", "logx": true, "logy": true, "points": true,
  "title": "Plan time vs seed error: mesh size (colour), dz in mm (label)",
  "png": "speed_vs_error.png"},
 {"csv": "rigid.csv", "x": "plan_s", "y": "planned_error_mm", "annotate": "target",
  "title": "Planned error vs planning time per target", "logy": true, "png": "planned_error_vs_time.png"},
 {"csv": "robust.csv", "x": "nominal_error_mm", "y": "robust_error_mm", "annotate": "target",
  "title": "Seed error on patients with +-30 % stiffness: nominal vs robust plan", "points": true,
  "png": "robust_vs_nominal.png"},
 {"csv": "error_vs_depth.csv", "x": "depth_mm", "y": "error_mm", "logy": true,
  "title": "Placement error vs release depth at the target height (fig. 4.5)", "png": "error_vs_depth.png"},
 {"csv": "error_vs_height.csv", "x": "height_mm", "y": "error_mm", "logy": true,
  "title": "Best-depth error vs insertion height (fig. 4.6)", "png": "error_vs_height.png"},
 {"csv": "seed_map.csv", "x": "x_mm", "y": "y_mm", "group": "kind", "points": true,
  "title": "Targets and final seeds, unplanned vs planned (fig. 4.7)", "png": "seed_map.png"}])json");
    std::cout << table.toText() << json.str();
  } catch (const std::exception& e) {
    std::cerr << "bench_rigid: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
