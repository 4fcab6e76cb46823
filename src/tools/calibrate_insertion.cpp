// Calibrates the needle–tissue interaction (cutting force, shaft friction, pre-puncture
// stiffness; dissertation 2.3.4–2.3.5) to measured insertion forces, or scores a preset on
// trials it never saw. Input: a folder of CSV trials `t_s,depth_mm,force_N`.
//   calibrate_insertion --trials DIR --out DIR [--folds K] [--seed N] [--name NAME]
//   calibrate_insertion --check [PRESET] --trials DIR --out DIR
// Writes OUT/summary.json, OUT/force_depth.csv, OUT/scores.csv, plots (plot.json drawn by
// scripts/plot_bench.py) and, when fitting, the preset OUT/NAME.yaml.
#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "needle_guidance/calibration/calibration.h"
#include "needle_guidance/format.h"
#include "needle_guidance/package_paths.h"
#include "needle_guidance/report/table.h"

namespace ng = needle_guidance;
namespace cal = needle_guidance::calibration;
namespace fs = std::filesystem;
using ng::formatNumber;
using ng::report::jsonNumber;

namespace {

constexpr double kMm = 1e-3;
/// Tissue kept between the deepest compared depth and the block's fixed far face [m] (the
/// 120 mm block leaves 35 mm beyond the liver trials' 85 mm).
constexpr double kFarFaceMargin_m = 0.035;

const char* kUsage =
    "usage: calibrate_insertion --trials DIR --out DIR [--folds K] [--seed N] [--name NAME]\n"
    "                           [--static-ratio R] [--thickness-mm H]\n"
    "       calibrate_insertion --check [PRESET] --trials DIR --out DIR\n"
    "Fits the needle-tissue interaction to force trials (CSV t_s,depth_mm,force_N), with K-fold\n"
    "cross-validation (default 5 folds, seed 29), and writes the preset OUT/NAME.yaml (default\n"
    "name fitted). --check scores a preset (a name in config/interaction/ or a path; default\n"
    "liver_de_jong_2017) on the trials. --static-ratio: static/kinetic friction (default 1.5);\n"
    "--thickness-mm: slice thickness of the simulated block (default 10). Both write\n"
    "OUT/summary.json, force_depth.csv, scores.csv and one plot per trial.\n";

struct Args {
  std::string trials, out, name = "fitted", preset = "liver_de_jong_2017";
  bool check = false;
  int folds = 5;
  unsigned seed = 29;
  double static_ratio = 1.5;
  double thickness_mm = 10.0;
};

/// Parses argv; returns false (with a message) on bad usage.
bool parse(int argc, char** argv, Args& a, std::string& error) {
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        error = arg + " needs a value";
        return "";
      }
      return argv[++i];
    };
    try {
      if (arg == "--trials") {
        a.trials = next();
      } else if (arg == "--out") {
        a.out = next();
      } else if (arg == "--name") {
        a.name = next();
      } else if (arg == "--folds") {
        a.folds = std::stoi(next());
      } else if (arg == "--seed") {
        a.seed = static_cast<unsigned>(std::stoul(next()));
      } else if (arg == "--static-ratio") {
        a.static_ratio = std::stod(next());
      } else if (arg == "--thickness-mm") {
        a.thickness_mm = std::stod(next());
      } else if (arg == "--check") {
        a.check = true;
        if (i + 1 < argc && std::string(argv[i + 1]).rfind("--", 0) != 0) {
          a.preset = argv[++i];
        }
      } else {
        error = "unknown argument '" + arg + "'";
      }
    } catch (const std::exception&) {
      error = "bad number for " + arg;
    }
    if (!error.empty()) {
      return false;
    }
  }
  if (a.trials.empty() || a.out.empty()) {
    error = "--trials DIR and --out DIR are required";
    return false;
  }
  if (!(a.thickness_mm > 0.0) || !(a.static_ratio >= 1.0) || a.folds < 2) {
    error = "--thickness-mm must be > 0, --static-ratio >= 1 and --folds >= 2";
    return false;
  }
  return true;
}

