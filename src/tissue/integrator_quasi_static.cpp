// Quasi-static integrator: K u = f each step (dissertation 2.2.2, "Linear Quasi-static
// Formulation"), with the needle's prescribed displacements (2.3.3-2.3.5).
#include <cmath>

#include "constrained_solver.h"
#include "integrator_impl.h"

namespace needle_guidance::tissue::detail {
namespace {

class QuasiStaticIntegrator : public Integrator {
public:
  QuasiStaticIntegrator(const FemModel& model, std::vector<int> fixed_dofs,
                        const IntegratorOptions& options)
      : Integrator(model, std::move(fixed_dofs)),
        options_(options),
        fixed_mark_(fixedMark(model.dofCount(), fixed_dofs_)) {
    if (options_.corotational) {
      K_R_ = model.stiffness();
      C_R_ = model.damping();
      solver_ = std::make_unique<ConstrainedSolver>(K_R_, fixed_dofs_, false);
    } else {
      // K is updated in place by FemModel::moveNode; modelChanged tells the solver which DOFs.
      solver_ = std::make_unique<ConstrainedSolver>(model.stiffness(), fixed_dofs_, true);
    }
  }

  IntegratorKind kind() const override { return IntegratorKind::kQuasiStatic; }

  std::unique_ptr<Integrator> clone(const FemModel& model) const override {
    std::unique_ptr<QuasiStaticIntegrator> copy(new QuasiStaticIntegrator(model, *this));
    return copy;
  }

  StepStatus step(double dt_s, const Eigen::VectorXd& f_ext, const Prescribed& prescribed,
                  Eigen::VectorXd& reactions) override {
    StepStatus status = checkStepInput(model_, fixed_mark_, dt_s, false, f_ext, prescribed);
    if (!status)
      return status;
    Eigen::VectorXd u_new, r;
    if (!options_.corotational) {
      if (!solver_->solve(f_ext, prescribed.dofs, prescribed.values, u_new, r, status.message)) {
        status.ok = false;
        return status;
      }
    } else {
      // Corotational equilibrium f_int(u) = f by fixed-point iteration on the warped stiffness:
      // K_R(u_k) u_{k+1} = f + f0(u_k) (Mueller et al. 2002).
      u_new = u_;
      Eigen::VectorXd f0, u_next;
      bool converged = false;
      for (int it = 0; it < kCorotationalMaxIterations && !converged; ++it) {
        model_.assembleCorotational(u_new, K_R_, C_R_, f0);
        solver_->matrixReplaced();
        if (!solver_->solve(f_ext + f0, prescribed.dofs, prescribed.values, u_next, r,
                            status.message)) {
          status.ok = false;
          return status;
        }
        const double change = (u_next - u_new).lpNorm<Eigen::Infinity>();
        converged = change <= kCorotationalRelTol * u_next.lpNorm<Eigen::Infinity>() + 1e-15;
        u_new = u_next;
      }
      // Reactions from the corotational force at the final state: r = f_int(u) - f on P.
      const Eigen::VectorXd f_int = model_.corotationalForce(u_new);
      r.resize(static_cast<Eigen::Index>(prescribed.dofs.size()));
      for (std::size_t i = 0; i < prescribed.dofs.size(); ++i) {
        r(static_cast<Eigen::Index>(i)) = f_int(prescribed.dofs[i]) - f_ext(prescribed.dofs[i]);
      }
      if (!converged) {
        status.ok = false;
        status.message = "QuasiStaticIntegrator: corotational iterations did not converge in " +
                         std::to_string(kCorotationalMaxIterations) +
                         " iterations; state unchanged";
        return status;
      }
    }
    if (!u_new.allFinite() || !r.allFinite()) {
      status.ok = false;
      status.message =
          "QuasiStaticIntegrator: the solve produced a non-finite value; state unchanged";
      return status;
    }
    u_ = u_new;
    v_.setZero();
    a_.setZero();
    reactions = r;
    return status;
  }

  SolverCounters solverCounters() const override { return solverCountersOf(solver_->stats()); }

  void modelChanged(const std::vector<int>& dofs) override {
    if (!options_.corotational)
      solver_->matrixChanged(dofs);
  }

protected:
  double strainEnergy() const override {
    return options_.corotational ? model_.corotationalStrainEnergy(u_) : Integrator::strainEnergy();
  }

private:
  /// The copy of `other` for `model` (a copy of other's model).
  QuasiStaticIntegrator(const FemModel& model, const QuasiStaticIntegrator& other)
      : Integrator(model, other.fixed_dofs_),
        options_(other.options_),
        fixed_mark_(other.fixed_mark_),
        K_R_(other.K_R_),
        C_R_(other.C_R_),
        solver_(other.solver_->clone(options_.corotational ? K_R_ : model.stiffness())) {
    u_ = other.u_;
    v_ = other.v_;
    a_ = other.a_;
  }

  IntegratorOptions options_;
  std::vector<char> fixed_mark_;
  SparseMatrix K_R_, C_R_;
  std::unique_ptr<ConstrainedSolver> solver_;
};

}  // namespace

std::unique_ptr<Integrator> makeQuasiStatic(const FemModel& model, std::vector<int> fixed_dofs,
                                            const IntegratorOptions& options) {
  return std::make_unique<QuasiStaticIntegrator>(model, std::move(fixed_dofs), options);
}

}  // namespace needle_guidance::tissue::detail
