// Biplane tip triangulation (closed loop through two orthogonal fluoroscopy views):
// two orthographic views of frame scene, one along z (it sees x, y) and one along y (it sees
// x, z), each with a 2-D tip detection and its covariance, fused into a 3-D tip position with a
// covariance by linear-Gaussian information fusion. Both views see x, so one degree of freedom
// checks them against each other: views whose chi-square disagreement exceeds the gate are
// refused (gated), never fused. Plain C++ and Eigen; no ROS.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <random>
#include <string>

#include "needle_guidance/needle_model/needle_3d.h"
#include "needle_guidance/status.h"

namespace needle_guidance::needle_model {

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
  kNoDetection,  ///< a view found no tip (dropped frame or detection): nothing to fuse
};
using BiplaneStatus = Status<BiplaneCode, BiplaneCode::kOk>;

/// The fused tip.
struct TipEstimate3 {
  Vector3 p_SceneTip = Vector3::Zero();         ///< [m]
  Matrix3 covariance_m2 = Matrix3::Identity();  ///< [m^2]
  double chi_square = 0.0;                      ///< the views' disagreement (1 degree of freedom)
};

/// Rows of frame scene axes a view measures: (x, y) along z, (x, z) along y.
Eigen::Matrix<double, 2, 3> viewRows(ViewAxis axis);
/// The tip seen by both views: at p_SceneTip, its tangent from the shaft's headings in the view
/// along z (atan2(t_y, t_x)) and along y (atan2(t_z, t_x)), with t_x > 0; the bevel as close to
/// bevel_hint as the tangent allows (the views do not see the roll).
TipPose3 tipFromViews(const Vector3& p_SceneTip, double heading_z_rad, double heading_y_rad,
                      const Vector3& bevel_hint);

/// 99.9 % point of the chi-square distribution with one degree of freedom.
constexpr double kBiplaneGateChiSquare = 10.827566170662733;

/// Fuses one view along z and one along y (either order). Returns kDisagree (with the
/// disagreement in the message) when the chi-square exceeds `gate`, kBadInput for bad input.
Result<TipEstimate3, BiplaneStatus> triangulateBiplane(const ViewDetection& a,
                                                       const ViewDetection& b,
                                                       double gate = kBiplaneGateChiSquare);

/// The simulated biplane imaging of the closed loop: each view detects the tip's
/// projection with Gaussian noise, and the projected shaft direction with angular noise; a view
/// may find nothing (dropout) or a false tip (an outlier displaced by outlier_offset_m in a random
/// direction of its image plane). The two views are fused by triangulateBiplane with its gate.
struct BiplaneImaging3 {
  double sigma_position_m = 2e-4;       ///< per axis per view [m], > 0
  double sigma_heading_rad = 0.01;      ///< projected shaft angle per view [rad], >= 0
  double dropout = 0.05;                ///< probability that a view has no detection, [0, 1]
  double outlier = 0.02;                ///< probability of a false detection in a view, [0, 1]
  double outlier_offset_m = 5e-3;       ///< a false detection's displacement [m], >= 0
  double gate = kBiplaneGateChiSquare;  ///< chi-square gate (1 degree of freedom), > 0
  /// Throws std::invalid_argument naming the first value out of range.
  void validate() const;
};

/// Seeded biplane imaging of a true tip.
class BiplaneObserver3 {
public:
  BiplaneObserver3(BiplaneImaging3 imaging, std::uint64_t seed);
  /// Images `truth` in both views and fuses them. The estimate has the fused position, the
  /// tangent from the two projected shaft directions (frame scene +x must point along the shaft's
  /// insertion, t_x > 0) and the bevel of `predicted` (the views do not see the bevel's roll).
  /// kNoDetection when a view dropped out, kDisagree when the gate refused the pair. Every call
  /// makes the same number of draws.
  Result<TipPose3, BiplaneStatus> observe(const TipPose3& truth, const TipPose3& predicted);

private:
  ViewDetection detect(const TipPose3& truth, ViewAxis axis, double& heading_rad, bool& found);

  BiplaneImaging3 imaging_;
  std::mt19937_64 rng_;
  std::normal_distribution<double> normal_{0.0, 1.0};
  std::uniform_real_distribution<double> unit_{0.0, 1.0};
};

}  // namespace needle_guidance::needle_model
