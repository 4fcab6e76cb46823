// Explicit central-difference integrator, Newmark beta = 0, gamma = 1/2 with the lumped mass
// (dissertation 2.2.2):
//   u_{i+1} = u_i + h v_i + h^2/2 a_i
//   (M_L + h/2 C_L) a_{i+1} = f_{i+1} - K u_{i+1} - C (v_i + h/2 a_i)
//   v_{i+1} = v_i + h/2 (a_i + a_{i+1})
// C_L is the row-sum lumping of C (= alpha M_L: the stiffness-proportional part has zero row
// sums); the rest of C acts through the predicted velocity. The step is refused above
// explicit_safety * stableTimeStep().
#include <algorithm>
#include <cmath>
#include <sstream>

#include "integrator_impl.h"

namespace needle_guidance::tissue::detail {
namespace {

class ExplicitIntegrator : public Integrator {
public:
  ExplicitIntegrator(const FemModel& model, std::vector<int> fixed_dofs,
                     const IntegratorOptions& options)
      : Integrator(model, std::move(fixed_dofs)),
        options_(options),
        fixed_mark_(fixedMark(model.dofCount(), fixed_dofs_)) {}

  IntegratorKind kind() const override { return IntegratorKind::kExplicit; }

  double stableTimeStep() const override {
    if (!(stable_dt_s_ > 0.0))
      stable_dt_s_ = computeStableTimeStep();
    return stable_dt_s_;
  }

  StepStatus step(double dt_s, const Eigen::VectorXd& f_ext, const Prescribed& prescribed,
                  Eigen::VectorXd& reactions) override {
    StepStatus status = checkStepInput(model_, fixed_mark_, dt_s, true, f_ext, prescribed);
    if (!status)
      return status;
    const double limit_s = options_.explicit_safety * stableTimeStep();
    if (dt_s > limit_s) {
      std::ostringstream msg;
      msg.precision(6);
      msg << "ExplicitIntegrator: time step dt = " << dt_s << " s exceeds the stability limit "
          << limit_s << " s (explicit_safety " << options_.explicit_safety << " x stableTimeStep "
          << stableTimeStep() << " s); step refused, state unchanged";
      status.ok = false;
      status.message = msg.str();
      return status;
    }
    const double h = dt_s;
    const int n = model_.dofCount();
    Eigen::VectorXd u_new = u_ + h * v_ + 0.5 * h * h * a_;
    for (int d : fixed_dofs_)
      u_new(d) = 0.0;
    for (std::size_t i = 0; i < prescribed.dofs.size(); ++i)
      u_new(prescribed.dofs[i]) = prescribed.values[i];
    const Eigen::VectorXd v_pred = v_ + 0.5 * h * a_;
    const Eigen::VectorXd f_int = options_.corotational
                                      ? model_.corotationalForce(u_new)
                                      : Eigen::VectorXd(model_.stiffness() * u_new);
    const Eigen::VectorXd f_damp = model_.damping() * v_pred;
    const Eigen::VectorXd& m_l = model_.lumpedMass();
    const Eigen::VectorXd c_l = model_.damping() * Eigen::VectorXd::Ones(n);
    Eigen::VectorXd lhs = m_l + 0.5 * h * c_l;
    Eigen::VectorXd a_new = (f_ext - f_int - f_damp).cwiseQuotient(lhs);
    Eigen::VectorXd v_new = v_pred + 0.5 * h * a_new;
    for (int d : fixed_dofs_)
      a_new(d) = v_new(d) = 0.0;
    // Prescribed DOFs follow the prescribed path: backward-difference velocity and acceleration.
    Eigen::VectorXd r(static_cast<Eigen::Index>(prescribed.dofs.size()));
    for (std::size_t i = 0; i < prescribed.dofs.size(); ++i) {
      const int d = prescribed.dofs[i];
      v_new(d) = (prescribed.values[i] - u_(d)) / h;
      a_new(d) = (v_new(d) - v_(d)) / h;
      r(static_cast<Eigen::Index>(i)) = lhs(d) * a_new(d) + f_damp(d) + f_int(d) - f_ext(d);
    }
    if (!u_new.allFinite() || !v_new.allFinite() || !a_new.allFinite()) {
      status.ok = false;
      status.message = "ExplicitIntegrator: the step produced a non-finite value; state unchanged";
      return status;
    }
    u_.swap(u_new);
    v_.swap(v_new);
    a_.swap(a_new);
    reactions = r;
    return status;
  }

  void modelChanged(const std::vector<int>& /*dofs*/) override { stable_dt_s_ = 0.0; }

protected:
  double strainEnergy() const override {
    return options_.corotational ? model_.corotationalStrainEnergy(u_) : Integrator::strainEnergy();
  }
  double kineticEnergy() const override {
    return 0.5 * v_.dot(model_.lumpedMass().cwiseProduct(v_));
  }

private:
  /// Critical step of central differences with stiffness-proportional damping,
  /// dt = 2/w (sqrt(1 + xi^2) - xi), xi = beta w / 2 (Belytschko et al., Nonlinear Finite
  /// Elements, 6.2), with w_max bounded from above by Gershgorin's theorem on
  /// M_L^-1/2 K M_L^-1/2 over the non-fixed DOFs (removing rows/columns only lowers w_max, so
  /// the bound also holds for any prescribed set). Rotations do not change element eigenvalues,
  /// so the bound is used for the corotational option as well.
  double computeStableTimeStep() const {
    const SparseMatrix& k = model_.stiffness();
    const Eigen::VectorXd& m = model_.lumpedMass();
    double lambda_max = 0.0;
    for (int col = 0; col < k.outerSize(); ++col) {
      if (fixed_mark_[col])
        continue;
      double row_sum = 0.0;
      for (SparseMatrix::InnerIterator it(k, col); it; ++it) {
        if (!fixed_mark_[it.row()])
          row_sum += std::abs(it.value()) / std::sqrt(m(it.row()) * m(col));
      }
      lambda_max = std::max(lambda_max, row_sum);
    }
    if (!(lambda_max > 0.0))
      return std::numeric_limits<double>::infinity();
    double beta_max_s = 0.0;
    for (const ElementMaterial& mat : model_.materials())
      beta_max_s = std::max(beta_max_s, mat.rayleigh_beta_s);
    const double omega = std::sqrt(lambda_max);
    const double xi = 0.5 * beta_max_s * omega;
    return 2.0 / omega * (std::sqrt(1.0 + xi * xi) - xi);
  }

  IntegratorOptions options_;
  std::vector<char> fixed_mark_;
  mutable double stable_dt_s_ = 0.0;  ///< cached; 0 = recompute
};

}  // namespace

std::unique_ptr<Integrator> makeExplicit(const FemModel& model, std::vector<int> fixed_dofs,
                                         const IntegratorOptions& options) {
  return std::make_unique<ExplicitIntegrator>(model, std::move(fixed_dofs), options);
}

}  // namespace needle_guidance::tissue::detail
