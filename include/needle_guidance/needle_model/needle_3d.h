// The bevel-tip steerable needle in 3-D: a unicycle in SE(3) after Webster et al.,
// "Nonholonomic modeling of needle steering" (IJRR 2006), with duty-cycled spinning for any
// effective curvature in [0, kappa_max] (Minhas et al. 2007; Patil et al., T-RO 2014) and the
// process noise of dissertation 5.3 generalised to 3-D. Plain C++ and Eigen; no ROS.
//
// Frames: everything is in frame `scene` (+x insertion, +y height, +z lateral; the
// planar scenes are its z = 0 plane). The tip frame's columns are (d, n, t): d the bevel
// direction (the side the needle curves towards), n = t x d, t the tip tangent. Per unit
// inserted length the tip frame moves with the constant body twist
//   linear (0, 0, 1), angular (0, kappa, omega / v),
// i.e. it bends about n at curvature kappa and rolls about t at the spin rate omega over the
// insertion speed v. Without spin this is the exact arc dt/ds = kappa d of 5.3.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <random>
#include <string>
#include <vector>

namespace needle_guidance::needle_model {

using Vector3 = Eigen::Vector3d;
using Matrix3 = Eigen::Matrix3d;

/// Tip pose: position and orientation of the tip frame (d, n, t) in frame scene.
struct TipPose3 {
  Vector3 p_SceneTip = Vector3::Zero();      ///< tip position [m]
  Matrix3 R_SceneTip = Matrix3::Identity();  ///< columns d (bevel), n (binormal), t (tangent)

