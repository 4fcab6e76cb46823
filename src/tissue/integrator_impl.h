// Private to the tissue module: factories and shared building blocks of the integrators
// (dissertation 2.2.2).
#pragma once

#include <memory>
#include <vector>

#include "constrained_solver.h"
#include "needle_guidance/tissue/integrator.h"

namespace needle_guidance::tissue::detail {

/// Validates a step's inputs. Throws std::invalid_argument for broken preconditions (sizes,
/// DOF out of range, duplicated or fixed prescribed DOF); returns a failed status for a
/// non-finite input or a bad time step.
StepStatus checkStepInput(const FemModel& model, const std::vector<char>& fixed_mark, double dt_s,
                          bool dynamic, const Eigen::VectorXd& f_ext, const Prescribed& prescribed);

std::unique_ptr<Integrator> makeQuasiStatic(const FemModel& model, std::vector<int> fixed_dofs,
                                            const IntegratorOptions& options);
std::unique_ptr<Integrator> makeNewmark(const FemModel& model, std::vector<int> fixed_dofs,
                                        const IntegratorOptions& options);
std::unique_ptr<Integrator> makeExplicit(const FemModel& model, std::vector<int> fixed_dofs,
                                         const IntegratorOptions& options);

/// Marker per DOF (1 = fixed).
inline std::vector<char> fixedMark(int dof_count, const std::vector<int>& fixed_dofs) {
  std::vector<char> mark(dof_count, 0);
  for (int d : fixed_dofs)
    mark[d] = 1;
  return mark;
}

/// A constrained solver's work counters as an integrator reports them.
inline Integrator::SolverCounters solverCountersOf(const SolverStats& s) {
  return {s.factorizations, s.row_deletions, s.row_additions,
          s.rank_updates,   s.solves,        s.factor_entries};
}

/// Maximum number of fixed-point iterations of the corotational quasi-static solve.
constexpr int kCorotationalMaxIterations = 30;
/// Convergence of the corotational iterations: max |du| below this times max |u| (+ 1e-15 m).
constexpr double kCorotationalRelTol = 1e-10;

}  // namespace needle_guidance::tissue::detail
