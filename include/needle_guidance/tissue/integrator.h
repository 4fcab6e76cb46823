// Time integration of M a + C v + K u = f (dissertation 2.2.2) behind one interface: quasi-static
// (K u = f), Newmark implicit (beta = gamma = 1/2) and explicit central difference with lumped
// mass. Prescribed displacements (the needle's tip and shaft constraints, 2.3.3–2.3.5) change
// from step to step; the permanent fixed DOFs (fixed boundary, bone) are given once.
#pragma once

#include <Eigen/Core>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "needle_guidance/tissue/fem_model.h"

namespace needle_guidance::tissue {

/// Displacements prescribed for one step: dofs[i] gets values[i] [m]. DOFs are unique and
/// must not be permanent fixed DOFs.
struct Prescribed {
  std::vector<int> dofs;
  std::vector<double> values;
};

/// Outcome of a step. On failure the integrator's state is unchanged.
struct StepStatus {
  bool ok = true;
  std::string message;
  explicit operator bool() const { return ok; }
  const std::string& toString() const { return message; }
};

enum class IntegratorKind { kQuasiStatic, kNewmark, kExplicit };
const char* toString(IntegratorKind kind);

struct IntegratorOptions {
  bool corotational = false;  ///< large-rotation (corotational) elements
  /// Explicit only: refuse steps above safety * stableTimeStep().
  double explicit_safety = 0.9;
};

/// One interface for all integrators. Holds u, v, a for every DOF.
class Integrator {
public:
  virtual ~Integrator() = default;
  virtual IntegratorKind kind() const = 0;

  /// Advances by dt_s (ignored by quasi-static except for bookkeeping) with external nodal
  /// forces f_ext [N] (size dofCount) and the prescribed displacements. Fills `reactions`
  /// (same order as prescribed.dofs) with the force the constraints apply to the tissue [N].
  /// Refuses (status not ok, state unchanged) a non-finite input, dt_s <= 0 for dynamic
  /// integrators, dt_s above the explicit stability limit, or a solve that produced NaN.
  virtual StepStatus step(double dt_s, const Eigen::VectorXd& f_ext, const Prescribed& prescribed,
                          Eigen::VectorXd& reactions) = 0;

  /// The model's matrices changed in these DOFs (after FemModel::moveNode); the integrator
  /// updates or refreshes its factorisation.
  virtual void modelChanged(const std::vector<int>& dofs) = 0;

  /// Largest stable step [s]: infinity for unconditionally stable integrators.
  virtual double stableTimeStep() const { return std::numeric_limits<double>::infinity(); }

  /// Work counters of the linear solver (added by the FEM core; zeros for explicit).
  struct SolverCounters {
    long factorizations = 0;  ///< full numeric factorisations
    long row_deletions = 0;   ///< prescribed DOFs deleted from the factor
    long row_additions = 0;   ///< released DOFs added back to the factor
    long rank_updates = 0;    ///< rank-1 updates/downdates for model changes
    long solves = 0;          ///< triangular solves
    long factor_entries = 0;  ///< entries of the factor at its last factorisation
  };
  /// Counters since construction (for benchmarks and tests).
  virtual SolverCounters solverCounters() const { return {}; }
  /// A copy of this integrator (state, factorisation) for `model`, a copy of the model this
  /// integrator steps: stepping the copy gives the same results, bit for bit, as stepping this
  /// one. nullptr when the integrator cannot be copied (the caller rebuilds instead).
  virtual std::unique_ptr<Integrator> clone(const FemModel& model) const {
    (void)model;
    return nullptr;
  }

  const Eigen::VectorXd& displacement() const { return u_; }  ///< u [m]
  const Eigen::VectorXd& velocity() const { return v_; }      ///< v [m/s]
  const Eigen::VectorXd& acceleration() const { return a_; }  ///< a [m/s^2]
  /// Kinetic + strain energy for the current state [J per thickness].
  double energy() const;
  /// Sets u = v = a = 0.
  void reset();
  /// Sets the state (sizes must match; throws std::invalid_argument otherwise).
  void setState(const Eigen::VectorXd& u, const Eigen::VectorXd& v, const Eigen::VectorXd& a);

protected:
  Integrator(const FemModel& model, std::vector<int> fixed_dofs);
  // ---- added by the FEM core (additive) ----
  /// Strain energy of the current u [J per thickness]: 1/2 u^T K u, or corotational.
  virtual double strainEnergy() const;
  /// Kinetic energy of the current v [J per thickness]: 1/2 v^T M v (lumped M for explicit).
  virtual double kineticEnergy() const;
  const FemModel& model_;
  std::vector<int> fixed_dofs_;
  Eigen::VectorXd u_, v_, a_;
};

/// Makes an integrator for `model` (kept by reference: it must outlive the integrator) with
/// the permanent zero-displacement DOFs `fixed_dofs`. Throws std::invalid_argument for a
/// fixed DOF out of range.
std::unique_ptr<Integrator> makeIntegrator(IntegratorKind kind, const FemModel& model,
                                           std::vector<int> fixed_dofs,
                                           const IntegratorOptions& options = {});

}  // namespace needle_guidance::tissue
