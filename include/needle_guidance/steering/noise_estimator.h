// Online estimate of the needle's deflection noise (dissertation 5.3: beta ~ N(0, sigma_i) per
// insertion, N(0, sigma_r) per insertion after a flip) from the tip poses a run observes, for a
// policy that learns the needle's noise instead of assuming it. Plain C++; no ROS.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance::steering {

/// A maximum-likelihood standard deviation with its two-sided confidence interval [rad].
struct SigmaEstimate {
  std::int64_t samples = 0;  ///< deflections seen
  double sigma_rad = 0.0;    ///< ML estimate sqrt(sum beta^2 / n); 0 without samples
  double low_rad = 0.0;      ///< interval bounds (0 and +inf without samples)
  double high_rad = 0.0;
  bool contains(double sigma) const { return sigma >= low_rad && sigma <= high_rad; }
};

/// Accumulates deflections per control and estimates sigma_i and sigma_r by maximum likelihood
/// (zero-mean normal: sigma^2 = mean beta^2) with the chi-square interval
/// [sqrt(n s^2 / chi2_{n, 1 - a/2}), sqrt(n s^2 / chi2_{n, a/2})].
class NoiseEstimator {
public:
  /// @param[in] confidence level of the intervals, in (0, 1); throws std::invalid_argument
  explicit NoiseEstimator(double confidence = 0.95);

  /// The deflection of one observed step: the tip went from `before` to `after` under `control`
  /// with arc length delta over radius r, so after.theta = before.theta + beta +- delta / r (5.3,
  /// advanceTip). Returns beta [rad] in (-pi, pi]. Throws std::invalid_argument for a non-finite
  /// pose or a non-positive radius.
  static double deflection(const TipPose& before, const TipPose& after, Control control,
                           double arc_length_m, double radius_m);
  /// The deflection of a step that stopped after an unknown arc length (it touched an obstacle or
  /// the workspace edge): the arc from `before` with heading theta + beta ends at `stopped` with
  /// heading theta + beta +- l / r, and its chord points along theta + beta +- l / (2 r), so
  /// beta = 2 chord angle - stopped.theta - before.theta, whatever l is. Needs a chord of at
  /// least min_chord_m; nullopt for a shorter one (nothing to learn). Dropping such steps would
  /// bias the estimate low: the largest deflections are the ones that stop a step. Throws
  /// std::invalid_argument for a non-finite pose.
  static std::optional<double> deflectionOfStoppedStep(const TipPose& before,
                                                       const TipPose& stopped, double min_chord_m);

  /// Adds one deflection [rad] observed under `control`. Throws std::invalid_argument for a
  /// non-finite beta (the estimate is left unchanged).
  void add(Control control, double beta_rad);
  /// Adds the deflection of one observed step (deflection() then add()).
  void addStep(const TipPose& before, const TipPose& after, Control control, double arc_length_m,
               double radius_m);

  /// The estimate for insertions (sigma_i) or flips (sigma_r), at confidence().
  SigmaEstimate estimate(Control control) const;
  /// The same at another confidence level in (0, 1) (the re-solve test's, adaptive_policy.h).
  SigmaEstimate estimate(Control control, double confidence) const;
  double confidence() const { return confidence_; }

private:
  double confidence_;
  std::int64_t n_[2] = {0, 0};
  double sum_sq_[2] = {0.0, 0.0};
};

/// Quantile of the chi-square distribution with `dof` degrees of freedom (> 0) at probability p
/// in (0, 1), by the Wilson-Hilferty cube-root normal approximation (relative error below 1 %
/// for dof >= 3; adequate for an interval, not for tail probabilities).
double chiSquareQuantile(double p, double dof);

}  // namespace needle_guidance::steering
