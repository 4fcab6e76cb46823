#include "needle_guidance/calibration/insertion_force_fit.h"

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <unsupported/Eigen/NonLinearOptimization>
#include <unsupported/Eigen/NumericalDiff>

#include "needle_guidance/calibration/force_trials.h"

namespace needle_guidance::calibration {
namespace {

// The optimiser works in N, N/cm and mm so that the three unknowns have similar sizes.
constexpr double kPerCm = 100.0;
constexpr double kMm = 1e-3;
// Bounds that keep the curve physical: a puncture depth of at least 0.01 mm, forces >= 0.
constexpr double kMinPunctureDepth_mm = 0.01;

ForceCurveParams fromScaled(const Eigen::VectorXd& x) {
  ForceCurveParams p;
  p.cutting_force_N = std::max(0.0, x[0]);
  p.friction_N_per_m = std::max(0.0, x[1]) * kPerCm;
  p.puncture_depth_m = std::max(kMinPunctureDepth_mm, x[2]) * kMm;
  return p;
}

struct Residual {
  using Scalar = double;
  using InputType = Eigen::VectorXd;
  using ValueType = Eigen::VectorXd;
  using JacobianType = Eigen::MatrixXd;
  enum { InputsAtCompileTime = Eigen::Dynamic, ValuesAtCompileTime = Eigen::Dynamic };

  const std::vector<double>* depths;
  const std::vector<double>* target;
  int inputs() const { return 3; }
  int values() const { return static_cast<int>(target->size()); }
  int operator()(const Eigen::VectorXd& x, Eigen::VectorXd& r) const {
    const std::vector<double> f = reducedInsertionForce(fromScaled(x), *depths);
    for (std::size_t i = 0; i < f.size(); ++i) {
      r[static_cast<Eigen::Index>(i)] = f[i] - (*target)[i];
    }
    return 0;
  }
};

}  // namespace

std::vector<double> reducedInsertionForce(const ForceCurveParams& p,
                                          const std::vector<double>& depths_m) {
  std::vector<double> f(depths_m.size());
  for (std::size_t i = 0; i < depths_m.size(); ++i) {
    const double d = depths_m[i];
    f[i] = d < p.puncture_depth_m
               ? p.cutting_force_N * std::max(0.0, d) / p.puncture_depth_m
               : p.cutting_force_N + p.friction_N_per_m * (d - p.puncture_depth_m);
  }
  return f;
}

std::vector<double> meanCurve(const std::vector<std::vector<double>>& curves) {
  if (curves.empty()) {
    throw std::invalid_argument("meanCurve: no curves");
  }
  std::vector<double> mean(curves.front().size(), 0.0);
  for (const auto& c : curves) {
    if (c.size() != mean.size()) {
      throw std::invalid_argument("meanCurve: curves of " + std::to_string(c.size()) + " and " +
                                  std::to_string(mean.size()) + " points");
    }
    for (std::size_t i = 0; i < c.size(); ++i) {
      mean[i] += c[i] / static_cast<double>(curves.size());
    }
  }
  return mean;
}

ForceFit fitInsertionForce(const std::vector<std::vector<double>>& curves,
                           const std::vector<double>& depths_m) {
  const std::vector<double> target = meanCurve(curves);
  if (target.size() != depths_m.size() || target.size() < 3) {
    throw std::invalid_argument("fitInsertionForce: " + std::to_string(target.size()) +
                                " forces for " + std::to_string(depths_m.size()) +
                                " depths (at least 3 needed)");
  }
  // Start: a straight line through the curve's second half gives f_k; its value at the first
  // depth gives f_c; the puncture at 1 mm.
  const std::size_t n = target.size();
  const std::size_t a = n / 2;
  const double slope = (target[n - 1] - target[a]) / (depths_m[n - 1] - depths_m[a]);
  Eigen::VectorXd x(3);
  x << std::max(1e-3, target[a] - slope * depths_m[a]), std::max(1e-3, slope / kPerCm), 1.0;

  Residual residual{&depths_m, &target};
  Eigen::NumericalDiff<Residual> functor(residual);
  Eigen::LevenbergMarquardt<Eigen::NumericalDiff<Residual>> lm(functor);
  const auto status = lm.minimize(x);
  ForceFit fit;
  fit.params = fromScaled(x);
  fit.rmse_N = rmse(reducedInsertionForce(fit.params, depths_m), target);
  fit.iterations = static_cast<int>(lm.iter);
  fit.converged = status == Eigen::LevenbergMarquardtSpace::RelativeReductionTooSmall ||
                  status == Eigen::LevenbergMarquardtSpace::RelativeErrorTooSmall ||
                  status == Eigen::LevenbergMarquardtSpace::RelativeErrorAndReductionTooSmall ||
                  status == Eigen::LevenbergMarquardtSpace::CosinusTooSmall ||
                  status == Eigen::LevenbergMarquardtSpace::XtolTooSmall ||
                  status == Eigen::LevenbergMarquardtSpace::FtolTooSmall ||
                  status == Eigen::LevenbergMarquardtSpace::GtolTooSmall;
  fit.message = "Levenberg-Marquardt status " + std::to_string(static_cast<int>(status)) +
                " after " + std::to_string(lm.iter) + " iterations";
  return fit;
}

}  // namespace needle_guidance::calibration
