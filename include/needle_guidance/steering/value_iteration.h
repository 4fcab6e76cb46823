// Value iteration on P_s (dissertation 5.4.3, equations 5.2-5.3): Gauss-Seidel sweeps over the
// discretised MDP of steering_model.h, producing the look-up table of policy_table.h.
#pragma once

#include <cstdint>
#include <vector>

#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance::steering {

struct SolverOptions {
  /// Stop when a full cycle of sweep orders changes no P_s by epsilon or more (5.4.3: 1e-3).
  double epsilon = 1e-3;
  int max_sweeps = 20000;  ///< give up (converged = false) after this many sweeps, >= 1
  /// Threads that share each sweep (rows split into bands; a band reads its neighbour's rows
  /// from a copy made at the start of the sweep, so results do not depend on timing). >= 1.
  int threads = 2;
  /// A position is updated only once the changes of its successors since its last update could
  /// move its values by epsilon * skip_fraction or more (a bound: eq. 5.2 is a maximum of means).
  /// 0 updates every position in every sweep. In [0, 1].
  double skip_fraction = 0.1;
};

struct SolveStats {
  int sweeps = 0;
  bool converged = false;
  double last_max_change = 0.0;  ///< max |change| in the last sweep
  double seconds = 0.0;          ///< wall time of the solve [s]
  std::vector<double> max_change_per_sweep;
  std::vector<std::int64_t> updated_per_sweep;  ///< free positions updated in each sweep
};

/// Solves P_s(x) = max_u sum_j p_ij(u) P_s(x_j) (eq. 5.2) from P_s = 0 (target cells 1), so the
/// values rise monotonically towards the fixed point and an unreachable state stays exactly 0.
/// Gauss-Seidel: each sweep updates in place, visiting columns in decreasing (or increasing) x
/// and rows in decreasing (or increasing) y; the four orders alternate, so every insertion
/// direction has an order in which its successors were already updated. Ties keep kInsert.
/// Values are float: an epsilon below ~1e-7 is met only once the values stop changing.
/// Throws std::invalid_argument for epsilon <= 0, max_sweeps < 1 or threads < 1.
/// @param[out] stats optional convergence record
PolicyTable solveValueIteration(const SteeringModel& model, const SolverOptions& options = {},
                                SolveStats* stats = nullptr);

}  // namespace needle_guidance::steering
