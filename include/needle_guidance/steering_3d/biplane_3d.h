// Biplane tip triangulation (issue 18, closed loop through two orthogonal fluoroscopy views):
// two orthographic views of frame scene, one along z (it sees x, y) and one along y (it sees
// x, z), each with a 2-D tip detection and its covariance, fused into a 3-D tip position with a
// covariance by linear-Gaussian information fusion. Both views see x, so one degree of freedom
// checks them against each other: views whose chi-square disagreement exceeds the gate are
// refused (gated), never fused. Plain C++ and Eigen; no ROS.
#pragma once

#include <Eigen/Core>
#include <string>

#include "needle_guidance/status.h"
#include "needle_guidance/steering_3d/needle_3d.h"

namespace needle_guidance::steering_3d {

/// The direction a view looks along.
enum class ViewAxis {
  kAlongZ,  ///< lateral view: measures (x, y) of frame scene
  kAlongY,  ///< anterior-posterior view: measures (x, z)
};

/// One view's tip detection, in frame scene coordinates of the two axes it sees.
struct ViewDetection {
  ViewAxis axis = ViewAxis::kAlongZ;
  Eigen::Vector2d p_m = Eigen::Vector2d::Zero();                ///< [m]
  Eigen::Matrix2d covariance_m2 = Eigen::Matrix2d::Identity();  ///< [m^2], positive definite
};

enum class BiplaneCode {
  kOk = 0,
  kDisagree,  ///< the views' shared coordinate disagrees beyond the gate: not fused
  kBadInput,  ///< non-finite values, a covariance not positive definite, or two views on one axis
};
using BiplaneStatus = Status<BiplaneCode, BiplaneCode::kOk>;

/// The fused tip.
struct TipEstimate3 {
  Vector3 p_SceneTip = Vector3::Zero();         ///< [m]
  Matrix3 covariance_m2 = Matrix3::Identity();  ///< [m^2]
  double chi_square = 0.0;                      ///< the views' disagreement (1 degree of freedom)
};

/// 99.9 % point of the chi-square distribution with one degree of freedom.
constexpr double kBiplaneGateChiSquare = 10.827566170662733;

/// Fuses one view along z and one along y (either order). Returns kDisagree (with the
/// disagreement in the message) when the chi-square exceeds `gate`, kBadInput for bad input.
Result<TipEstimate3, BiplaneStatus> triangulateBiplane(const ViewDetection& a,
                                                       const ViewDetection& b,
                                                       double gate = kBiplaneGateChiSquare);

}  // namespace needle_guidance::steering_3d
