// Calibration of the needle–tissue interaction (dissertation 2.3.4–2.3.5) to measured insertion
// forces: the k-fold cross-validated fit, the mapping of the fitted curve onto the FEM's
// parameters, and the scoring of an interaction preset on trials it never saw.
//
// Units and the 2-D assumption: the FEM is a plane-strain slice of thickness h whose stiffness
// matrix is scaled by h, so its nodal forces, and hence the needle's cutting force and shaft
// friction, are totals in N (N/m of needle), the same quantities a force sensor on a real needle
// measures. The slice thickness only changes how far the tissue moves under those forces; the
// fit identifies the tissue's stiffness against the tip as E h (calibration block below).
#pragma once

#include <string>
#include <vector>

#include "needle_guidance/calibration/fem_force_curve.h"
#include "needle_guidance/calibration/force_trials.h"
#include "needle_guidance/calibration/insertion_force_fit.h"

namespace needle_guidance::calibration {

/// Where the measured and the simulated curves are compared.
struct CompareGrid {
  double first_depth_m = 5e-4;  ///< shallowest depth compared [m]
  double step_m = 5e-4;         ///< grid spacing [m]
  /// Deepest depth compared [m]; 0: 0.5 mm short of the shallowest trial's deepest depth.
  double last_depth_m = 0.0;
};

/// The FEM's interaction parameters and the block they were fitted in.
struct InteractionModel {
  tissue::NeedleParams needle;
  CalibrationBlock block;
};

/// The reduced curve carried onto the FEM: the block's Young's modulus scaled so that the FEM's
/// pre-puncture stiffness is f_c / d_p (linear elasticity: stiffness proportional to E); then
/// the cutting force and kinetic friction corrected (two FEM insertions to the deepest of
/// depths_m) until the FEM's mean force past the puncture follows f_c + f_k (d - d_p); static
/// friction static_to_kinetic times kinetic (a steady insertion slips along the whole shaft,
/// so insertion data cannot tell it).
InteractionModel interactionFromCurve(const ForceCurveParams& curve, const InteractionModel& base,
                                      double static_to_kinetic,
                                      const std::vector<double>& depths_m);

/// FEM stiffness of the block against the needle tip before the first cut [N/m].
double prePunctureStiffness(const InteractionModel& model);

/// One trial's score.
struct TrialScore {
  std::string name;
  int fold = -1;          ///< cross-validation fold it was held out in (-1: scored by --check)
  double rmse_N = 0.0;    ///< model against the trial [N]
  double spread_N = 0.0;  ///< mean of the other trials against the trial [N]
};

/// k-fold cross-validation of the reduced-curve fit.
struct CrossValidation {
  std::vector<double> depths_m;
  std::vector<std::vector<double>> measured;   ///< per trial, at depths_m [N]
  std::vector<std::vector<double>> predicted;  ///< per trial, by the fit it was held out of [N]
  std::vector<TrialScore> scores;
  std::vector<ForceFit> fold_fits;
  ForceFit full_fit;  ///< on every trial: the parameters to ship
};

/// The depth grid every trial reaches. Throws std::invalid_argument naming a trial too shallow.
std::vector<double> compareDepths(const std::vector<ForceTrial>& trials, const CompareGrid& grid);

/// Splits n trials into `folds` folds by a seeded shuffle; fold of each trial.
std::vector<int> foldAssignment(std::size_t n, int folds, unsigned seed);

/// Fits on all folds but one, scores the held-out trials, for every fold; then fits all.
/// Needs at least 2 folds and as many trials. Throws std::invalid_argument otherwise.
CrossValidation crossValidate(const std::vector<ForceTrial>& trials, const CompareGrid& grid,
                              int folds, unsigned seed);

/// Scores a model curve (at `depths_m`) on measured curves: RMSE per trial and the
/// leave-one-out spread between the trials.
std::vector<TrialScore> scoreCurve(const std::vector<double>& model_N,
                                   const std::vector<std::vector<double>>& measured,
                                   const std::vector<ForceTrial>& trials);

/// Summary figures of scores: median and 90th percentile of rmse_N and spread_N.
struct ScoreSummary {
  double rmse_median_N = 0.0, rmse_p90_N = 0.0;
  double spread_median_N = 0.0, spread_p90_N = 0.0;
};
ScoreSummary summarise(const std::vector<TrialScore>& scores);

/// Reads the interaction preset's needle keys (scene::loadInteractionPreset) and its
/// `calibration_block:` section. Throws std::invalid_argument naming the file and key.
InteractionModel loadPreset(const std::string& name_or_path);

/// The preset file's text: needle keys, the calibration block, the fit's figures and sources.
std::string presetYaml(const std::string& name, const InteractionModel& model,
                       const ForceCurveParams& curve, const std::string& provenance);

/// Trials of de Jong et al. 2017 kept out of the liver preset's fit (every fifth: 04, 09, ...).
const std::vector<std::string>& liverHeldOutTrialNames();

/// The liver preset's held-out trials: from $NG_SHARED_DATA/needle_force_liver when that folder
/// is there, else the excerpt shipped in config/interaction/de_jong_2017_heldout. `source` says
/// which folder was read.
std::vector<ForceTrial> liverHeldOutTrials(std::string* source = nullptr);

/// A preset scored by the FEM on trials: per-trial scores and their summary.
struct PresetCheck {
  std::vector<double> depths_m;
  std::vector<std::vector<double>> measured;  ///< per trial [N]
  std::vector<double> simulated_N;            ///< the FEM's curve [N]
  std::vector<TrialScore> scores;
  ScoreSummary summary;
};
PresetCheck checkPreset(const InteractionModel& model, const std::vector<ForceTrial>& trials);

}  // namespace needle_guidance::calibration
