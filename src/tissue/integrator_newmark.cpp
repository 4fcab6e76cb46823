// Newmark implicit integrator with beta = gamma = 1/2 (dissertation 2.2.2):
//   (M + h/2 C + h^2/4 K) a_{i+1} = f_{i+1} - (h/2 C + h^2/4 K) a_i - (C + h K) v_i - K u_i
//   v_{i+1} = v_i + h/2 (a_i + a_{i+1}),  u_{i+1} = u_i + h v_i + h^2/4 (a_i + a_{i+1}).
// (The dissertation prints h v_{i+1} in the last update; h v_i is the form consistent with its
// system matrix and with the trapezoidal rule, which conserves energy for linear undamped
// systems.) A prescribed displacement g at u_{i+1} becomes the prescribed acceleration
// a_{i+1} = 4/h^2 (g - u_i - h v_i) - a_i.
#include <cmath>

#include "constrained_solver.h"
#include "integrator_impl.h"

namespace needle_guidance::tissue::detail {
namespace {

class NewmarkIntegrator : public Integrator {
public:
  NewmarkIntegrator(const FemModel& model, std::vector<int> fixed_dofs,
                    const IntegratorOptions& options)
      : Integrator(model, std::move(fixed_dofs)),
        options_(options),
        fixed_mark_(fixedMark(model.dofCount(), fixed_dofs_)),
        A_(model.stiffness()) {
    solver_ = std::make_unique<ConstrainedSolver>(A_, fixed_dofs_, !options_.corotational);
  }

  IntegratorKind kind() const override { return IntegratorKind::kNewmark; }

  StepStatus step(double dt_s, const Eigen::VectorXd& f_ext, const Prescribed& prescribed,
                  Eigen::VectorXd& reactions) override {
    StepStatus status = checkStepInput(model_, fixed_mark_, dt_s, true, f_ext, prescribed);
    if (!status)
      return status;
    const double h = dt_s;
    Eigen::VectorXd rhs;
    if (options_.corotational) {
      // Warped stiffness with the rotations of u_i (Mueller et al. 2002): K u -> K_R u - f0.
      Eigen::VectorXd f0;
      model_.assembleCorotational(u_, K_R_, C_R_, f0);
      assembleA(K_R_, C_R_, h);
      solver_->matrixReplaced();
      rhs = f_ext + f0 - C_R_ * (v_ + 0.5 * h * a_) - K_R_ * (u_ + h * v_ + 0.25 * h * h * a_);
    } else {
      if (h != factored_h_s_) {
        assembleA(model_.stiffness(), model_.damping(), h);
        solver_->matrixReplaced();
      }
      rhs = f_ext - model_.damping() * (v_ + 0.5 * h * a_) -
            model_.stiffness() * (u_ + h * v_ + 0.25 * h * h * a_);
    }
    std::vector<double> a_prescribed(prescribed.dofs.size());
    for (std::size_t i = 0; i < prescribed.dofs.size(); ++i) {
      const int d = prescribed.dofs[i];
      a_prescribed[i] = 4.0 / (h * h) * (prescribed.values[i] - u_(d) - h * v_(d)) - a_(d);
    }
    Eigen::VectorXd a_new, r;
    if (!solver_->solve(rhs, prescribed.dofs, a_prescribed, a_new, r, status.message)) {
      status.ok = false;
      status.message += "; state unchanged";
      return status;
    }
    Eigen::VectorXd v_new = v_ + 0.5 * h * (a_ + a_new);
    Eigen::VectorXd u_new = u_ + h * v_ + 0.25 * h * h * (a_ + a_new);
    for (std::size_t i = 0; i < prescribed.dofs.size(); ++i)
      u_new(prescribed.dofs[i]) = prescribed.values[i];
    if (!u_new.allFinite() || !v_new.allFinite()) {
      status.ok = false;
      status.message = "NewmarkIntegrator: the step produced a non-finite value; state unchanged";
      return status;
    }
    u_.swap(u_new);
    v_.swap(v_new);
    a_.swap(a_new);
    reactions = r;
    return status;
  }

  SolverCounters solverCounters() const override { return solverCountersOf(solver_->stats()); }

  void modelChanged(const std::vector<int>& dofs) override {
    if (options_.corotational || !std::isfinite(factored_h_s_))
      return;  // rebuilt at the next step
    // Recompute A = M + h/2 C + h^2/4 K in the changed columns (shared pattern), then tell the
    // solver (low-rank update of its factorisation).
    const double h = factored_h_s_;
    const double* k = model_.stiffness().valuePtr();
    const double* m = model_.mass().valuePtr();
    const double* c = model_.damping().valuePtr();
    double* a = A_.valuePtr();
    const int* outer = A_.outerIndexPtr();
    for (int col : dofs) {
      for (int idx = outer[col]; idx < outer[col + 1]; ++idx)
        a[idx] = m[idx] + 0.5 * h * c[idx] + 0.25 * h * h * k[idx];
    }
    solver_->matrixChanged(dofs);
  }

private:
  void assembleA(const SparseMatrix& k_mat, const SparseMatrix& c_mat, double h) {
    const double* k = k_mat.valuePtr();
    const double* m = model_.mass().valuePtr();
    const double* c = c_mat.valuePtr();
    double* a = A_.valuePtr();
    for (Eigen::Index idx = 0; idx < A_.nonZeros(); ++idx)
      a[idx] = m[idx] + 0.5 * h * c[idx] + 0.25 * h * h * k[idx];
    factored_h_s_ = h;
  }

protected:
  double strainEnergy() const override {
    return options_.corotational ? model_.corotationalStrainEnergy(u_) : Integrator::strainEnergy();
  }

private:
  IntegratorOptions options_;
  std::vector<char> fixed_mark_;
  SparseMatrix A_;          ///< M + h/2 C + h^2/4 K on the model's pattern
  SparseMatrix K_R_, C_R_;  ///< corotational K and C
  double factored_h_s_ = std::numeric_limits<double>::quiet_NaN();
  std::unique_ptr<ConstrainedSolver> solver_;
};

}  // namespace

std::unique_ptr<Integrator> makeNewmark(const FemModel& model, std::vector<int> fixed_dofs,
                                        const IntegratorOptions& options) {
  return std::make_unique<NewmarkIntegrator>(model, std::move(fixed_dofs), options);
}

}  // namespace needle_guidance::tissue::detail
