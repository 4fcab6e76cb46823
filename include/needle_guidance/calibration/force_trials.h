// Measured needle insertion forces: a folder of CSV trials `t_s,depth_mm,force_N` (the format of
// de Jong et al. 2017's liver data), their insertion phase on a common depth grid, and the
// spread between trials measured the way a model's error is.
#pragma once

#include <string>
#include <vector>

namespace needle_guidance::calibration {

/// One insertion as recorded: time, needle depth and axial force, one row per sample.
struct ForceTrial {
  std::string name;  ///< file stem, e.g. trial_07
  std::string path;
  std::vector<double> t_s;
  std::vector<double> depth_m;  ///< needle displacement from first contact [m]
  std::vector<double> force_N;  ///< axial force on the needle, + resisting insertion [N]
};

/// Reads one trial. Throws std::invalid_argument "FILE:LINE: what" for a missing file, a header
/// other than `t_s,depth_mm,force_N`, a row without three numbers, a non-finite value, time not
/// increasing, or fewer than two rows. Blank lines and Windows line ends are accepted.
ForceTrial readForceTrial(const std::string& path);

/// Every *.csv of a folder, by file name. Throws std::invalid_argument for a missing folder, a
/// folder without CSVs, or any bad file (the message names it).
std::vector<ForceTrial> readForceTrials(const std::string& folder);

/// Deepest depth of a trial [m].
double maxDepth(const ForceTrial& trial);

/// The insertion phase (from the start to where the deepest depth is first reached) resampled at
/// `depths_m` (ascending): at each depth, the force when the needle first got there (linear
/// between samples). Throws std::invalid_argument naming the trial when it does not reach the
/// deepest grid depth.
std::vector<double> insertionForceAt(const ForceTrial& trial, const std::vector<double>& depths_m);

/// Depth grid from first_m to last_m in steps of step_m (last included when on the grid).
std::vector<double> depthGrid(double first_m, double last_m, double step_m);

/// Root mean square of a - b (same length, not empty) [units of a].
double rmse(const std::vector<double>& a, const std::vector<double>& b);

/// Spread between trials, measured as a model's error is: for each curve, the RMSE against the
/// mean of the other curves (all on the same depth grid) [N]. Needs at least two curves.
std::vector<double> leaveOneOutSpread(const std::vector<std::vector<double>>& curves);

/// The p-th percentile (0-100) of values, linear between order statistics (not empty).
double percentile(std::vector<double> values, double p);

}  // namespace needle_guidance::calibration
