// The 3-D bevel-tip needle: screw motions, duty cycles and the seeded noisy world (needle_3d.h).
#include "needle_guidance/needle_model/needle_3d.h"
#include "needle_guidance/math.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::needle_model {
namespace {

/// Below this rotation angle the screw uses the series of its translation (relative error of the
/// series ~ theta^4 / 120, far below double precision at 1e-4).
constexpr double kSmallAngle_rad = 1e-4;
/// Path points along held arcs are at most this far apart: the chord of a 1 mm piece lies
/// within kappa l^2 / 8 = 2.5 um of an arc of kappa = 20 /m [m].
constexpr double kPathSpacing_m = 1e-3;

Matrix3 skew(const Vector3& w) {
  Matrix3 m;
  m << 0.0, -w.z(), w.y(), w.z(), 0.0, -w.x(), -w.y(), w.x(), 0.0;
  return m;
}

void requireFinite(const char* where, const char* name, double value, bool positive) {
  if (!std::isfinite(value) || (positive ? value <= 0.0 : value < 0.0)) {
    std::ostringstream os;
    os << where << ": " << name << " = " << value << " must be finite and "
       << (positive ? "> 0" : ">= 0");
    throw std::invalid_argument(os.str());
  }
}

}  // namespace

TipPose3 makeTipPose(const Vector3& p_SceneTip, const Vector3& tangent, const Vector3& bevel_hint) {
  const double t_norm = tangent.norm();
  if (!(t_norm > 0.0) || !std::isfinite(t_norm) || !p_SceneTip.allFinite()) {
    throw std::invalid_argument("makeTipPose: tangent must be finite and non-zero");
  }
  const Vector3 t = tangent / t_norm;
  const Vector3 d_raw = bevel_hint - bevel_hint.dot(t) * t;
  if (!(d_raw.norm() > 1e-9 * std::max(1.0, bevel_hint.norm())) || !d_raw.allFinite()) {
    throw std::invalid_argument("makeTipPose: bevel hint is parallel to the tangent");
  }
  const Vector3 d = d_raw.normalized();
  TipPose3 pose;
  pose.p_SceneTip = p_SceneTip;
  pose.R_SceneTip.col(0) = d;
  pose.R_SceneTip.col(1) = t.cross(d);
  pose.R_SceneTip.col(2) = t;
  return pose;
}

TipPose3 screwMotion(const TipPose3& pose, double curvature_per_m, double roll_per_m,
                     double length_m) {
  // exp of the body twist (v = e_z, w = (0, kappa, roll)) times s: SE(3) exponential.
  const Vector3 w = Vector3(0.0, curvature_per_m, roll_per_m) * length_m;
  const double theta = w.norm();
  const Matrix3 W = skew(w);
  Matrix3 V;
  Matrix3 R_body;
  if (theta < kSmallAngle_rad) {
    V = Matrix3::Identity() + 0.5 * W + W * W / 6.0;
    R_body = Matrix3::Identity() + W + 0.5 * W * W;
    // Re-orthonormalise the second-order rotation (error ~ theta^3).
    Eigen::Quaterniond q(R_body);
    R_body = q.normalized().toRotationMatrix();
  } else {
    const double t2 = theta * theta;
    V = Matrix3::Identity() + (1.0 - std::cos(theta)) / t2 * W +
        (theta - std::sin(theta)) / (t2 * theta) * W * W;
    R_body = Eigen::AngleAxisd(theta, w / theta).toRotationMatrix();
  }
  TipPose3 out;
  out.p_SceneTip = pose.p_SceneTip + pose.R_SceneTip * (V * Vector3(0.0, 0.0, length_m));
  out.R_SceneTip = pose.R_SceneTip * R_body;
  return out;
}

TipPose3 advanceArc(const TipPose3& pose, double curvature_per_m, double length_m) {
  return screwMotion(pose, curvature_per_m, 0.0, length_m);
}

TipPose3 rotateBevel(const TipPose3& pose, double angle_rad) {
  TipPose3 out = pose;
  out.R_SceneTip =
      pose.R_SceneTip * Eigen::AngleAxisd(angle_rad, Vector3::UnitZ()).toRotationMatrix();
  return out;
}

