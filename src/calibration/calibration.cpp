#include "needle_guidance/calibration/calibration.h"

#include "needle_guidance/package_paths.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <numeric>
#include <random>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/format.h"
#include "needle_guidance/scene/interaction_preset.h"

namespace needle_guidance::calibration {
namespace {

constexpr double kMm = 1e-3;
/// Depth at which the pre-puncture stiffness is read: two grid steps into the tissue.
constexpr int kStiffnessSteps = 2;
/// A cutting force no needle reaches: the tissue only deforms.
constexpr double kNoCut_N = 1e6;
/// The FEM-curve correction compares depths beyond this many puncture depths.
constexpr double kSettledPunctures = 3.0;
/// Tissue kept between the deepest compared depth and the block's fixed far face [m].
constexpr double kFarFaceMargin_m = 0.035;
/// Rounds of the FEM-curve correction (each one FEM insertion).
constexpr int kCorrectionRounds = 2;

}  // namespace

double prePunctureStiffness(const InteractionModel& model) {
  tissue::NeedleParams needle = model.needle;
  needle.cutting_force_N = kNoCut_N;
  const double depth = kStiffnessSteps * model.block.depth_step_m;
  const std::vector<double> force = femInsertionForce(model.block, needle, {depth});
  return force.front() / depth;
}

InteractionModel interactionFromCurve(const ForceCurveParams& curve, const InteractionModel& base,
                                      double static_to_kinetic,
                                      const std::vector<double>& depths_m) {
  if (!(static_to_kinetic >= 1.0) || !std::isfinite(static_to_kinetic)) {
    throw std::invalid_argument("interactionFromCurve: static/kinetic friction ratio " +
                                formatNumber(static_to_kinetic) + " must be >= 1");
  }
  InteractionModel model = base;
  model.needle.cutting_force_N = curve.cutting_force_N;
  model.needle.kinetic_friction_N_per_m = curve.friction_N_per_m;
  const double wanted = curve.cutting_force_N / curve.puncture_depth_m;
  const double have = prePunctureStiffness(base);
  if (!(have > 0.0) || !(wanted > 0.0)) {
    throw std::invalid_argument("interactionFromCurve: pre-puncture stiffness " +
                                formatNumber(wanted) +
                                " N/m cannot be reached (block: " + formatNumber(have) + " N/m)");
  }
  model.block.young_modulus_Pa = base.block.young_modulus_Pa * wanted / have;
  // The FEM's tip force saws between the cutting force and the force just after a cut, so its
  // mean lies below the cutting force; the shaft's length in tissue lags the depth by the
  // tissue's displacement. A least-squares line through FEM - curve past the puncture corrects
  // the cutting force (offset) and the friction (slope); a few rounds settle it.
  std::vector<double> past;
  for (double d : depths_m) {
    if (d >= kSettledPunctures * curve.puncture_depth_m) {
      past.push_back(d);
    }
  }
  const std::vector<double> target = reducedInsertionForce(curve, past);
  for (int round = 0; round < kCorrectionRounds && past.size() >= 2; ++round) {
    model.needle.static_friction_N_per_m =
        static_to_kinetic * model.needle.kinetic_friction_N_per_m;
    const std::vector<double> fem = femInsertionForce(model.block, model.needle, past);
    double sx = 0.0, sy = 0.0, sxx = 0.0, sxy = 0.0;
    const double n = static_cast<double>(past.size());
    for (std::size_t i = 0; i < past.size(); ++i) {
      const double x = past[i] - curve.puncture_depth_m;
      const double r = fem[i] - target[i];
      sx += x;
      sy += r;
      sxx += x * x;
      sxy += x * r;
    }
    const double slope = (n * sxy - sx * sy) / (n * sxx - sx * sx);
    const double offset = (sy - slope * sx) / n;
    model.needle.cutting_force_N = std::max(0.0, model.needle.cutting_force_N - offset);
    model.needle.kinetic_friction_N_per_m =
        std::max(0.0, model.needle.kinetic_friction_N_per_m - slope);
  }
  model.needle.static_friction_N_per_m = static_to_kinetic * model.needle.kinetic_friction_N_per_m;
  return model;
}

std::vector<double> compareDepths(const std::vector<ForceTrial>& trials, const CompareGrid& grid) {
  if (trials.empty()) {
    throw std::invalid_argument("compareDepths: no trials");
  }
  double last = grid.last_depth_m;
  if (!(last > 0.0)) {
    const auto shallowest = std::min_element(
        trials.begin(), trials.end(),
        [](const ForceTrial& a, const ForceTrial& b) { return maxDepth(a) < maxDepth(b); });
    last = maxDepth(*shallowest) - 0.5 * kMm;
    if (!(last >= grid.first_depth_m)) {
      throw std::invalid_argument(
          shallowest->path + ": reaches only " + formatNumber(maxDepth(*shallowest) / kMm) +
          " mm, too shallow to compare from " + formatNumber(grid.first_depth_m / kMm) + " mm");
    }
  }
  return depthGrid(grid.first_depth_m, last, grid.step_m);
}

std::vector<int> foldAssignment(std::size_t n, int folds, unsigned seed) {
  std::vector<std::size_t> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::mt19937 rng(seed);
  std::shuffle(order.begin(), order.end(), rng);
  std::vector<int> fold(n);
  for (std::size_t i = 0; i < n; ++i) {
    fold[order[i]] = static_cast<int>(i % static_cast<std::size_t>(folds));
  }
  return fold;
}

std::vector<TrialScore> scoreCurve(const std::vector<double>& model_N,
                                   const std::vector<std::vector<double>>& measured,
                                   const std::vector<ForceTrial>& trials) {
  const std::vector<double> spread = leaveOneOutSpread(measured);
  std::vector<TrialScore> scores;
  for (std::size_t i = 0; i < measured.size(); ++i) {
    scores.push_back({trials[i].name, -1, rmse(model_N, measured[i]), spread[i]});
  }
  return scores;
}

CrossValidation crossValidate(const std::vector<ForceTrial>& trials, const CompareGrid& grid,
                              int folds, unsigned seed) {
  if (folds < 2 || trials.size() < static_cast<std::size_t>(folds)) {
    throw std::invalid_argument("crossValidate: " + std::to_string(folds) +
                                " folds need at least " + "2 folds and as many trials (have " +
                                std::to_string(trials.size()) + ")");
  }
  CrossValidation cv;
  cv.depths_m = compareDepths(trials, grid);
  for (const ForceTrial& trial : trials) {
    cv.measured.push_back(insertionForceAt(trial, cv.depths_m));
  }
  const std::vector<int> fold = foldAssignment(trials.size(), folds, seed);
  const std::vector<double> spread = leaveOneOutSpread(cv.measured);
  cv.predicted.resize(trials.size());
  cv.scores.resize(trials.size());
  for (int f = 0; f < folds; ++f) {
    std::vector<std::vector<double>> training;
    for (std::size_t i = 0; i < trials.size(); ++i) {
      if (fold[i] != f) {
        training.push_back(cv.measured[i]);
      }
    }
    cv.fold_fits.push_back(fitInsertionForce(training, cv.depths_m));
    const std::vector<double> curve =
        reducedInsertionForce(cv.fold_fits.back().params, cv.depths_m);
    for (std::size_t i = 0; i < trials.size(); ++i) {
      if (fold[i] == f) {
        cv.predicted[i] = curve;
        cv.scores[i] = {trials[i].name, f, rmse(curve, cv.measured[i]), spread[i]};
      }
    }
  }
  cv.full_fit = fitInsertionForce(cv.measured, cv.depths_m);
  return cv;
}

ScoreSummary summarise(const std::vector<TrialScore>& scores) {
  std::vector<double> r, s;
  for (const TrialScore& score : scores) {
    r.push_back(score.rmse_N);
    s.push_back(score.spread_N);
  }
  return {percentile(r, 50.0), percentile(r, 90.0), percentile(s, 50.0), percentile(s, 90.0)};
}

InteractionModel loadPreset(const std::string& name_or_path) {
  const scene::Needle keys = scene::loadInteractionPreset(name_or_path);
  InteractionModel model;
  model.needle.cutting_force_N = keys.cutting_force_N;
  if (keys.cut_length_m > 0.0) {
    model.needle.cut_length_m = keys.cut_length_m;
  }
  model.needle.static_friction_N_per_m = keys.static_friction_N_per_m;
  model.needle.kinetic_friction_N_per_m = keys.kinetic_friction_N_per_m;
  model.needle.stick_velocity_m_s = keys.stick_velocity_m_s;
  model.needle.tip_radius_m = 0.5 * keys.diameter_m;

  const std::string path = scene::interactionPresetFile(name_or_path);
  const YAML::Node block = YAML::LoadFile(path)["calibration_block"];
  auto value = [&](const char* key, double to_si) {
    const YAML::Node v = block[key];
    double x = 0.0;
    try {
      x = v.as<double>();
    } catch (const YAML::Exception&) {
      throw std::invalid_argument(path + ": calibration_block." + key +
                                  " is missing or not a number");
    }
    if (!std::isfinite(x) || !(x > 0.0)) {
      throw std::invalid_argument(path + ": calibration_block." + key + " " + formatNumber(x) +
                                  " must be positive");
    }
    return x * to_si;
  };
  model.block.length_m = value("length_mm", kMm);
  model.block.height_m = value("height_mm", kMm);
  model.block.thickness_m = value("thickness_mm", kMm);
  model.block.young_modulus_Pa = value("young_modulus_kPa", 1e3);
  model.block.poisson_ratio = value("poisson_ratio", 1.0);
  model.block.insertion_velocity_m_s = value("insertion_velocity_mm_s", kMm);
  return model;
}

std::string presetYaml(const std::string& name, const InteractionModel& model,
                       const ForceCurveParams& curve, const std::string& provenance) {
  const tissue::NeedleParams& n = model.needle;
  const CalibrationBlock& b = model.block;
  auto num = [](double v) { return formatNumber(v, 4); };
  std::ostringstream y;
  y << provenance << "interaction: {name: " << name << "}\n"
    << "# Forces are totals on the needle [N] (2-D plane-strain slice of thickness h).\n"
    << "needle:\n"
    << "  cutting_force_N: " << num(n.cutting_force_N) << "\n"
    << "  cut_length_mm: " << num(n.cut_length_m / kMm) << "\n"
    << "  static_friction_N_per_cm: " << num(n.static_friction_N_per_m / 100.0) << "\n"
    << "  kinetic_friction_N_per_cm: " << num(n.kinetic_friction_N_per_m / 100.0) << "\n"
    << "  stick_velocity_mm_s: " << num(n.stick_velocity_m_s / kMm) << "\n"
    << "  diameter_mm: " << num(2.0 * n.tip_radius_m / kMm) << "\n"
    << "# The block the fit simulated (not read by scenes): its Young's modulus sets the\n"
    << "# pre-puncture stiffness f_c / d_p for this slice thickness (only E h is identified).\n"
    << "calibration_block:\n"
    << "  length_mm: " << num(b.length_m / kMm) << "\n"
    << "  height_mm: " << num(b.height_m / kMm) << "\n"
    << "  thickness_mm: " << num(b.thickness_m / kMm) << "\n"
    << "  young_modulus_kPa: " << num(b.young_modulus_Pa / 1e3) << "\n"
    << "  poisson_ratio: " << num(b.poisson_ratio) << "\n"
    << "  insertion_velocity_mm_s: " << num(b.insertion_velocity_m_s / kMm) << "\n"
    << "fitted_curve: {cutting_force_N: " << num(curve.cutting_force_N)
    << ", kinetic_friction_N_per_cm: " << num(curve.friction_N_per_m / 100.0)
    << ", puncture_depth_mm: " << num(curve.puncture_depth_m / kMm) << "}\n";
  return y.str();
}

const std::vector<std::string>& liverHeldOutTrialNames() {
  static const std::vector<std::string> names{"trial_04", "trial_09", "trial_14",
                                              "trial_19", "trial_24", "trial_29"};
  return names;
}

std::vector<ForceTrial> liverHeldOutTrials(std::string* source) {
  namespace fs = std::filesystem;
  const char* shared = std::getenv("NG_SHARED_DATA");
  std::error_code error;
  fs::path dir = configDir() / "interaction" / "de_jong_2017_heldout";
  if (shared != nullptr && fs::is_directory(fs::path(shared) / "needle_force_liver", error)) {
    dir = fs::path(shared) / "needle_force_liver";
  }
  std::vector<ForceTrial> trials;
  for (const std::string& name : liverHeldOutTrialNames()) {
    trials.push_back(readForceTrial((dir / (name + ".csv")).string()));
  }
  if (source != nullptr) {
    *source = dir.string();
  }
  return trials;
}

PresetCheck checkPreset(const InteractionModel& model, const std::vector<ForceTrial>& trials) {
  PresetCheck check;
  check.depths_m = compareDepths(trials, CompareGrid{});
  for (const ForceTrial& trial : trials) {
    check.measured.push_back(insertionForceAt(trial, check.depths_m));
  }
  InteractionModel deep_enough = model;  // a longer block for trials deeper than the preset's
  deep_enough.block.length_m =
      std::max(model.block.length_m, check.depths_m.back() + kFarFaceMargin_m);
  check.simulated_N = femInsertionForce(deep_enough.block, model.needle, check.depths_m);
  check.scores = scoreCurve(check.simulated_N, check.measured, trials);
  check.summary = summarise(check.scores);
  return check;
}

}  // namespace needle_guidance::calibration
