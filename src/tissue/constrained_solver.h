// Private to the tissue module: solves A x = b for a symmetric positive definite A with the
// permanent zero DOFs eliminated and a changing set of prescribed DOFs (x_P = g), and reports
// the constraint reactions r_P = (A x - b)_P. Used by the implicit integrators (dissertation
// 2.2.2) for the needle's tip and shaft constraints (2.3.3-2.3.5).
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <memory>
#include <string>
#include <vector>

namespace needle_guidance::tissue {

/// Counters of the work a ConstrainedSolver did (for benchmarks and tests).
struct SolverStats {
  long factorizations = 0;  ///< full numeric factorisations
  long row_deletions = 0;   ///< DOFs newly prescribed by a factor modification
  long row_additions = 0;   ///< DOFs released by a factor modification
  long rank_updates = 0;    ///< rank-1 updates/downdates for matrix changes
  long solves = 0;          ///< solves
  /// Entries of L (strictly lower part and diagonal) at the last numeric factorisation: every
  /// operation above touches up to this many entries, so it scales their cost with the mesh.
  long factor_entries = 0;
};

class ConstrainedSolver {
public:
  /// @param[in] a symmetric matrix (full storage, both triangles); kept by pointer: the owner
  ///            changes its values in place and calls matrixChanged/matrixReplaced
  /// @param[in] fixed_dofs permanent zero DOFs (sorted, unique)
  /// @param[in] incremental modify the factorisation (row deletions/additions, low-rank
  ///            updates) instead of refactorising on every change
  ConstrainedSolver(const Eigen::SparseMatrix<double>& a, std::vector<int> fixed_dofs,
                    bool incremental);
  ~ConstrainedSolver();
  /// A copy of this solver (factor, pending changes, counters) for `a`, a copy of the matrix
  /// this solver was given (same pattern and values): continuing with the copy gives the same
  /// results, bit for bit, as continuing with this solver.
  std::unique_ptr<ConstrainedSolver> clone(const Eigen::SparseMatrix<double>& a) const;
  ConstrainedSolver(const ConstrainedSolver&) = delete;
  ConstrainedSolver& operator=(const ConstrainedSolver&) = delete;

  /// Every value of A changed (refactorise at the next solve).
  void matrixReplaced();
  /// Only the rows/columns `dofs` of A changed.
  void matrixChanged(const std::vector<int>& dofs);

  /// Solves A x = b on the free DOFs with x_F = 0 and x_P = g; reactions (order of p_dofs)
  /// = (A x - b)_P. Returns false (and an error message) when the factorisation fails (A not
  /// positive definite on the free DOFs) or the result is not finite.
  bool solve(const Eigen::VectorXd& b, const std::vector<int>& p_dofs,
             const std::vector<double>& p_values, Eigen::VectorXd& x, Eigen::VectorXd& reactions,
             std::string& error);

  const SolverStats& stats() const { return stats_; }

private:
  ConstrainedSolver() = default;
  struct Impl;
  std::unique_ptr<Impl> impl_;
  SolverStats stats_;
};

}  // namespace needle_guidance::tissue