TipPose3 deflect(const TipPose3& pose, const Vector3& deflection_rad) {
  const double angle = deflection_rad.norm();
  if (angle == 0.0) {
    return pose;
  }
  TipPose3 out = pose;
  out.R_SceneTip =
      pose.R_SceneTip * Eigen::AngleAxisd(angle, deflection_rad / angle).toRotationMatrix();
  return out;
}

void NeedleParams3::validate() const {
  const char* where = "NeedleParams3";
  requireFinite(where, "kappa_max_per_m", kappa_max_per_m, true);
  requireFinite(where, "insertion_speed_m_s", insertion_speed_m_s, true);
  requireFinite(where, "spin_rate_max_rad_s", spin_rate_max_rad_s, true);
  requireFinite(where, "duty_cycle_length_m", duty_cycle_length_m, true);
  if (minSpinFraction(*this, duty_cycle_length_m) >= 1.0) {
    std::ostringstream os;
    os << "NeedleParams3: spin_rate_max_rad_s = " << spin_rate_max_rad_s
       << " cannot turn the needle once per duty cycle of " << duty_cycle_length_m << " m at "
       << insertion_speed_m_s << " m/s (needs > "
       << 2.0 * kPi * insertion_speed_m_s / duty_cycle_length_m << " rad/s)";
    throw std::invalid_argument(os.str());
  }
}

double cycleLength(double step_length_m, const NeedleParams3& params) {
  const double cycles = std::max(1.0, std::floor(step_length_m / params.duty_cycle_length_m));
  return step_length_m / cycles;
}

double minSpinFraction(const NeedleParams3& params, double cycle_length_m) {
  return 2.0 * kPi * params.insertion_speed_m_s / (params.spin_rate_max_rad_s * cycle_length_m);
}

DutyCycle dutyCycleFor(double kappa_request_per_m, const NeedleParams3& params,
                       double cycle_length_m) {
  DutyCycle cycle;
  cycle.requested_per_m = kappa_request_per_m;
  const double kmax = params.kappa_max_per_m;
  const double alpha_min = minSpinFraction(params, cycle_length_m);
  double kappa = kappa_request_per_m;
  if (!(kappa >= 0.0) || kappa > kmax) {  // also NaN
    cycle.saturated = true;
    kappa = kappa > kmax ? kmax : 0.0;
  }
  double alpha = 1.0 - kappa / kmax;
  constexpr double kFullCurvature = 1e-12;  // relative: a request this close to kmax is kmax
  if (alpha <= kFullCurvature) {
    alpha = 0.0;
  } else if (alpha < alpha_min * (1.0 - kFullCurvature)) {
    // The spin would have to be faster than the stage allows: take the nearest achievable.
    cycle.saturated = true;
    alpha = (alpha < 0.5 * alpha_min || alpha_min > 1.0) ? 0.0 : alpha_min;
  } else {
    alpha = std::max(alpha, alpha_min);  // rounding at the limit itself
  }
  cycle.spin_fraction = alpha;
  cycle.kappa_per_m = kmax * (1.0 - alpha);
  cycle.spin_rate_rad_s =
      alpha > 0.0 ? 2.0 * kPi * params.insertion_speed_m_s / (alpha * cycle_length_m) : 0.0;
  return cycle;
}

