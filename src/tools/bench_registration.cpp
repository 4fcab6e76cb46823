// Benchmark of deformable registration with tissue-parameter estimation (dissertation
// 3.3): on 5 balloon-probe and 5 rigid-probe seeded synthetic cases, per case and method --
// ours (fast optimiser), ours with the dissertation's steepest descent + Armijo, rigid
// centre-of-mass translation, intensity-based registration (demons and DIS optical flow on
// rendered images) -- Dice, mean test-point error and time; then the sensitivity to the mesh
// size n and to alpha like figures 3.7-3.8 (speed against error).
// Usage: bench_registration --out DIR [--quick]
#include <chrono>
#include <iostream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/registration/baselines.h"
#include "needle_guidance/registration/deformable_registration.h"
#include "needle_guidance/registration/probe_case.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/statistics.h"
#include "needle_guidance/report/table.h"

namespace ng = needle_guidance;
namespace reg = ng::registration;

namespace {

constexpr double kMmPerM = 1e3;
constexpr int kCasesPerProbe = 5;

double secondsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

struct MethodStats {
  std::vector<double> dice, error_mm, seconds;
  int failures = 0;
};

/// Sensitivity (figures 3.7-3.8): mesh size n with the fast optimiser (its force penalty is
/// fixed, so alpha does not enter it), and alpha with the dissertation's steepest descent,
/// whose objective is Q = S - alpha E, at n = 500.
ng::report::Table sensitivitySweep(const std::vector<reg::ProbeCase>& cases, bool quick) {
  ng::report::Table sensitivity({"optimizer", "target_nodes", "alpha", "mesh_nodes", "dice_mean",
                                 "point_error_mm_mean", "seconds_mean"},
                                6);
  auto sweep = [&](reg::Optimizer optimizer, int nodes, double alpha) {
    std::vector<double> dice, error_mm, seconds, mesh_nodes;
    for (const reg::ProbeCase& c : cases) {
      reg::RegistrationOptions options;
      options.optimizer = optimizer;
      options.target_nodes = nodes;
      options.alpha = alpha;
      const auto t0 = std::chrono::steady_clock::now();
      const reg::RegistrationResult r = reg::registerSlices(c.probe_out, c.probe_in, options);
      seconds.push_back(secondsSince(t0));
      if (reg::hasMapping(r.status) && r.mapping) {
        dice.push_back(r.dice);
        error_mm.push_back(reg::meanPointError(*r.mapping, c) * kMmPerM);
        mesh_nodes.push_back(double(r.mesh.nodeCount()));
      }
    }
    const std::string name = optimizer == reg::Optimizer::kFast ? "fast" : "steepest_descent";
    sensitivity.addRow({name, double(nodes), alpha, ng::report::mean(mesh_nodes),
                        ng::report::mean(dice), ng::report::mean(error_mm),
                        ng::report::mean(seconds)});
    std::cout << "[registration] " << name << " n " << nodes << " alpha " << alpha << ": Dice "
              << ng::report::mean(dice) << ", point error " << ng::report::mean(error_mm) << " mm, "
              << ng::report::mean(seconds) << " s\n";
  };
  const std::vector<int> node_counts =
      quick ? std::vector<int>{100, 500} : std::vector<int>{100, 250, 500, 1000, 2000};
  for (const int nodes : node_counts) {
    sweep(reg::Optimizer::kFast, nodes, reg::RegistrationOptions{}.alpha);
  }
  const std::vector<double> alphas =
      quick ? std::vector<double>{0.0, 0.01} : std::vector<double>{0.0, 0.005, 0.01};
  for (const double alpha : alphas) {
    sweep(reg::Optimizer::kSteepestDescent, 500, alpha);
  }
  return sensitivity;
}

}  // namespace

