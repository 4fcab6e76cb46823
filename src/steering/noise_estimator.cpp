// Maximum-likelihood deflection noise with chi-square intervals (issue 21; dissertation 5.3).
#include "needle_guidance/steering/noise_estimator.h"

#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace needle_guidance::steering {
namespace {

constexpr double kPi = 3.14159265358979323846;

/// Standard normal quantile by bisection on erfc (60 halvings: ~1e-16 of the bracket).
double normalQuantile(double p) {
  double lo = -40.0, hi = 40.0;
  for (int i = 0; i < 200 && hi - lo > 1e-15; ++i) {
    const double mid = 0.5 * (lo + hi);
    (0.5 * std::erfc(-mid / std::sqrt(2.0)) < p ? lo : hi) = mid;
  }
  return 0.5 * (lo + hi);
}

}  // namespace

double chiSquareQuantile(double p, double dof) {
  if (!(p > 0.0 && p < 1.0) || !(dof > 0.0) || !std::isfinite(dof)) {
    throw std::invalid_argument("chiSquareQuantile: need p in (0, 1) and dof > 0, got p " +
                                std::to_string(p) + ", dof " + std::to_string(dof));
  }
  const double z = normalQuantile(p);
  const double c = 2.0 / (9.0 * dof);
  const double t = 1.0 - c + z * std::sqrt(c);
  return dof * std::max(0.0, t * t * t);
}

NoiseEstimator::NoiseEstimator(double confidence) : confidence_(confidence) {
  if (!(confidence > 0.0 && confidence < 1.0)) {
    throw std::invalid_argument("NoiseEstimator: confidence must be in (0, 1), got " +
                                std::to_string(confidence));
  }
}

double NoiseEstimator::deflection(const TipPose& before, const TipPose& after, Control control,
                                  double arc_length_m, double radius_m) {
  if (!std::isfinite(before.theta_rad) || !std::isfinite(after.theta_rad) ||
      !std::isfinite(arc_length_m) || !(radius_m > 0.0) || !std::isfinite(radius_m)) {
    throw std::invalid_argument(
        "NoiseEstimator::deflection: non-finite orientation or arc length, or radius " +
        std::to_string(radius_m) + " not > 0");
  }
  const Bevel traced = control == Control::kFlip ? flipped(before.bevel) : before.bevel;
  const double turn = (traced == Bevel::kLeft ? 1.0 : -1.0) * arc_length_m / radius_m;
  const double beta = std::remainder(after.theta_rad - before.theta_rad - turn, 2.0 * kPi);
  return beta == -kPi ? kPi : beta;
}

void NoiseEstimator::add(Control control, double beta_rad) {
  if (!std::isfinite(beta_rad)) {
    throw std::invalid_argument("NoiseEstimator::add: deflection is not finite");
  }
  const int u = static_cast<int>(control);
  ++n_[u];
  sum_sq_[u] += beta_rad * beta_rad;
}

void NoiseEstimator::addStep(const TipPose& before, const TipPose& after, Control control,
                             double arc_length_m, double radius_m) {
  add(control, deflection(before, after, control, arc_length_m, radius_m));
}

SigmaEstimate NoiseEstimator::estimate(Control control) const {
  const int u = static_cast<int>(control);
  SigmaEstimate e;
  e.samples = n_[u];
  if (e.samples == 0) {
    e.high_rad = std::numeric_limits<double>::infinity();
    return e;
  }
  const double n = static_cast<double>(e.samples);
  e.sigma_rad = std::sqrt(sum_sq_[u] / n);
  const double a = 1.0 - confidence_;
  e.low_rad = std::sqrt(sum_sq_[u] / chiSquareQuantile(1.0 - 0.5 * a, n));
  e.high_rad = std::sqrt(sum_sq_[u] / chiSquareQuantile(0.5 * a, n));
  return e;
}

}  // namespace needle_guidance::steering
