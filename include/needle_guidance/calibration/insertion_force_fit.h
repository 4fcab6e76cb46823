// Fit of the needle–tissue interaction to measured insertion forces (dissertation 2.3.4–2.3.5).
// During a steady insertion the 2-D model's axial force is the cutting force at the tip plus
// kinetic friction along the shaft in the tissue; before the first cut the tip only deforms the
// tissue (the pre-puncture stiffness phase). The reduced curve
//   F(d) = f_c d / d_p                      for d < d_p
//   F(d) = f_c + f_k (d - d_p)              for d >= d_p
// (f_c cutting force [N], f_k kinetic friction per unit length [N/m], d_p puncture depth [m])
// is fitted by Levenberg–Marquardt (Eigen unsupported NonLinearOptimization) and checked
// against the FEM (fem_force_curve.h).
#pragma once

#include <string>
#include <vector>

namespace needle_guidance::calibration {

/// Parameters of the reduced force–depth curve.
struct ForceCurveParams {
  double cutting_force_N = 0.3;    ///< f_c: tip force while cutting [N], >= 0
  double friction_N_per_m = 15.0;  ///< f_k: shaft friction per unit length in tissue [N/m]
  double puncture_depth_m = 1e-3;  ///< d_p: depth of the first cut [m], > 0
};

/// F(d) at each depth [N].
std::vector<double> reducedInsertionForce(const ForceCurveParams& params,
                                          const std::vector<double>& depths_m);

/// Outcome of a least-squares fit.
struct ForceFit {
  ForceCurveParams params;
  double rmse_N = 0.0;  ///< against the mean of the fitted curves [N]
  int iterations = 0;
  bool converged = false;
  std::string message;  ///< what the optimiser reported
};

/// Least-squares fit of the reduced curve to the mean of `curves` (each sampled at depths_m),
/// which minimises the summed squared error over all trials. Throws std::invalid_argument for
/// no curves or mismatched lengths.
ForceFit fitInsertionForce(const std::vector<std::vector<double>>& curves,
                           const std::vector<double>& depths_m);

/// Pointwise mean of equal-length curves.
std::vector<double> meanCurve(const std::vector<std::vector<double>>& curves);

}  // namespace needle_guidance::calibration
