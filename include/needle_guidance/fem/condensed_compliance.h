// Condensation of a linear FEM model onto the DOFs a needle touches: the stiffness restricted to
// the free DOFs is factored once (CHOLMOD, supernodal Cholesky) and the compliance entries
// G = K_ff^-1 are formed column by column, only for the DOFs that constraints ever use, cached
// and reused across steps and insertions. A step then solves a small dense system on the
// constrained DOFs (Goksel et al. 2006 condense the same way and update it with low-rank
// terms); the full field costs one more solve, only when it is asked for.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <vector>

#include "needle_guidance/fem/linear_elasticity.h"

namespace needle_guidance::fem {

class CondensedCompliance {
public:
  /// Factors K restricted to the DOFs with fixed_dof[i] == 0. Throws std::invalid_argument if the
  /// sizes differ, no DOF is fixed and K is singular, or the factorisation fails (the message
  /// says which).
  CondensedCompliance(const SparseMatrix& stiffness, const std::vector<char>& fixed_dof);
  ~CondensedCompliance();
  CondensedCompliance(const CondensedCompliance&) = delete;
  CondensedCompliance& operator=(const CondensedCompliance&) = delete;

  int dofCount() const { return static_cast<int>(fixed_.size()); }
  bool fixed(int dof) const { return fixed_[static_cast<std::size_t>(dof)] != 0; }

  /// Solves the columns of the listed DOFs that are not cached yet, in one batched solve.
  void require(const std::vector<int>& dofs);
  /// Column of G for DOF j: the displacement of every DOF under a unit force on j [m/N]; zero
  /// for a fixed DOF. require({j}) must have been called.
  const Eigen::VectorXd& column(int dof) const;
  /// G(i, j) [m/N]; zero if either DOF is fixed. require({j}) must have been called.
  double entry(int i, int j) const;

  /// Displacement of every DOF under force f (one solve) [m].
  Eigen::VectorXd solve(const Eigen::VectorXd& force_N) const;
  /// solve() in single precision, on a single-precision copy of the factor (formed on first use
  /// after each factorisation; half the bytes a solve reads): the solve's answer to about 1e-7
  /// relative, for an iteration whose tolerance lies far above that (the corotational warp).
  Eigen::VectorXd solveSinglePrecision(const Eigen::VectorXd& force_N) const;
  /// Displacement of every DOF under a force f that is zero outside the listed DOFs (each listed
  /// once) [m]: the combination of their cached columns, read in single precision, where that
  /// reads fewer bytes than a solve (which reads the double factor twice), else one solve. The
  /// solve's field to about 1e-7 relative; a needle acts on a few nodes, so its field costs a
  /// fraction of a solve.
  Eigen::VectorXd solveSupported(const Eigen::VectorXd& force_N,
                                 const std::vector<int>& support) const;

  int cachedColumns() const { return cached_; }
  long long solvedColumns() const { return solved_; }  ///< columns solved since construction
  double factorCpuSeconds() const { return factor_cpu_s_; }
  /// Entries of the Cholesky factor (CHOLMOD's count; a solve reads each twice).
  double factorEntries() const { return factor_entries_; }
  /// Bytes held by the factor (double, and its single-precision copy once formed) and the cached
  /// columns (double and single precision).
  std::size_t memoryBytes() const;
  /// Bytes held by the factor alone.
  std::size_t factorBytes() const;
  /// Drops every cached column (memory bound between insertions along new paths).
  void clearCache();

  /// Factors a new stiffness of the same sparsity pattern and the same fixed DOFs (the warped
  /// stiffness of corotational tissue), re-using the symbolic analysis, and drops every cached
  /// column. Throws std::invalid_argument like the constructor; the compliance is then unusable.
  void refactor(const SparseMatrix& stiffness);
  int refactorCount() const { return refactors_; }
  /// CPU time of the refactorisations so far [s].
  double refactorCpuSeconds() const { return refactor_cpu_s_; }

private:
  /// K restricted to the free DOFs, lower triangle.
  SparseMatrix freeBlock(const SparseMatrix& stiffness) const;

  struct Impl;
  std::unique_ptr<Impl> impl_;
  std::vector<char> fixed_;
  std::vector<int> free_index_;  ///< DOF -> row of K_ff, -1 if fixed
  std::vector<int> free_dofs_;
  std::vector<Eigen::VectorXd> columns_;  ///< per DOF, empty until required
  /// The same columns in single precision, read by solveSupported: a field is read from memory
  /// column by column, and half the bytes take about half the time; its relative error, about
  /// 1e-7, is far below any tolerance the needle's iterations use.
  std::vector<Eigen::VectorXf> field_columns_;
  int cached_ = 0;
  long long solved_ = 0;
  double factor_entries_ = 0.0;  ///< entries of the Cholesky factor (CHOLMOD's count)
  double factor_cpu_s_ = 0.0;
  int refactors_ = 0;
  double refactor_cpu_s_ = 0.0;
};

}  // namespace needle_guidance::fem
