// Condensed compliance on the needle DOFs (condensed_compliance.h).
#include "needle_guidance/fem/condensed_compliance.h"

#include <Eigen/CholmodSupport>
#include <algorithm>
#include <mutex>
#include <stdexcept>
#include <string>

#include "needle_guidance/cpu_time.h"

namespace needle_guidance::fem {

// Single-precision routines of the BLAS that CHOLMOD links (OpenBLAS), Fortran interface.
extern "C" {
void sgemv_(const char* trans, const int* m, const int* n, const float* alpha, const float* a,
            const int* lda, const float* x, const int* incx, const float* beta, float* y,
            const int* incy);
void strsv_(const char* uplo, const char* trans, const char* diag, const int* n, const float* a,
            const int* lda, float* x, const int* incx);
}

namespace {

/// CHOLMOD's supernodal LL^T with its factor readable (its supernodes, for the
/// single-precision solve).
class SupernodalLLT : public Eigen::CholmodSupernodalLLT<SparseMatrix, Eigen::Lower> {
public:
  const cholmod_factor& factor() const { return *this->m_cholmodFactor; }
};

}  // namespace

struct CondensedCompliance::Impl {
  SupernodalLLT llt;
  /// The factor's values in single precision, in CHOLMOD's supernodal layout (formed by the
  /// first solveSinglePrecision after a factorisation).
  std::vector<float> single_factor;
  std::size_t factor_bytes = 0;
  /// Guards the column cache and CHOLMOD's workspace: copies of a needle share one compliance.
  std::mutex mutex;
};

CondensedCompliance::CondensedCompliance(const SparseMatrix& k, const std::vector<char>& fixed_dof)
    : impl_(std::make_unique<Impl>()), fixed_(fixed_dof) {
  const int n = static_cast<int>(fixed_.size());
  free_index_.assign(static_cast<std::size_t>(n), -1);
  for (int i = 0; i < n; ++i) {
    if (!fixed_[static_cast<std::size_t>(i)]) {
      free_index_[static_cast<std::size_t>(i)] = static_cast<int>(free_dofs_.size());
      free_dofs_.push_back(i);
    }
  }
  if (free_dofs_.empty()) {
    throw std::invalid_argument("CondensedCompliance: every DOF is fixed");
  }
  if (static_cast<int>(free_dofs_.size()) == n) {
    throw std::invalid_argument(
        "CondensedCompliance: no DOF is fixed: the body is free to move rigidly (K singular)");
  }
  const SparseMatrix kff = freeBlock(k);
  const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
  // Fill-reducing ordering: CHOLMOD tries AMD and METIS's nested dissection and keeps the
  // sparser factor. On tetrahedral meshes that is METIS's (13 % fewer entries and a third fewer
  // flops at 18.6k tetrahedra); a solve reads the whole factor twice, so it runs faster in
  // proportion (docs/tissue_3d.md, "Cost of one update").
  cholmod_common& common = impl_->llt.cholmod();
  common.nmethods = 2;
  common.method[0].ordering = CHOLMOD_AMD;
  common.method[1].ordering = CHOLMOD_METIS;
  impl_->llt.compute(kff);
  factor_cpu_s_ = clock.seconds();
  if (impl_->llt.info() != Eigen::Success) {
    throw std::invalid_argument(
        "CondensedCompliance: the free-DOF stiffness (" + std::to_string(kff.rows()) +
        " DOFs) is not positive definite: too few fixed DOFs to hold the tissue, or a "
        "degenerate element");
  }
  impl_->factor_bytes = impl_->llt.cholmod().memory_inuse;  // CHOLMOD's own accounting
  factor_entries_ = common.lnz;
  columns_.resize(static_cast<std::size_t>(n));
  field_columns_.resize(static_cast<std::size_t>(n));
}

CondensedCompliance::~CondensedCompliance() = default;

SparseMatrix CondensedCompliance::freeBlock(const SparseMatrix& k) const {
  const int n = dofCount();
  if (k.rows() != n || k.cols() != n) {
    throw std::invalid_argument("CondensedCompliance: stiffness is " + std::to_string(k.rows()) +
                                " x " + std::to_string(k.cols()) + " for " + std::to_string(n) +
                                " DOFs");
  }
  const int m = static_cast<int>(free_dofs_.size());
  std::vector<Eigen::Triplet<double>> t;
  t.reserve(static_cast<std::size_t>(k.nonZeros()));
  for (int col = 0; col < n; ++col) {
    const int fc = free_index_[static_cast<std::size_t>(col)];
    if (fc < 0) {
      continue;
    }
    for (SparseMatrix::InnerIterator it(k, col); it; ++it) {
      const int fr = free_index_[static_cast<std::size_t>(it.row())];
      if (fr >= fc) {
        t.emplace_back(fr, fc, it.value());
      }
    }
  }
  SparseMatrix kff(m, m);
  kff.setFromTriplets(t.begin(), t.end());
  return kff;
}

void CondensedCompliance::refactor(const SparseMatrix& k) {
  const SparseMatrix kff = freeBlock(k);
  const std::lock_guard<std::mutex> lock(impl_->mutex);
  const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
  impl_->llt.factorize(kff);
  impl_->single_factor.clear();
  refactor_cpu_s_ += clock.seconds();
  ++refactors_;
  for (Eigen::VectorXd& c : columns_) {
    c.resize(0);
  }
  for (Eigen::VectorXf& c : field_columns_) {
    c.resize(0);
  }
  cached_ = 0;
  if (impl_->llt.info() != Eigen::Success) {
    throw std::invalid_argument("CondensedCompliance: the refactored stiffness (" +
                                std::to_string(kff.rows()) +
                                " free DOFs) is not positive definite");
  }
}

void CondensedCompliance::require(const std::vector<int>& dofs) {
  const std::lock_guard<std::mutex> lock(impl_->mutex);
  std::vector<int> todo;
  for (int d : dofs) {
    if (d < 0 || d >= dofCount()) {
      throw std::out_of_range("CondensedCompliance: DOF " + std::to_string(d) + " out of range");
    }
    if (columns_[static_cast<std::size_t>(d)].size() == 0 &&
        std::find(todo.begin(), todo.end(), d) == todo.end()) {
      todo.push_back(d);
    }
  }
  if (todo.empty()) {
    return;
  }
  // Batches of columns: the supernodal solve runs on blocks of right-hand sides (BLAS 3),
  // bounded so the dense right-hand side stays small.
  constexpr std::size_t kBatch = 96;
  const int m = static_cast<int>(free_dofs_.size());
  for (std::size_t first = 0; first < todo.size(); first += kBatch) {
    const std::size_t count = std::min(kBatch, todo.size() - first);
    Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(m, static_cast<int>(count));
    for (std::size_t c = 0; c < count; ++c) {
      const int fr = free_index_[static_cast<std::size_t>(todo[first + c])];
      if (fr >= 0) {
        rhs(fr, static_cast<int>(c)) = 1.0;
      }
    }
    const Eigen::MatrixXd x = impl_->llt.solve(rhs);
    for (std::size_t c = 0; c < count; ++c) {
      const int dof = todo[first + c];
      Eigen::VectorXd col = Eigen::VectorXd::Zero(dofCount());
      if (free_index_[static_cast<std::size_t>(dof)] >= 0) {
        for (int r = 0; r < m; ++r) {
          col(free_dofs_[static_cast<std::size_t>(r)]) = x(r, static_cast<int>(c));
        }
        ++solved_;
      }
      field_columns_[static_cast<std::size_t>(dof)] = col.cast<float>();
      columns_[static_cast<std::size_t>(dof)] = std::move(col);
      ++cached_;
    }
  }
}

const Eigen::VectorXd& CondensedCompliance::column(int dof) const {
  const Eigen::VectorXd& c = columns_.at(static_cast<std::size_t>(dof));
  if (c.size() == 0) {
    throw std::logic_error("CondensedCompliance: column of DOF " + std::to_string(dof) +
                           " was not required");
  }
  return c;
}

double CondensedCompliance::entry(int i, int j) const {
  return column(j)(i);
}

Eigen::VectorXd CondensedCompliance::solve(const Eigen::VectorXd& force_N) const {
  if (force_N.size() != dofCount()) {
    throw std::invalid_argument("CondensedCompliance::solve: force has " +
                                std::to_string(force_N.size()) + " entries for " +
                                std::to_string(dofCount()) + " DOFs");
  }
  const std::lock_guard<std::mutex> lock(impl_->mutex);
  const int m = static_cast<int>(free_dofs_.size());
  Eigen::VectorXd b(m);
  for (int r = 0; r < m; ++r) {
    b(r) = force_N(free_dofs_[static_cast<std::size_t>(r)]);
  }
  const Eigen::VectorXd x = impl_->llt.solve(b);
  Eigen::VectorXd u = Eigen::VectorXd::Zero(dofCount());
  for (int r = 0; r < m; ++r) {
    u(free_dofs_[static_cast<std::size_t>(r)]) = x(r);
  }
  return u;
}

Eigen::VectorXd CondensedCompliance::solveSinglePrecision(const Eigen::VectorXd& force_N) const {
  const cholmod_factor& l = impl_->llt.factor();
  if (!l.is_super || !l.is_ll || l.itype != CHOLMOD_INT || l.xtype != CHOLMOD_REAL) {
    return solve(force_N);  // not a supernodal LL^T of int indices: the double solve
  }
  if (force_N.size() != dofCount()) {
    return solve(force_N);  // which refuses it
  }
  const std::lock_guard<std::mutex> lock(impl_->mutex);
  // CHOLMOD's supernodal layout (Chen, Davis, Hager and Rajamanickam 2008): supernode k holds
  // columns super[k] .. super[k+1] - 1 of L as a dense column-major block of the rows
  // s[pi[k]] .. s[pi[k+1] - 1] (its own columns first), stored from x[px[k]]. P A P^T = L L^T.
  const int nsuper = static_cast<int>(l.nsuper);
  const int* super = static_cast<const int*>(l.super);
  const int* pi = static_cast<const int*>(l.pi);
  const int* px = static_cast<const int*>(l.px);
  const int* rows = static_cast<const int*>(l.s);
  const int* perm = static_cast<const int*>(l.Perm);
  if (impl_->single_factor.empty()) {
    const double* x = static_cast<const double*>(l.x);
    impl_->single_factor.assign(x, x + px[nsuper]);
  }
  const float* values = impl_->single_factor.data();
  const int m = static_cast<int>(free_dofs_.size());
  auto dof = [&](int i) { return free_dofs_[static_cast<std::size_t>(perm ? perm[i] : i)]; };
  std::vector<float> y(static_cast<std::size_t>(m));
  for (int i = 0; i < m; ++i) {
    y[static_cast<std::size_t>(i)] = static_cast<float>(force_N(dof(i)));
  }
  std::vector<float> below(static_cast<std::size_t>(m));  // a supernode's rows below its columns
  const int one = 1;
  const float plus = 1.0f;
  const float zero = 0.0f;
  const float minus = -1.0f;
  // L y = P f, supernode by supernode: the diagonal block's triangle, then its rows below.
  for (int k = 0; k < nsuper; ++k) {
    const int columns = super[k + 1] - super[k];
    const int height = pi[k + 1] - pi[k];
    const int under = height - columns;
    const float* block = values + px[k];
    float* yk = y.data() + super[k];
    strsv_("L", "N", "N", &columns, block, &height, yk, &one);
    if (under > 0) {
      sgemv_("N", &under, &columns, &plus, block + columns, &height, yk, &one, &zero, below.data(),
             &one);
      const int* r = rows + pi[k] + columns;
      for (int i = 0; i < under; ++i) {
        y[static_cast<std::size_t>(r[i])] -= below[static_cast<std::size_t>(i)];
      }
    }
  }
  // L^T x = y, in reverse.
  for (int k = nsuper - 1; k >= 0; --k) {
    const int columns = super[k + 1] - super[k];
    const int height = pi[k + 1] - pi[k];
    const int under = height - columns;
    const float* block = values + px[k];
    float* yk = y.data() + super[k];
    if (under > 0) {
      const int* r = rows + pi[k] + columns;
      for (int i = 0; i < under; ++i) {
        below[static_cast<std::size_t>(i)] = y[static_cast<std::size_t>(r[i])];
      }
      sgemv_("T", &under, &columns, &minus, block + columns, &height, below.data(), &one, &plus, yk,
             &one);
    }
    strsv_("L", "T", "N", &columns, block, &height, yk, &one);
  }
  Eigen::VectorXd u = Eigen::VectorXd::Zero(dofCount());
  for (int i = 0; i < m; ++i) {
    u(dof(i)) = y[static_cast<std::size_t>(i)];
  }
  return u;
}

Eigen::VectorXd CondensedCompliance::solveSupported(const Eigen::VectorXd& force_N,
                                                    const std::vector<int>& support) const {
  const double column_bytes = static_cast<double>(support.size()) * dofCount() * sizeof(float);
  const bool cached = std::all_of(support.begin(), support.end(), [&](int d) {
    return d >= 0 && d < dofCount() && columns_[static_cast<std::size_t>(d)].size() > 0;
  });
  if (force_N.size() != dofCount() || !cached ||
      !(column_bytes < 2.0 * factor_entries_ * sizeof(double))) {
    return solve(force_N);
  }
  Eigen::VectorXd u = Eigen::VectorXd::Zero(dofCount());
  for (int d : support) {
    const double f = force_N(d);
    if (f != 0.0) {
      u.noalias() += f * field_columns_[static_cast<std::size_t>(d)].cast<double>();
    }
  }
  return u;
}

std::size_t CondensedCompliance::factorBytes() const {
  return impl_->factor_bytes;
}

std::size_t CondensedCompliance::memoryBytes() const {
  return impl_->factor_bytes + impl_->single_factor.size() * sizeof(float) +
         static_cast<std::size_t>(cached_) * static_cast<std::size_t>(dofCount()) *
             (sizeof(double) + sizeof(float));
}

void CondensedCompliance::clearCache() {
  for (Eigen::VectorXd& c : columns_) {
    c.resize(0);
  }
  for (Eigen::VectorXf& c : field_columns_) {
    c.resize(0);
  }
  cached_ = 0;
}

}  // namespace needle_guidance::fem