TipPose3 insertDutyCycled(const TipPose3& pose, const DutyCycle& cycle, double length_m,
                          const NeedleParams3& params, std::vector<Vector3>* path) {
  if (!(length_m >= 0.0) || !std::isfinite(length_m)) {
    throw std::invalid_argument("insertDutyCycled: length_m = " + std::to_string(length_m) +
                                " must be finite and >= 0");
  }
  if (length_m == 0.0) {
    return pose;
  }
  const double kmax = params.kappa_max_per_m;
  const auto hold_arc = [&](const TipPose3& from, double length) {
    // Path points along the held arc at most kPathSpacing_m apart.
    const int pieces = std::max(1, static_cast<int>(std::ceil(length / kPathSpacing_m)));
    for (int i = 1; path != nullptr && i < pieces; ++i) {
      path->push_back(advanceArc(from, kmax, length * i / pieces).p_SceneTip);
    }
    const TipPose3 end = advanceArc(from, kmax, length);
    if (path != nullptr) {
      path->push_back(end.p_SceneTip);
    }
    return end;
  };
  if (cycle.spin_fraction <= 0.0) {
    return hold_arc(pose, length_m);
  }
  // Whole cycles only, so a step ends with the bevel where it began.
  const double cycle_length = cycleLength(length_m, params);
  const int cycles = static_cast<int>(std::lround(length_m / cycle_length));
  const double hold = (1.0 - cycle.spin_fraction) * cycle_length;
  const double spin = cycle.spin_fraction * cycle_length;
  const double roll_per_m = 2.0 * kPi / spin;
  TipPose3 out = pose;
  for (int c = 0; c < cycles; ++c) {
    if (hold > 0.0) {
      out = hold_arc(out, hold);
    }
    out = screwMotion(out, kmax, roll_per_m, spin);
    if (path != nullptr) {
      path->push_back(out.p_SceneTip);
    }
  }
  return out;
}

double residualHeadingRad(const DutyCycle& cycle, const NeedleParams3& params,
                          double cycle_length_m) {
  return cycle.spin_fraction * cycle.spin_fraction * params.kappa_max_per_m * cycle_length_m /
         (2.0 * kPi);
}

NoiseParams3 NoiseParams3::scaled(double factor) const {
  NoiseParams3 out = *this;
  out.sigma_insert_rad *= factor;
  out.sigma_spin_rad *= factor;
  out.sigma_roll_rad *= factor;
  return out;
}

void NoiseParams3::validate() const {
  const char* where = "NoiseParams3";
  requireFinite(where, "sigma_insert_rad", sigma_insert_rad, false);
  requireFinite(where, "sigma_spin_rad", sigma_spin_rad, false);
  requireFinite(where, "sigma_roll_rad", sigma_roll_rad, false);
}

NoisyNeedle3::NoisyNeedle3(NeedleParams3 params, NoiseParams3 noise, std::uint64_t seed)
    : params_(params), noise_(noise), rng_(seed) {
  params_.validate();
  noise_.validate();
}

StepRecord NoisyNeedle3::step(const TipPose3& pose, const Control3& control) {
  if (!std::isfinite(control.rotate_rad) || !std::isfinite(control.curvature_per_m) ||
      !(control.curvature_per_m >= 0.0) || !std::isfinite(control.length_m) ||
      !(control.length_m >= 0.0)) {
    std::ostringstream os;
    os << "NoisyNeedle3::step: control (rotate " << control.rotate_rad << " rad, curvature "
       << control.curvature_per_m << " 1/m, length " << control.length_m
       << " m) must be finite with curvature and length >= 0";
    throw std::invalid_argument(os.str());
  }
  // Always three draws per step (common random numbers across policies).
  const double z_d = normal_(rng_);
  const double z_n = normal_(rng_);
  const double z_roll = normal_(rng_);
  const bool rotated = control.rotate_rad != 0.0;
  StepRecord record;
  record.path.push_back(pose.p_SceneTip);
  TipPose3 current = pose;
  if (rotated) {
    current = rotateBevel(current, control.rotate_rad + noise_.sigma_roll_rad * z_roll);
  }
  const double sigma = rotated ? noise_.sigma_spin_rad : noise_.sigma_insert_rad;
  record.deflection_rad = Vector3(noise_.in_plane_only ? 0.0 : sigma * z_d, sigma * z_n, 0.0);
  current = deflect(current, record.deflection_rad);
  record.cycle =
      dutyCycleFor(control.curvature_per_m, params_, cycleLength(control.length_m, params_));
  record.pose = insertDutyCycled(current, record.cycle, control.length_m, params_, &record.path);
  return record;
}

}  // namespace needle_guidance::needle_model
