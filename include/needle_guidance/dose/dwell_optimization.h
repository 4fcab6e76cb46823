// Dwell-time optimisation for HDR brachytherapy (dissertation ch. 6): the IPSA penalty
// objective (eq. 6.1-6.3), its exact linear programme (eq. 6.6) solved with COIN-OR Clp, and a
// simulated-annealing optimiser of the same objective in IPSA's style as the clinical baseline.
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

#include "needle_guidance/dose/hdr_case.h"

namespace needle_guidance::dose {

/// The objective per dose point: no penalty for a dose in [lo, hi]; per Gy below lo costs
/// w_under, per Gy above hi costs w_over (weights already divided by the point type's count m_s,
/// eq. 6.2). A point under no criterion has zero weights.
struct PenaltyModel {
  Eigen::VectorXd lo, hi, w_under, w_over;
  std::vector<std::string> notes;  ///< e.g. criteria whose structure has no dose points
  double operator()(const Eigen::VectorXd& dose_Gy) const;  ///< E of eq. 6.3
};

/// Builds the penalty model of the case's criteria. Throws std::invalid_argument for a criterion
/// with D_min > D_max, negative or non-finite weights or doses, or an unknown structure; a
/// criterion whose structure has no points of its kind contributes nothing and is noted.
PenaltyModel penaltyModel(const HdrCase& c);

struct DwellResult {
  std::string method;           ///< "lp" or "sa"
  std::vector<double> times_s;  ///< dwell times t_j >= 0 [s]
  double objective = 0.0;       ///< E (eq. 6.3) of times_s, evaluated from the dose
  double seconds = 0.0;         ///< wall time of the optimisation
  long iterations = 0;          ///< simplex iterations / annealing moves
  /// LP only: the solver's optimum (a lower bound on E for any dwell times); objective -
  /// lower_bound is the optimality gap left by round-off.
  double lower_bound = 0.0;
  std::string status = "ok";
  bool ok() const { return status == "ok"; }
};

struct LpOptions {
  std::string mps_path;  ///< if set, the LP is also written there (MPS) for any other solver
  /// Solve the dual of the ranged-row LP (one row per dwell position, basis n x n) with the
  /// dual simplex: ~10x faster on the cohort than the ranged-row primal (one row per point).
  bool dual_formulation = true;
  double max_seconds = 600.0;
};

/// The LP of eq. 6.6 written with one ranged row per dose point,
///   lo_i <= sum_j d_ij t_j + u_i - o_i <= hi_i,  t, u, o >= 0,  min sum_i w_under_i u_i + w_over_i
///   o_i,
/// equivalent to 6.6 (c_i = w_under u_i + w_over o_i at the optimum) but with one row per point
/// instead of two, and its basis mostly row slacks (the work scales with the dwell count).
/// By default its dual is solved (see LpOptions::dual_formulation) and the dwell times are read
/// from the dual's row prices. Throws std::invalid_argument for a case without dwell positions
/// or a matrix of the wrong size.
DwellResult optimizeLp(const HdrCase& c, const Eigen::MatrixXd& dose_rate,
                       const LpOptions& options = {});

/// Writes the LP above as an MPS file (free format), without solving.
void writeLpMps(const HdrCase& c, const Eigen::MatrixXd& dose_rate, const std::string& path);

struct AnnealingOptions {
  long iterations = 100000;  ///< moves (IPSA-style: one dwell time changed per move)
  unsigned seed = 1;
  double initial_temperature = 0.0;  ///< 0: 0.2 % of the starting objective
  double final_temperature_ratio = 1e-4;
};

/// Simulated annealing of E over dwell times (exponential cooling, Metropolis acceptance, the
/// best state kept), starting from equal times that give the target its prescription on average.
DwellResult optimizeAnnealing(const HdrCase& c, const Eigen::MatrixXd& dose_rate,
                              const AnnealingOptions& options = {});

}  // namespace needle_guidance::dose
