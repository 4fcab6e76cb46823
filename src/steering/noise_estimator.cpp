// Maximum-likelihood deflection noise with chi-square intervals (dissertation 5.3).
#include "needle_guidance/steering/noise_estimator.h"
#include "needle_guidance/math.h"

#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace needle_guidance::steering {
namespace {

/// Standard normal quantile: Acklam's rational approximation (relative error 1.15e-9) refined
/// by one Halley step on erfc (then about machine precision); it is called after every observed
/// step, so it must be cheap.
double normalQuantile(double p) {
  static const double a[] = {-3.969683028665376e+01, 2.209460984245205e+02,  -2.759285104469687e+02,
                             1.383577518672690e+02,  -3.066479806614716e+01, 2.506628277459239e+00};
  static const double b[] = {-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02,
                             6.680131188771972e+01, -1.328068155288572e+01};
  static const double c[] = {-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00,
                             -2.549732539343734e+00, 4.374664141464968e+00,  2.938163982698783e+00};
  static const double d[] = {7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00,
                             3.754408661907416e+00};
  constexpr double kLow = 0.02425;
  double x = 0.0;
  if (p < kLow || p > 1.0 - kLow) {
    const double q = std::sqrt(-2.0 * std::log(p < kLow ? p : 1.0 - p));
    x = (((((c[0] * q + c[1]) * q + c[2]) * q + c[3]) * q + c[4]) * q + c[5]) /
        ((((d[0] * q + d[1]) * q + d[2]) * q + d[3]) * q + 1.0);
    x = p < kLow ? x : -x;
  } else {
    const double q = p - 0.5, r = q * q;
    x = (((((a[0] * r + a[1]) * r + a[2]) * r + a[3]) * r + a[4]) * r + a[5]) * q /
        (((((b[0] * r + b[1]) * r + b[2]) * r + b[3]) * r + b[4]) * r + 1.0);
  }
  const double e = 0.5 * std::erfc(-x / std::sqrt(2.0)) - p;
  const double u = e * std::sqrt(2.0 * kPi) * std::exp(0.5 * x * x);
  return x - u / (1.0 + 0.5 * x * u);
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

std::optional<double> NoiseEstimator::deflectionOfStoppedStep(const TipPose& before,
                                                              const TipPose& stopped,
                                                              double min_chord_m) {
  if (!before.p_SceneTip.allFinite() || !stopped.p_SceneTip.allFinite() ||
      !std::isfinite(before.theta_rad) || !std::isfinite(stopped.theta_rad)) {
    throw std::invalid_argument("NoiseEstimator::deflectionOfStoppedStep: non-finite pose");
  }
  const Point2 chord = stopped.p_SceneTip - before.p_SceneTip;
  if (!(chord.norm() >= min_chord_m) || chord.norm() == 0.0) {
    return std::nullopt;
  }
  // The chord bisects the turn whichever way the bevel traced it: no control needed.
  const double chord_angle = std::atan2(chord.y(), chord.x());
  const double beta =
      std::remainder(2.0 * chord_angle - stopped.theta_rad - before.theta_rad, 2.0 * kPi);
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
  return estimate(control, confidence_);
}

SigmaEstimate NoiseEstimator::estimate(Control control, double confidence) const {
  if (!(confidence > 0.0 && confidence < 1.0)) {
    throw std::invalid_argument("NoiseEstimator::estimate: confidence must be in (0, 1), got " +
                                std::to_string(confidence));
  }
  const int u = static_cast<int>(control);
  SigmaEstimate e;
  e.samples = n_[u];
  if (e.samples == 0) {
    e.high_rad = std::numeric_limits<double>::infinity();
    return e;
  }
  const double n = static_cast<double>(e.samples);
  e.sigma_rad = std::sqrt(sum_sq_[u] / n);
  const double a = 1.0 - confidence;
  e.low_rad = std::sqrt(sum_sq_[u] / chiSquareQuantile(1.0 - 0.5 * a, n));
  e.high_rad = std::sqrt(sum_sq_[u] / chiSquareQuantile(0.5 * a, n));
  return e;
}

}  // namespace needle_guidance::steering