/// force_depth.csv (trial, curve, depth_mm, force_N) and one plot per trial in plot.json.
void writeCurves(const std::string& out, const std::vector<cal::ForceTrial>& trials,
                 const std::vector<double>& depths,
                 const std::vector<std::vector<double>>& measured,
                 const std::vector<std::vector<double>>& simulated, const std::string& label) {
  ng::report::Table table({"trial", "curve", "depth_mm", "force_N"});
  std::ostringstream plots;
  plots << "[";
  for (std::size_t t = 0; t < trials.size(); ++t) {
    for (std::size_t i = 0; i < depths.size(); ++i) {
      table.addRow({trials[t].name, std::string("measured"), depths[i] / kMm, measured[t][i]});
    }
    for (std::size_t i = 0; i < depths.size(); ++i) {
      table.addRow({trials[t].name, label, depths[i] / kMm, simulated[t][i]});
    }
    plots << (t ? ",\n " : "") << R"({"csv": "force_depth.csv", "x": "depth_mm", "y": "force_N", )"
          << R"("group": "curve", "filter": {"trial": ")" << trials[t].name
          << R"("}, "title": "insertion force against depth, )" << trials[t].name
          << R"(", "png": "force_depth_)" << trials[t].name << R"(.png"})";
  }
  plots << "]\n";
  table.writeCsv(out + "/force_depth.csv");
  ng::report::writeTextFile(out + "/plot.json", plots.str());
}

void writeScores(const std::string& out, const std::vector<cal::TrialScore>& scores) {
  ng::report::Table table({"trial", "fold", "rmse_N", "trial_spread_N"});
  for (const cal::TrialScore& s : scores) {
    table.addRow({s.name, static_cast<double>(s.fold), s.rmse_N, s.spread_N});
  }
  table.writeCsv(out + "/scores.csv");
}

/// Draws the plots with the repository's plotter when it is there.
void drawPlots(const std::string& out) {
  const fs::path script = needle_guidance::packageDir() / "scripts" / "plot_bench.py";
  if (fs::exists(script) && fs::exists("/usr/bin/python3")) {
    const std::string command = "/usr/bin/python3 '" + script.string() + "' '" + out + "'";
    if (std::system(command.c_str()) != 0) {
      std::cerr << "calibrate_insertion: plotting failed: " << command << "\n";
    }
  }
}

std::string scoreJson(const cal::ScoreSummary& s) {
  std::ostringstream j;
  j << "  \"rmse_N_median\": " << jsonNumber(s.rmse_median_N) << ",\n"
    << "  \"rmse_N_p90\": " << jsonNumber(s.rmse_p90_N) << ",\n"
    << "  \"trial_spread_N\": " << jsonNumber(s.spread_median_N) << ",\n"
    << "  \"trial_spread_N_p90\": " << jsonNumber(s.spread_p90_N) << ",\n"
    << "  \"rmse_within_spread\": " << (s.rmse_median_N <= s.spread_median_N ? "true" : "false")
    << ",\n";
  return j.str();
}

const char* kSpreadDefinition =
    "  \"trial_spread_definition\": \"median over trials of the RMSE of each trial against the "
    "mean of the other trials, insertion phase, same depth grid as rmse_N\",\n";

int check(const Args& a) {
  const std::vector<cal::ForceTrial> trials = cal::readForceTrials(a.trials);
  const cal::PresetCheck c = cal::checkPreset(cal::loadPreset(a.preset), trials);
  const std::vector<double>& depths = c.depths_m;
  const cal::ScoreSummary& summary = c.summary;
  writeCurves(a.out, trials, depths, c.measured,
              std::vector<std::vector<double>>(trials.size(), c.simulated_N), "simulated_fem");
  writeScores(a.out, c.scores);
  std::ostringstream j;
  j << "{\n  \"mode\": \"check\",\n  \"preset\": \"" << a.preset
    << "\",\n  \"trials\": " << trials.size() << ",\n  \"depth_range_mm\": ["
    << jsonNumber(depths.front() / kMm) << ", " << jsonNumber(depths.back() / kMm) << "],\n"
    << scoreJson(summary) << kSpreadDefinition << "  \"model\": \"2-D FEM insertion into the "
    << "preset's calibration block (quasi-static, the project's needle-tissue interaction)\"\n}\n";
  ng::report::writeTextFile(a.out + "/summary.json", j.str());
  drawPlots(a.out);
  std::cout << j.str();
  return 0;
}