  Vector3 tangent() const { return R_SceneTip.col(2); }
  Vector3 bevel() const { return R_SceneTip.col(0); }
};

/// A tip pose with tangent `tangent` and bevel direction the component of `bevel_hint`
/// perpendicular to it. Throws std::invalid_argument (naming the values) for a zero tangent or a
/// hint parallel to it.
TipPose3 makeTipPose(const Vector3& p_SceneTip, const Vector3& tangent, const Vector3& bevel_hint);

/// Exact screw motion of the constant body twist above over `length_m` of insertion.
/// @param[in] curvature_per_m kappa >= 0 [1/m]; @param[in] roll_per_m omega / v [rad/m]
/// @param[in] length_m inserted length [m], >= 0
TipPose3 screwMotion(const TipPose3& pose, double curvature_per_m, double roll_per_m,
                     double length_m);
/// The arc of curvature kappa in the bevel direction (screwMotion without roll).
TipPose3 advanceArc(const TipPose3& pose, double curvature_per_m, double length_m);
/// Rotates the bevel about the tangent by angle_rad (right-handed about t); position unchanged.
TipPose3 rotateBevel(const TipPose3& pose, double angle_rad);

/// Properties of the needle, the tissue and the rotation stage.
struct NeedleParams3 {
  double kappa_max_per_m = 1.0 / 0.05;  ///< curvature with the bevel held still [1/m]
  double insertion_speed_m_s = 2e-3;    ///< v [m/s], > 0
  double spin_rate_max_rad_s = 2.0 * 3.14159265358979 * 5.0;  ///< stage's spin limit [rad/s]
  double duty_cycle_length_m = 2e-3;  ///< inserted length of one spin + hold cycle [m], > 0
  /// Throws std::invalid_argument naming the first non-positive or non-finite field.
  void validate() const;
};

/// One duty cycle: hold the bevel for (1 - spin_fraction) of the cycle, then spin one full turn
/// while inserting the rest. Mean curvature kappa_max (1 - spin_fraction) (Minhas 2007).
struct DutyCycle {
  double requested_per_m = 0.0;  ///< the curvature asked for [1/m]
  double kappa_per_m = 0.0;      ///< the nominal curvature this cycle achieves [1/m]
  double spin_fraction = 0.0;    ///< alpha in {0} u [alpha_min, 1]
  double spin_rate_rad_s = 0.0;  ///< omega = 2 pi v / (alpha L) while spinning; 0 if alpha = 0
  /// The request fell in (kappa_max (1 - alpha_min), kappa_max) or outside [0, kappa_max]: the
  /// spin-rate limit forbids it and the nearest achievable curvature was taken.
  bool saturated = false;
};

/// Length of each duty cycle in a step of step_length_m: the step is cut into
/// max(1, floor(step / duty_cycle_length)) whole cycles, so a step ends with the bevel where it
/// began; cycles are at least duty_cycle_length_m long unless the step is shorter.
double cycleLength(double step_length_m, const NeedleParams3& params);
/// Smallest spin fraction the spin-rate limit allows in a cycle of cycle_length_m:
/// 2 pi v / (omega_max cycle_length) (> 1: no spin fits, only alpha = 0).
double minSpinFraction(const NeedleParams3& params, double cycle_length_m);
/// The duty cycle for an effective curvature in cycles of cycle_length_m; see
/// DutyCycle::saturated. Never exceeds the spin-rate limit.
DutyCycle dutyCycleFor(double kappa_request_per_m, const NeedleParams3& params,
                       double cycle_length_m);

/// The duty-cycle model's residual error: during a spin the tip follows a screw whose axis is
/// tilted from the tangent by kappa_max / rho (rho = 2 pi / (alpha L), the roll per length),
/// towards the binormal n. Averaged over a cycle the heading is off by alpha^2 kappa_max L /
/// (2 pi) [rad] (3.2 mrad at alpha = 1, kappa_max = 20 /m, L = 2 mm), which the closed loop
/// corrects; each turn also over-rolls the bevel by about pi (kappa_max / rho)^2 [rad].
double residualHeadingRad(const DutyCycle& cycle, const NeedleParams3& params,
                          double cycle_length_m);

/// Exact duty-cycled insertion over length_m from `pose` (bevel as in `pose`): the whole cycles
/// of cycleLength(length_m), each a hold arc and a one-turn screw. The spin's screw leaves a small
/// residual bend and roll (the model's residual error against the ideal arc of kappa_per_m).
/// Appends tip positions to `path` if given: at most 1 mm apart along held arcs and after each
/// spin (whose helix has a radius of microns).
TipPose3 insertDutyCycled(const TipPose3& pose, const DutyCycle& cycle, double length_m,
                          const NeedleParams3& params, std::vector<Vector3>* path = nullptr);

/// Process noise of 5.3 generalised to 3-D. Each step first deflects the tangent by
/// N(0, sigma) about each of the two axes perpendicular to it (d and n), with sigma =
/// sigma_spin when the step begins with a bevel rotation (5.3's sigma_r: the extra deflection a
/// rotation causes) and sigma_insert otherwise (5.3's sigma_i); a rotation also misses its
/// angle by N(0, sigma_roll). With in_plane_only the deflection is about n only (the bevel's
/// plane), which is 5.3 exactly for a needle whose bevel stays in one plane. Every step draws
/// the same three normals, so two policies see the same noise stream (common random numbers).
struct NoiseParams3 {
  double sigma_insert_rad = 0.0;  ///< per axis, per step [rad], >= 0
  double sigma_spin_rad = 0.0;    ///< per axis on a step after a bevel rotation [rad], >= 0
  double sigma_roll_rad = 0.0;    ///< error of a commanded bevel rotation [rad], >= 0
  bool in_plane_only = false;
  /// Scales all three sigmas (the bench's 0, 1x, 2x).
  NoiseParams3 scaled(double factor) const;
  /// Throws std::invalid_argument naming a negative or non-finite sigma.
  void validate() const;
};

/// One command: rotate the bevel by rotate_rad, then insert length_m with duty-cycled spinning
/// for effective curvature curvature_per_m.
struct Control3 {
  double rotate_rad = 0.0;
  double curvature_per_m = 0.0;
  double length_m = 0.0;
};

/// What a noisy step did.
struct StepRecord {
  TipPose3 pose;                             ///< tip after the step
  DutyCycle cycle;                           ///< the duty cycle used
  Vector3 deflection_rad = Vector3::Zero();  ///< applied deflection about (d, n, t) [rad]
  std::vector<Vector3> path;                 ///< tip positions along the step, start included [m]
};

/// The "world" needle: deterministic given its seed (std::mt19937_64).
class NoisyNeedle3 {
public:
  NoisyNeedle3(NeedleParams3 params, NoiseParams3 noise, std::uint64_t seed);
  /// Applies one command from `pose` (see Control3 and NoiseParams3). Throws
  /// std::invalid_argument for a negative or non-finite length or curvature.
  StepRecord step(const TipPose3& pose, const Control3& control);
  const NeedleParams3& params() const { return params_; }
  const NoiseParams3& noise() const { return noise_; }

private:
  NeedleParams3 params_;
  NoiseParams3 noise_;
  std::mt19937_64 rng_;
  std::normal_distribution<double> normal_{0.0, 1.0};
};

/// Rotation that deflects the tangent by `deflection_rad` given about the tip axes (d, n, t).
TipPose3 deflect(const TipPose3& pose, const Vector3& deflection_rad);

}  // namespace needle_guidance::needle_model
