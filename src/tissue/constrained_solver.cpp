// Constrained sparse solves for the implicit integrators (see constrained_solver.h).
//
// One simplicial LDL' factorisation (CHOLMOD) of the base matrix with the permanent fixed DOFs
// eliminated is kept and modified instead of refactorised (Davis & Hager, "Modifying a sparse
// Cholesky factorization", SIAM J. Matrix Anal. Appl. 20, 1999; "Row modifications of a sparse
// Cholesky factorization", 2005):
//  * a newly prescribed DOF k is deleted from the factor (cholmod_rowdel: row/column k become
//    the identity, so the solve returns x_k = rhs_k = g_k); a released DOF is added back
//    (cholmod_rowadd with the current column of A);
//  * a model change confined to DOFs D (FemModel::moveNode) is A' = A + E_D Delta E_D^T: Delta
//    is split by its eigen-decomposition into C+ C+^T - C- C-^T and applied as a rank-|D|
//    update then downdate (cholmod_updown);
//  * after kMaxModifications modifications, or when A is replaced (Newmark dt change,
//    corotational), the matrix is refactorised numerically with the symbolic analysis (fill-
//    reducing ordering computed once, the pattern never changes) reused.
#include "constrained_solver.h"

extern "C" {
#include <cholmod.h>
}

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace needle_guidance::tissue {
namespace {

/// Factor modifications (rank-1 equivalents: row deletions/additions count 1, updown columns
/// count 1) after which refactorising is cheaper and keeps round-off from accumulating.
constexpr long kMaxModifications = 400;
/// Eigenvalues of a model change below this fraction of the largest are dropped (round-off).
constexpr double kDeltaEigenRelTol = 1e-15;

}  // namespace

/// The solver's state that plain copies copy (everything but the matrix and CHOLMOD's objects).
struct ConstrainedSolverData {
  bool incremental = true;
  int n_full = 0;
  int n_red = 0;
  std::vector<int> red_of_full;  ///< full DOF -> reduced (permuted) index, -1 for fixed
  std::vector<int> full_of_red;
  std::vector<int> entry_pos;  ///< full A value index -> CHOLMOD upper value index, or -1
  std::vector<int> entry_row_red, entry_col_red;  ///< per CHOLMOD value: reduced row / column
  std::vector<int> full_entry_of_pos;             ///< CHOLMOD value index -> full A value index
  std::vector<double> base;   ///< A values (upper, reduced) represented by the factor
  std::vector<char> deleted;  ///< per reduced index: row/column deleted (prescribed)
  std::vector<char> pending;  ///< per reduced index: A changed since the last sync
  std::vector<int> pending_list;
  bool dirty = true;
  long modifications = 0;
};

struct ConstrainedSolver::Impl : ConstrainedSolverData {
  const Eigen::SparseMatrix<double>* a = nullptr;
  cholmod_common common{};
  cholmod_sparse* a_chol = nullptr;  ///< upper triangle, permuted, values of the factored matrix
  cholmod_factor* l_symbolic = nullptr;
  cholmod_factor* l = nullptr;
  cholmod_dense* x_dense = nullptr;
  cholmod_dense* b_dense = nullptr;
  cholmod_dense* y_work = nullptr;
  cholmod_dense* e_work = nullptr;

  ~Impl() {
    if (a_chol)
      cholmod_free_sparse(&a_chol, &common);
    if (l)
      cholmod_free_factor(&l, &common);
    if (l_symbolic)
      cholmod_free_factor(&l_symbolic, &common);
    if (x_dense)
      cholmod_free_dense(&x_dense, &common);
    if (b_dense)
      cholmod_free_dense(&b_dense, &common);
    if (y_work)
      cholmod_free_dense(&y_work, &common);
    if (e_work)
      cholmod_free_dense(&e_work, &common);
    cholmod_finish(&common);
  }

  /// cholmod_start with the settings every factorisation after setup() uses.
  void start() {
    cholmod_start(&common);
    common.print = 0;
    common.error_handler = nullptr;
  }

  /// The settings setup() leaves for the numeric factorisations (natural order, simplicial).
  void numericSettings() {
    common.nmethods = 1;
    common.method[0].ordering = CHOLMOD_NATURAL;
    common.postorder = 0;
    common.supernodal = CHOLMOD_SIMPLICIAL;
    common.final_ll = 0;
  }

  /// Copies `o`'s state (a fresh CHOLMOD workspace, copies of its matrices and factor).
  void copyFrom(const Impl& o) {
    start();
    numericSettings();
    static_cast<ConstrainedSolverData&>(*this) = o;
    a_chol = cholmod_copy_sparse(o.a_chol, &common);
    l_symbolic = cholmod_copy_factor(o.l_symbolic, &common);
    l = o.l ? cholmod_copy_factor(o.l, &common) : nullptr;
    b_dense = cholmod_allocate_dense(n_red, 1, n_red, CHOLMOD_REAL, &common);
    if (!a_chol || !l_symbolic || (o.l && !l) || !b_dense) {
      throw std::runtime_error("ConstrainedSolver: copying the factorisation failed");
    }
  }

  void setup(const std::vector<int>& fixed_dofs) {
    start();
    n_full = static_cast<int>(a->rows());
    std::vector<char> fixed(n_full, 0);
    for (int d : fixed_dofs)
      fixed[d] = 1;
    std::vector<int> free_of_full(n_full, -1), full_of_free;
    for (int d = 0; d < n_full; ++d) {
      if (!fixed[d]) {
        free_of_full[d] = static_cast<int>(full_of_free.size());
        full_of_free.push_back(d);
      }
    }
    n_red = static_cast<int>(full_of_free.size());
    // Fill-reducing ordering (AMD / METIS as CHOLMOD chooses) of the free-DOF matrix, once.
    std::vector<int> perm(n_red);
    {
      std::vector<Eigen::Triplet<double>> t;
      for (int col = 0; col < n_full; ++col) {
        if (free_of_full[col] < 0)
          continue;
        for (Eigen::SparseMatrix<double>::InnerIterator it(*a, col); it; ++it) {
          const int r = free_of_full[it.row()];
          if (r >= 0 && r <= free_of_full[col])
            t.emplace_back(r, free_of_full[col], 1.0);
        }
      }
      cholmod_sparse* pat = buildUpper(t, n_red);
      common.supernodal = CHOLMOD_SIMPLICIAL;
      cholmod_factor* lp = cholmod_analyze(pat, &common);
      if (!lp)
        throw std::runtime_error("ConstrainedSolver: CHOLMOD analysis failed");
      const int* p = static_cast<const int*>(lp->Perm);
      for (int i = 0; i < n_red; ++i)
        perm[i] = p[i];  // new index i <- free index p[i]
      cholmod_free_factor(&lp, &common);
      cholmod_free_sparse(&pat, &common);
    }
    red_of_full.assign(n_full, -1);
    full_of_red.resize(n_red);
    for (int i = 0; i < n_red; ++i) {
      full_of_red[i] = full_of_free[perm[i]];
      red_of_full[full_of_red[i]] = i;
    }
    // Upper-triangular pattern in the permuted order and the map from A's values.
    std::vector<Eigen::Triplet<double>> t;
    for (int col = 0; col < n_full; ++col) {
      const int rc = red_of_full[col];
      if (rc < 0)
        continue;
      for (Eigen::SparseMatrix<double>::InnerIterator it(*a, col); it; ++it) {
        const int rr = red_of_full[it.row()];
        if (rr >= 0 && rr <= rc)
          t.emplace_back(rr, rc, 0.0);
      }
    }
    a_chol = buildUpper(t, n_red);
    const int* ap = static_cast<const int*>(a_chol->p);
    const int* ai = static_cast<const int*>(a_chol->i);
    entry_pos.assign(a->nonZeros(), -1);
    full_entry_of_pos.assign(ap[n_red], -1);
    entry_row_red.resize(ap[n_red]);
    entry_col_red.resize(ap[n_red]);
    for (int c = 0; c < n_red; ++c) {
      for (int k = ap[c]; k < ap[c + 1]; ++k) {
        entry_row_red[k] = ai[k];
        entry_col_red[k] = c;
      }
    }
    const int* outer = a->outerIndexPtr();
    const int* inner = a->innerIndexPtr();
    for (int col = 0; col < n_full; ++col) {
      const int rc = red_of_full[col];
      if (rc < 0)
        continue;
      for (int idx = outer[col]; idx < outer[col + 1]; ++idx) {
        const int rr = red_of_full[inner[idx]];
        if (rr < 0 || rr > rc)
          continue;
        const int* it = std::lower_bound(ai + ap[rc], ai + ap[rc + 1], rr);
        entry_pos[idx] = static_cast<int>(it - ai);
        full_entry_of_pos[entry_pos[idx]] = idx;
      }
    }
    // Symbolic analysis of the permuted matrix in its natural order (kept: the pattern of A
    // never changes; every refactorisation starts from a copy of it).
    numericSettings();
    l_symbolic = cholmod_analyze(a_chol, &common);
    if (!l_symbolic)
      throw std::runtime_error("ConstrainedSolver: CHOLMOD symbolic analysis failed");
    base.assign(ap[n_red], 0.0);
    deleted.assign(n_red, 0);
    pending.assign(n_red, 0);
    b_dense = cholmod_allocate_dense(n_red, 1, n_red, CHOLMOD_REAL, &common);
  }

  cholmod_sparse* buildUpper(std::vector<Eigen::Triplet<double>>& t, int n) {
    std::sort(t.begin(), t.end(), [](const auto& x, const auto& y) {
      return x.col() != y.col() ? x.col() < y.col() : x.row() < y.row();
    });
    t.erase(std::unique(t.begin(), t.end(),
                        [](const auto& x, const auto& y) {
                          return x.col() == y.col() && x.row() == y.row();
                        }),
            t.end());
    cholmod_sparse* s = cholmod_allocate_sparse(n, n, t.size(), 1, 1, 1, CHOLMOD_REAL, &common);
    int* p = static_cast<int*>(s->p);
    int* i = static_cast<int*>(s->i);
    double* x = static_cast<double*>(s->x);
    std::fill(p, p + n + 1, 0);
    for (std::size_t k = 0; k < t.size(); ++k) {
      ++p[t[k].col() + 1];
      i[k] = t[k].row();
      x[k] = t[k].value();
    }
    for (int c = 0; c < n; ++c)
      p[c + 1] += p[c];
    return s;
  }

  /// Numeric refactorisation of the current A with the rows/columns `del` replaced by identity.
  bool refactor(const std::vector<char>& del, std::string& error) {
    const double* av = a->valuePtr();
    double* x = static_cast<double*>(a_chol->x);
    for (std::size_t k = 0; k < base.size(); ++k) {
      base[k] = av[full_entry_of_pos[k]];
      const int r = entry_row_red[k], c = entry_col_red[k];
      x[k] = (del[r] || del[c]) ? (r == c ? 1.0 : 0.0) : base[k];
    }
    deleted = del;
    for (int r : pending_list)
      pending[r] = 0;
    pending_list.clear();
    if (l)
      cholmod_free_factor(&l, &common);
    l = cholmod_copy_factor(l_symbolic, &common);
    const int ok = cholmod_factorize(a_chol, l, &common);
    modifications = 0;
    if (!ok || common.status != CHOLMOD_OK || static_cast<int>(l->minor) != n_red) {
      error =
          "ConstrainedSolver: the system matrix is not positive definite on the free DOFs (pivot " +
          std::to_string(l->minor) + ")";
      dirty = true;
      return false;
    }
    dirty = false;
    return true;
  }

  /// Entries of the simplicial factor (column counts, diagonal included).
  long factorEntries() const {
    const int* nz = static_cast<const int*>(l->nz);
    long entries = 0;
    for (int j = 0; j < n_red; ++j)
      entries += nz[j];
    return entries;
  }

  /// Current A column `rc` (reduced) restricted to non-deleted rows, as an n_red x 1 sparse.
  cholmod_sparse* currentColumn(int rc) {
    const int col = full_of_red[rc];
    std::vector<std::pair<int, double>> entries;
    for (Eigen::SparseMatrix<double>::InnerIterator it(*a, col); it; ++it) {
      const int rr = red_of_full[it.row()];
      if (rr >= 0 && (!deleted[rr] || rr == rc))
        entries.emplace_back(rr, it.value());
    }
    std::sort(entries.begin(), entries.end());
    cholmod_sparse* r =
        cholmod_allocate_sparse(n_red, 1, entries.size(), 1, 1, 0, CHOLMOD_REAL, &common);
    int* p = static_cast<int*>(r->p);
    int* i = static_cast<int*>(r->i);
    double* x = static_cast<double*>(r->x);
    p[0] = 0;
    p[1] = static_cast<int>(entries.size());
    for (std::size_t k = 0; k < entries.size(); ++k) {
      i[k] = entries[k].first;
      x[k] = entries[k].second;
    }
    return r;
  }

  /// Syncs base with A for the entries of reduced column/row rc.
  void syncBase(int rc) {
    const double* av = a->valuePtr();
    const int col = full_of_red[rc];
    const int* outer = a->outerIndexPtr();
    for (int idx = outer[col]; idx < outer[col + 1]; ++idx) {
      const int pos = entry_pos[idx];
      if (pos >= 0)
        base[pos] = av[idx];
      // the symmetric entry (rr > rc) is stored in column rr's upper part
      const int rr = red_of_full[a->innerIndexPtr()[idx]];
      if (rr > rc) {
        const int* ap = static_cast<const int*>(a_chol->p);
        const int* ai = static_cast<const int*>(a_chol->i);
        const int* it = std::lower_bound(ai + ap[rr], ai + ap[rr + 1], rc);
        base[it - ai] = av[idx];
      }
    }
  }

  /// Applies the pending model changes on non-deleted rows as a low-rank update/downdate.
  bool applyPending(SolverStats& stats) {
    std::vector<int> d;
    for (int r : pending_list) {
      if (!deleted[r])
        d.push_back(r);
    }
    std::sort(d.begin(), d.end());
    const int nd = static_cast<int>(d.size());
    if (nd > 0) {
      std::vector<int> local(n_red, -1);
      for (int k = 0; k < nd; ++k)
        local[d[k]] = k;
      Eigen::MatrixXd delta = Eigen::MatrixXd::Zero(nd, nd);
      const int* ap = static_cast<const int*>(a_chol->p);
      const int* ai = static_cast<const int*>(a_chol->i);
      const double* av = a->valuePtr();
      for (int k = 0; k < nd; ++k) {
        const int c = d[k];
        for (int pos = ap[c]; pos < ap[c + 1]; ++pos) {
          const int lr = local[ai[pos]];
          if (lr < 0)
            continue;
          const double now = av[full_entry_of_pos[pos]];
          const double change = now - base[pos];
          delta(lr, k) = change;
          delta(k, lr) = change;
          base[pos] = now;
        }
      }
      Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(delta);
      const Eigen::VectorXd& lambda = eig.eigenvalues();
      const double lambda_max = lambda.cwiseAbs().maxCoeff();
      for (int sign : {+1, -1}) {
        std::vector<int> cols;
        for (int k = 0; k < nd; ++k) {
          if (sign * lambda(k) > kDeltaEigenRelTol * lambda_max && lambda_max > 0.0)
            cols.push_back(k);
        }
        if (cols.empty())
          continue;
        cholmod_sparse* c = cholmod_allocate_sparse(n_red, cols.size(), cols.size() * nd, 1, 1, 0,
                                                    CHOLMOD_REAL, &common);
        int* cp = static_cast<int*>(c->p);
        int* ci = static_cast<int*>(c->i);
        double* cx = static_cast<double*>(c->x);
        for (std::size_t j = 0; j < cols.size(); ++j) {
          cp[j] = static_cast<int>(j) * nd;
          const double s = std::sqrt(std::abs(lambda(cols[j])));
          for (int k = 0; k < nd; ++k) {
            ci[j * nd + k] = d[k];
            cx[j * nd + k] = s * eig.eigenvectors()(k, cols[j]);
          }
        }
        cp[cols.size()] = static_cast<int>(cols.size()) * nd;
        const int ok = cholmod_updown(sign > 0 ? 1 : 0, c, l, &common);
        cholmod_free_sparse(&c, &common);
        stats.rank_updates += static_cast<long>(cols.size());
        modifications += static_cast<long>(cols.size());
        if (!ok || common.status != CHOLMOD_OK)
          return false;
      }
    }
    for (int r : pending_list) {
      if (!deleted[r])
        pending[r] = 0;
    }
    pending_list.erase(std::remove_if(pending_list.begin(), pending_list.end(),
                                      [&](int r) { return !pending[r]; }),
                       pending_list.end());
    return true;
  }
};

ConstrainedSolver::ConstrainedSolver(const Eigen::SparseMatrix<double>& a,
                                     std::vector<int> fixed_dofs, bool incremental)
    : impl_(std::make_unique<Impl>()) {
  impl_->a = &a;
  impl_->incremental = incremental;
  impl_->setup(fixed_dofs);
}

ConstrainedSolver::~ConstrainedSolver() = default;

std::unique_ptr<ConstrainedSolver> ConstrainedSolver::clone(
    const Eigen::SparseMatrix<double>& a) const {
  if (a.rows() != impl_->n_full ||
      a.nonZeros() != static_cast<Eigen::Index>(impl_->entry_pos.size())) {
    throw std::invalid_argument(
        "ConstrainedSolver::clone: the matrix is not a copy of the solver's");
  }
  std::unique_ptr<ConstrainedSolver> copy(new ConstrainedSolver());
  copy->impl_ = std::make_unique<Impl>();
  copy->impl_->a = &a;
  copy->impl_->copyFrom(*impl_);
  copy->stats_ = stats_;
  return copy;
}

void ConstrainedSolver::matrixReplaced() {
  impl_->dirty = true;
}

void ConstrainedSolver::matrixChanged(const std::vector<int>& dofs) {
  Impl& im = *impl_;
  if (!im.incremental) {
    im.dirty = true;
    return;
  }
  for (int d : dofs) {
    const int r = im.red_of_full[d];
    if (r >= 0 && !im.pending[r]) {
      im.pending[r] = 1;
      im.pending_list.push_back(r);
    }
  }
}

bool ConstrainedSolver::solve(const Eigen::VectorXd& b, const std::vector<int>& p_dofs,
                              const std::vector<double>& p_values, Eigen::VectorXd& x,
                              Eigen::VectorXd& reactions, std::string& error) {
  Impl& im = *impl_;
  const Eigen::SparseMatrix<double>& a = *im.a;
  std::vector<char> del(im.n_red, 0);
  for (int d : p_dofs) {
    const int r = im.red_of_full[d];
    if (r >= 0)
      del[r] = 1;
  }
  bool need_refactor = im.dirty || !im.l || !im.incremental;
  std::vector<int> to_delete, to_add;
  if (!need_refactor) {
    for (int d : p_dofs) {
      const int r = im.red_of_full[d];
      if (r >= 0 && !im.deleted[r])
        to_delete.push_back(r);
    }
    for (int r = 0; r < im.n_red; ++r) {
      if (im.deleted[r] && !del[r])
        to_add.push_back(r);
    }
    const long planned =
        static_cast<long>(to_delete.size() + to_add.size() + im.pending_list.size());
    need_refactor = im.modifications + planned > kMaxModifications;
  }
  if (!need_refactor) {
    // Delete newly prescribed rows, apply model changes on the rest, add released rows back.
    bool ok = true;
    for (int r : to_delete) {
      ok = ok && cholmod_rowdel(r, nullptr, im.l, &im.common) && im.common.status == CHOLMOD_OK;
      im.deleted[r] = 1;
      ++stats_.row_deletions;
      ++im.modifications;
    }
    ok = ok && im.applyPending(stats_);
    std::sort(to_add.begin(), to_add.end());
    for (int r : to_add) {
      if (!ok)
        break;
      im.deleted[r] = 0;
      cholmod_sparse* col = im.currentColumn(r);
      ok = cholmod_rowadd(r, col, im.l, &im.common) && im.common.status == CHOLMOD_OK;
      cholmod_free_sparse(&col, &im.common);
      im.syncBase(r);
      if (im.pending[r]) {
        im.pending[r] = 0;
        im.pending_list.erase(std::find(im.pending_list.begin(), im.pending_list.end(), r));
      }
      ++stats_.row_additions;
      ++im.modifications;
    }
    if (!ok)
      need_refactor = true;  // a modification failed (e.g. lost definiteness): start over
  }
  if (need_refactor) {
    ++stats_.factorizations;
    if (!im.refactor(del, error))
      return false;
    stats_.factor_entries = im.factorEntries();
  }
  // x_P = g, x_F = 0; rhs = b - A_{:,P} g on the free rows, g on the deleted (identity) rows.
  x = Eigen::VectorXd::Zero(im.n_full);
  for (std::size_t i = 0; i < p_dofs.size(); ++i)
    x(p_dofs[i]) = p_values[i];
  double* rhs = static_cast<double*>(im.b_dense->x);
  for (int r = 0; r < im.n_red; ++r)
    rhs[r] = b(im.full_of_red[r]);
  for (std::size_t i = 0; i < p_dofs.size(); ++i) {
    const double g = p_values[i];
    if (g == 0.0)
      continue;
    for (Eigen::SparseMatrix<double>::InnerIterator it(a, p_dofs[i]); it; ++it) {
      const int rr = im.red_of_full[it.row()];
      if (rr >= 0)
        rhs[rr] -= it.value() * g;
    }
  }
  for (std::size_t i = 0; i < p_dofs.size(); ++i) {
    const int r = im.red_of_full[p_dofs[i]];
    if (r >= 0)
      rhs[r] = p_values[i];
  }
  if (!cholmod_solve2(CHOLMOD_A, im.l, im.b_dense, nullptr, &im.x_dense, nullptr, &im.y_work,
                      &im.e_work, &im.common)) {
    error = "ConstrainedSolver: CHOLMOD solve failed";
    return false;
  }
  ++stats_.solves;
  const double* xs = static_cast<const double*>(im.x_dense->x);
  for (int r = 0; r < im.n_red; ++r) {
    if (!im.deleted[r])
      x(im.full_of_red[r]) = xs[r];
  }
  reactions.resize(static_cast<Eigen::Index>(p_dofs.size()));
  for (std::size_t i = 0; i < p_dofs.size(); ++i) {
    const int d = p_dofs[i];
    double r = -b(d);
    for (Eigen::SparseMatrix<double>::InnerIterator it(a, d); it; ++it)
      r += it.value() * x(it.row());  // symmetric
    reactions(static_cast<Eigen::Index>(i)) = r;
  }
  if (!x.allFinite() || !reactions.allFinite()) {
    error = "ConstrainedSolver: the solve produced a non-finite value";
    return false;
  }
  return true;
}

}  // namespace needle_guidance::tissue