int main(int argc, char** argv) {
  const auto args = ng::report::parseBenchArgs(argc, argv, "bench_registration");
  if (!args) {
    return 2;
  }
  std::vector<reg::ProbeCase> cases;
  for (const reg::ProbeType type : {reg::ProbeType::kBalloon, reg::ProbeType::kRigid}) {
    for (int seed = 1; seed <= kCasesPerProbe; ++seed) {
      cases.push_back(reg::generateProbeCase(type, std::uint64_t(seed)));
    }
  }

  ng::report::Table per_case(
      {"probe", "seed", "method", "status", "dice", "point_error_mm", "seconds", "iterations",
       "cg_kPa", "pz_kPa", "true_cg_kPa", "true_pz_kPa", "true_surrounding_kPa"},
      6);
  std::map<std::string, MethodStats> stats;
  std::vector<double> unregistered_mm;
  auto record = [&](const reg::ProbeCase& c, const std::string& method, const std::string& status,
                    bool ok, double dice, double error_m, double seconds, int iterations,
                    double cg_Pa, double pz_Pa) {
    per_case.addRow({reg::toString(c.type), double(c.seed), method, status, dice, error_m * kMmPerM,
                     seconds, double(iterations), cg_Pa * 1e-3, pz_Pa * 1e-3,
                     c.truth.cg_modulus_Pa * 1e-3, c.truth.pz_modulus_Pa * 1e-3,
                     c.truth.surrounding_modulus_Pa * 1e-3});
    MethodStats& s = stats[method];
    if (!ok) {
      ++s.failures;
      return;
    }
    s.dice.push_back(dice);
    s.error_mm.push_back(error_m * kMmPerM);
    s.seconds.push_back(seconds);
  };
  for (const reg::ProbeCase& c : cases) {
    unregistered_mm.push_back(
        reg::meanPointError(reg::TranslationMapping(ng::geometry::Point2::Zero()), c) * kMmPerM);
    for (const reg::Optimizer optimizer :
         {reg::Optimizer::kFast, reg::Optimizer::kSteepestDescent}) {
      reg::RegistrationOptions options;
      options.optimizer = optimizer;
      const auto t0 = std::chrono::steady_clock::now();
      const reg::RegistrationResult r = reg::registerSlices(c.probe_out, c.probe_in, options);
      const double seconds = secondsSince(t0);
      const bool ok = reg::hasMapping(r.status) && r.mapping;
      record(c, optimizer == reg::Optimizer::kFast ? "ours_fast" : "ours_steepest_descent",
             reg::toString(r.status), ok, r.dice, ok ? reg::meanPointError(*r.mapping, c) : 0.0,
             seconds, r.iterations, r.modulus_Pa[reg::kCentralGland],
             r.modulus_Pa[reg::kPeripheralZone]);
    }
    {
      const auto t0 = std::chrono::steady_clock::now();
      const reg::BaselineResult b = reg::rigidCentreOfMass(c.probe_out, c.probe_in);
      const double seconds = secondsSince(t0);
      const bool ok = b.mapping != nullptr;
      record(c, "rigid_com", reg::toString(b.status), ok, b.dice,
             ok ? reg::meanPointError(*b.mapping, c) : 0.0, seconds, 0, 0.0, 0.0);
    }
    // Intensity baselines on rendered T2-like images. Default: each image has its own texture
    // (only anatomy boundaries correspond); "_tissue_tracking": one texture that moves with the
    // tissue, an optimistic setting kept for comparison.
    for (const auto texture : {reg::TextureMode::kIndependent, reg::TextureMode::kTissueTracking}) {
      const reg::SyntheticImagePair images =
          reg::renderProbeImages(c, 0.0005, 0.03, c.seed, texture);
      const std::string suffix =
          texture == reg::TextureMode::kIndependent ? "" : "_tissue_tracking";
      for (const reg::IntensityMethod method :
           {reg::IntensityMethod::kDemons, reg::IntensityMethod::kDisOpticalFlow}) {
        const auto t0 = std::chrono::steady_clock::now();
        const reg::BaselineResult b = reg::intensityRegistration(
            images, reg::prostateLoops(c.probe_out), c.probe_in.prostate.outer, method);
        const double seconds = secondsSince(t0);
        const bool ok = b.mapping != nullptr;
        record(c, std::string("intensity_") + reg::toString(method) + suffix,
               reg::toString(b.status), ok, b.dice, ok ? reg::meanPointError(*b.mapping, c) : 0.0,
               seconds, 0, 0.0, 0.0);
      }
    }
  }

  ng::report::Table methods({"method", "cases", "failures", "dice_mean", "dice_sd",
                             "point_error_mm_mean", "point_error_mm_sd", "seconds_mean"},
                            6);
  for (const auto& [name, s] : stats) {
    methods.addRow({name, double(s.dice.size()), double(s.failures), ng::report::mean(s.dice),
                    ng::report::sampleSd(s.dice), ng::report::mean(s.error_mm),
                    ng::report::sampleSd(s.error_mm), ng::report::mean(s.seconds)});
  }

  const ng::report::Table sensitivity = sensitivitySweep(cases, args->quick);

  per_case.writeCsv(args->out_dir + "/cases.csv");
  methods.writeCsv(args->out_dir + "/methods.csv");
  sensitivity.writeCsv(args->out_dir + "/sensitivity.csv");
  std::cout << methods.toText();
  const MethodStats& ours = stats["ours_fast"];
  const MethodStats& sd = stats["ours_steepest_descent"];
  const MethodStats& rigid = stats["rigid_com"];
  const MethodStats& demons = stats["intensity_demons"];
  const MethodStats& dis = stats["intensity_dis-flow"];
  std::ostringstream json;
  json << "{\n  \"bench\": \"registration\",\n  \"cases\": " << cases.size()
       << ",\n  \"seconds_per_slice_mean\": "
       << ng::report::jsonNumber(ng::report::mean(ours.seconds))
       << ",\n  \"dice_mean\": " << ng::report::jsonNumber(ng::report::mean(ours.dice))
       << ",\n  \"point_error_mm_mean\": "
       << ng::report::jsonNumber(ng::report::mean(ours.error_mm))
       << ",\n  \"rigid_point_error_mm_mean\": "
       << ng::report::jsonNumber(ng::report::mean(rigid.error_mm))
       << ",\n  \"rigid_dice_mean\": " << ng::report::jsonNumber(ng::report::mean(rigid.dice))
       << ",\n  \"intensity_point_error_mm_mean\": "
       << ng::report::jsonNumber(ng::report::mean(demons.error_mm))
       << ",\n  \"intensity_dice_mean\": " << ng::report::jsonNumber(ng::report::mean(demons.dice))
       << ",\n  \"intensity_dis_point_error_mm_mean\": "
       << ng::report::jsonNumber(ng::report::mean(dis.error_mm))
       << ",\n  \"steepest_descent_seconds_per_slice_mean\": "
       << ng::report::jsonNumber(ng::report::mean(sd.seconds))
       << ",\n  \"steepest_descent_dice_mean\": "
       << ng::report::jsonNumber(ng::report::mean(sd.dice))
       << ",\n  \"steepest_descent_point_error_mm_mean\": "
       << ng::report::jsonNumber(ng::report::mean(sd.error_mm))
       << ",\n  \"intensity_tissue_tracking_point_error_mm_mean\": "
       << ng::report::jsonNumber(
              ng::report::mean(stats["intensity_demons_tissue_tracking"].error_mm))
       << ",\n  \"ours_beats_both_baselines_on_point_error\": "
       << (ng::report::mean(ours.error_mm) < ng::report::mean(rigid.error_mm) &&
                   ng::report::mean(ours.error_mm) < ng::report::mean(demons.error_mm)
               ? "true"
               : "false")
       << ",\n  \"unregistered_point_error_mm_mean\": "
       << ng::report::jsonNumber(ng::report::mean(unregistered_mm))
       << ",\n  \"failures\": " << ours.failures << "\n}\n";
  ng::report::writeTextFile(args->out_dir + "/summary.json", json.str());
  ng::report::writeTextFile(
      args->out_dir + "/plot.json",
      R"json([{"csv": "cases.csv", "x": "seconds", "y": "point_error_mm", "group": "method", "points": true, "logx": true,
  "title": "Speed against error: time per slice vs mean test-point error (10 cases)", "png": "speed_vs_error.png"},
 {"csv": "cases.csv", "x": "seconds", "y": "dice", "group": "method", "points": true, "logx": true,
  "title": "Time per slice vs Dice of the prostate (10 cases)", "png": "dice.png"},
 {"csv": "sensitivity.csv", "x": "mesh_nodes", "y": "point_error_mm_mean", "filter": {"optimizer": "fast"}, "logx": true,
  "annotate": "seconds_mean", "title": "Mesh size vs mean point error, label: s per slice (figures 3.7-3.8)", "png": "sensitivity_nodes.png"},
 {"csv": "sensitivity.csv", "x": "mesh_nodes", "y": "dice_mean", "filter": {"optimizer": "fast"}, "logx": true,
  "title": "Mesh size vs Dice (figure 3.8a)", "png": "sensitivity_dice.png"},
 {"csv": "sensitivity.csv", "x": "alpha", "y": "point_error_mm_mean", "filter": {"optimizer": "steepest_descent"},
  "annotate": "dice_mean", "title": "Steepest descent: alpha vs mean point error, label: Dice (figure 3.7)", "png": "sensitivity_alpha.png"}]
)json");
  std::cout << json.str();
  return 0;
}
