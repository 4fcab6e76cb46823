// The dose-volume planner's model, shared by the MIP (dvh_optimization.cpp) and the descent on
// the criteria (dvh_descent.cpp): each criterion as a volume condition on the dose points of
// its structure, the points with their volume shares and dose-rate matrix, and the objective
// both methods are judged on.
#pragma once

#include <Eigen/Core>
#include <vector>

#include "needle_guidance/dose/dvh_optimization.h"

namespace needle_guidance::dose::dvh_model {

/// A criterion as a volume condition on the dose points of its structure: the volume at dose
/// >= level_Gy is at most (at_most) or at least budget_pct of the structure's volume.
struct VolumeCondition {
  std::size_t criterion = 0;
  int structure = 0;
  double level_Gy = 0.0;
  double budget_pct = 0.0;
  bool at_most = true;
  /// Count only doses above the level (D<p> <= L: less than p of the volume above L, so a point
  /// at exactly L does not count); otherwise doses at or above it (V<p>, D<p> >= L).
  bool strict = false;
  double cc = 0.0;  ///< D<v>cc: v [cm^3], whose share of the sampled volume is the budget
};

/// Dose points: a structure lattice of every structure a condition names.
struct PlanPoints {
  std::vector<int> first;  ///< per structure: index of its first point (-1 if unused)
  std::vector<int> count;
  std::vector<double> pct;        ///< per point: % of its structure's volume
  std::vector<double> volume_m3;  ///< per point: the volume it stands for
  Eigen::MatrixXd d;              ///< dose rate [Gy/s] per point and dwell
};

/// % of the condition's structure at dose >= its level, for point doses `dose` [Gy].
double coveredPct(const PlanPoints& p, const VolumeCondition& v, const Eigen::VectorXd& dose);

/// Sum over the conditions of the volume over (at most) or short of (at least) the budget
/// [percentage points of each structure]; condition 0 counts only when its budget is > 0.
double violationPct(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
                    const Eigen::VectorXd& dose);

/// The planner's objective for point doses `dose` of a plan with total time total_s: minus the
/// target V100 plus violation_penalty per point of violation (and 1e-6 / n per second of total
/// time); infinite over the total-time bound. Lower is better.
double objectiveAt(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
                   const Eigen::VectorXd& dose, double total_s, double total_time_s,
                   const DvhPlanOptions& o);

/// The descent's answer.
struct DescentResult {
  std::vector<double> times_s;   ///< empty when no start was usable
  double objective = 0.0;        ///< objectiveAt of times_s
  double start_objective = 0.0;  ///< the best start's (after its scaling)
  int iterations = 0;
  int restarts = 0;  ///< times the coverage goal was lowered
};

/// Projected descent on a piecewise-quadratic dose-volume penalty (Spirou and Chui, Med Phys
/// 1998: for each condition, only the points that break it beyond its budget are pushed back to
/// its level, with a level margin so that a zero penalty means the exact condition holds) with a
/// coverage goal above the best exact plan so far, raised when reached and lowered when the
/// descent stalls. Every iterate is scored exactly, total violation first and then the
/// objective, and the best is returned, so the answer is never worse than the best start.
/// Processor time at most seconds.
DescentResult descendOnCriteria(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
                                double total_time_s, const std::vector<std::vector<double>>& starts,
                                const DvhPlanOptions& o, double seconds);

}  // namespace needle_guidance::dose::dvh_model
