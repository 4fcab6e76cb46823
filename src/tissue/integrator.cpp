// Time integration of M a + C v + K u = f (dissertation 2.2.2): the Integrator base, input
// checks shared by all integrators, and makeIntegrator.
#include "needle_guidance/tissue/integrator.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "integrator_impl.h"

namespace needle_guidance::tissue {

const char* toString(IntegratorKind kind) {
  switch (kind) {
    case IntegratorKind::kQuasiStatic:
      return "quasi_static";
    case IntegratorKind::kNewmark:
      return "newmark";
    case IntegratorKind::kExplicit:
      return "explicit";
  }
  return "unknown";
}

Integrator::Integrator(const FemModel& model, std::vector<int> fixed_dofs)
    : model_(model), fixed_dofs_(std::move(fixed_dofs)) {
  const int n = model_.dofCount();
  for (int d : fixed_dofs_) {
    if (d < 0 || d >= n) {
      throw std::invalid_argument("makeIntegrator: fixed DOF " + std::to_string(d) +
                                  " out of range [0, " + std::to_string(n) + ")");
    }
  }
  std::sort(fixed_dofs_.begin(), fixed_dofs_.end());
  fixed_dofs_.erase(std::unique(fixed_dofs_.begin(), fixed_dofs_.end()), fixed_dofs_.end());
  u_ = Eigen::VectorXd::Zero(n);
  v_ = Eigen::VectorXd::Zero(n);
  a_ = Eigen::VectorXd::Zero(n);
}

double Integrator::strainEnergy() const {
  return 0.5 * u_.dot(model_.stiffness() * u_);
}

double Integrator::kineticEnergy() const {
  return 0.5 * v_.dot(model_.mass() * v_);
}

double Integrator::energy() const {
  return kineticEnergy() + strainEnergy();
}

void Integrator::reset() {
  u_.setZero();
  v_.setZero();
  a_.setZero();
}

void Integrator::setState(const Eigen::VectorXd& u, const Eigen::VectorXd& v,
                          const Eigen::VectorXd& a) {
  const Eigen::Index n = model_.dofCount();
  if (u.size() != n || v.size() != n || a.size() != n) {
    throw std::invalid_argument("Integrator::setState: sizes " + std::to_string(u.size()) + ", " +
                                std::to_string(v.size()) + ", " + std::to_string(a.size()) +
                                " differ from the " + std::to_string(n) + " DOFs of the model");
  }
  u_ = u;
  v_ = v;
  a_ = a;
}

namespace detail {

StepStatus checkStepInput(const FemModel& model, const std::vector<char>& fixed_mark, double dt_s,
                          bool dynamic, const Eigen::VectorXd& f_ext,
                          const Prescribed& prescribed) {
  const int n = model.dofCount();
  if (f_ext.size() != n) {
    throw std::invalid_argument("Integrator::step: f_ext has size " + std::to_string(f_ext.size()) +
                                ", expected " + std::to_string(n));
  }
  if (prescribed.dofs.size() != prescribed.values.size()) {
    throw std::invalid_argument("Integrator::step: " + std::to_string(prescribed.dofs.size()) +
                                " prescribed DOFs but " + std::to_string(prescribed.values.size()) +
                                " values");
  }
  std::vector<int> sorted = prescribed.dofs;
  std::sort(sorted.begin(), sorted.end());
  for (std::size_t i = 0; i < sorted.size(); ++i) {
    const int d = sorted[i];
    if (d < 0 || d >= n) {
      throw std::invalid_argument("Integrator::step: prescribed DOF " + std::to_string(d) +
                                  " out of range [0, " + std::to_string(n) + ")");
    }
    if (i > 0 && sorted[i - 1] == d) {
      throw std::invalid_argument("Integrator::step: prescribed DOF " + std::to_string(d) +
                                  " given twice");
    }
    if (fixed_mark[d]) {
      throw std::invalid_argument("Integrator::step: prescribed DOF " + std::to_string(d) +
                                  " is a fixed DOF");
    }
  }
  StepStatus status;
  if (!std::isfinite(dt_s) || (dynamic && dt_s <= 0.0)) {
    status.ok = false;
    status.message = "Integrator::step: time step " + std::to_string(dt_s) + " s must be finite" +
                     (dynamic ? std::string(" and > 0") : std::string());
    return status;
  }
  if (!f_ext.allFinite()) {
    status.ok = false;
    status.message = "Integrator::step: f_ext contains a non-finite value; state unchanged";
    return status;
  }
  for (std::size_t i = 0; i < prescribed.values.size(); ++i) {
    if (!std::isfinite(prescribed.values[i])) {
      status.ok = false;
      status.message = "Integrator::step: prescribed value of DOF " +
                       std::to_string(prescribed.dofs[i]) + " is not finite; state unchanged";
      return status;
    }
  }
  return status;
}

}  // namespace detail

std::unique_ptr<Integrator> makeIntegrator(IntegratorKind kind, const FemModel& model,
                                           std::vector<int> fixed_dofs,
                                           const IntegratorOptions& options) {
  if (!(options.explicit_safety > 0.0) || !(options.explicit_safety <= 1.0)) {
    throw std::invalid_argument("makeIntegrator: explicit_safety " +
                                std::to_string(options.explicit_safety) + " must be in (0, 1]");
  }
  switch (kind) {
    case IntegratorKind::kQuasiStatic:
      return detail::makeQuasiStatic(model, std::move(fixed_dofs), options);
    case IntegratorKind::kNewmark:
      return detail::makeNewmark(model, std::move(fixed_dofs), options);
    case IntegratorKind::kExplicit:
      return detail::makeExplicit(model, std::move(fixed_dofs), options);
  }
  throw std::invalid_argument("makeIntegrator: unknown integrator kind");
}

}  // namespace needle_guidance::tissue