int fit(const Args& a) {
  const std::vector<cal::ForceTrial> trials = cal::readForceTrials(a.trials);
  const cal::CrossValidation cv = cal::crossValidate(trials, cal::CompareGrid{}, a.folds, a.seed);
  cal::InteractionModel base;
  base.needle.cut_length_m = 1e-4;
  base.needle.tip_radius_m = 0.5 * 1.27e-3;  // 18 G needle
  base.needle.stick_velocity_m_s = 5e-4;
  base.block.thickness_m = a.thickness_mm * kMm;
  base.block.length_m = std::max(base.block.length_m, cv.depths_m.back() + kFarFaceMargin_m);

  // Cross-validation with the FEM itself: each fold's fit carried onto the FEM.
  std::vector<std::vector<double>> fem_predicted(trials.size());
  std::vector<cal::TrialScore> fem_scores = cv.scores;
  double reduced_vs_fem = 0.0;
  for (std::size_t f = 0; f < cv.fold_fits.size(); ++f) {
    const cal::InteractionModel m =
        cal::interactionFromCurve(cv.fold_fits[f].params, base, a.static_ratio, cv.depths_m);
    const std::vector<double> fem = cal::femInsertionForce(m.block, m.needle, cv.depths_m);
    reduced_vs_fem =
        std::max(reduced_vs_fem,
                 cal::rmse(fem, cal::reducedInsertionForce(cv.fold_fits[f].params, cv.depths_m)));
    for (std::size_t i = 0; i < trials.size(); ++i) {
      if (cv.scores[i].fold == static_cast<int>(f)) {
        fem_predicted[i] = fem;
        fem_scores[i].rmse_N = cal::rmse(fem, cv.measured[i]);
      }
    }
  }
  if (!cv.full_fit.converged) {
    throw std::runtime_error("the fit did not converge (" + cv.full_fit.message +
                             "); no preset written");
  }
  const cal::ScoreSummary reduced = cal::summarise(cv.scores);
  const cal::ScoreSummary held_out = cal::summarise(fem_scores);
  const cal::ForceCurveParams& p = cv.full_fit.params;
  const cal::InteractionModel model =
      cal::interactionFromCurve(p, base, a.static_ratio, cv.depths_m);

  std::ostringstream provenance;
  provenance << "# Needle-tissue interaction fitted by calibrate_insertion to " << trials.size()
             << " force trials (" << a.trials << "),\n# insertion phase "
             << formatNumber(cv.depths_m.front() / kMm, 3) << "-"
             << formatNumber(cv.depths_m.back() / kMm, 3) << " mm. " << a.folds
             << "-fold cross-validation, FEM on held-out trials: RMSE median "
             << formatNumber(held_out.rmse_median_N, 3) << " N, p90 "
             << formatNumber(held_out.rmse_p90_N, 3) << " N; trial spread median "
             << formatNumber(held_out.spread_median_N, 3) << " N.\n";
  ng::report::writeTextFile(a.out + "/" + a.name + ".yaml",
                            cal::presetYaml(a.name, model, p, provenance.str()));
  writeCurves(a.out, trials, cv.depths_m, cv.measured, fem_predicted, "simulated_fem_held_out");
  writeScores(a.out, fem_scores);
  std::ostringstream j;
  j << "{\n  \"mode\": \"fit\",\n  \"trials\": " << trials.size() << ",\n  \"folds\": " << a.folds
    << ",\n  \"seed\": " << a.seed << ",\n  \"depth_range_mm\": ["
    << jsonNumber(cv.depths_m.front() / kMm) << ", " << jsonNumber(cv.depths_m.back() / kMm)
    << "],\n"
    << scoreJson(held_out) << kSpreadDefinition
    << "  \"reduced_rmse_N_median\": " << jsonNumber(reduced.rmse_median_N) << ",\n"
    << "  \"reduced_vs_fem_rmse_N_max\": " << jsonNumber(reduced_vs_fem) << ",\n"
    << "  \"fit_rmse_to_mean_N\": " << jsonNumber(cv.full_fit.rmse_N) << ",\n"
    << "  \"fit_converged\": " << (cv.full_fit.converged ? "true" : "false") << ",\n"
    << "  \"cutting_force_N\": " << jsonNumber(p.cutting_force_N) << ",\n"
    << "  \"kinetic_friction_N_per_m\": " << jsonNumber(p.friction_N_per_m) << ",\n"
    << "  \"puncture_depth_mm\": " << jsonNumber(p.puncture_depth_m / kMm) << ",\n"
    << "  \"block_young_modulus_kPa\": " << jsonNumber(model.block.young_modulus_Pa / 1e3)
    << ",\n  \"preset\": \"" << a.out << "/" << a.name << ".yaml\"\n}\n";
  ng::report::writeTextFile(a.out + "/summary.json", j.str());
  drawPlots(a.out);
  std::cout << j.str();
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  for (int i = 1; i < argc; ++i) {
    if (std::string(argv[i]) == "--help" || std::string(argv[i]) == "-h") {
      std::cout << kUsage;
      return 0;
    }
  }
  Args args;
  std::string error;
  if (!parse(argc, argv, args, error)) {
    std::cerr << "calibrate_insertion: " << error << "\n" << kUsage;
    return 2;
  }
  try {
    fs::create_directories(args.out);
    return args.check ? check(args) : fit(args);
  } catch (const std::exception& e) {
    std::cerr << "calibrate_insertion: " << e.what() << "\n";
    return 1;
  }
}
