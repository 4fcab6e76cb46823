// Needle-tip tracker (tip_tracker.h): configuration, and the extended Kalman filter over
// (x, y, theta) that predicts from the robot's inserted length and bevel (dissertation 5.3's
// arcs, needle_model::advanceTip) and fuses detectTip's detections behind a chi-square gate.
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/math.h"

#include "detection_util.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::imaging {
namespace {

using detail::fmt;
using detail::wrapAngle;

constexpr double kDeg = kPi / 180.0;
/// The prediction is applied in sub-steps of at most this fraction of step_length_m, so the
/// linearisation of the arc stays accurate for long drives.
constexpr double kMaxSubstepFraction = 0.25;
/// Position process noise per metre travelled, beyond the heading deflections: the arc model's
/// mismatch (radius, tissue) [m^2 / m].
constexpr double kPositionNoisePerLength_m2_per_m = (0.05e-3 * 0.05e-3) / 1e-3;
/// Heading process noise on retraction per metre (the path is retraced, nearly exactly).
constexpr double kRetractHeadingNoise_rad2_per_m = (0.5 * kDeg) * (0.5 * kDeg) / 1e-2;
/// Longer inserted lengths are refused as implausible (a needle is centimetres long) [m].
constexpr double kMaxInsertedLength_m = 10.0;
/// Re-acquisition: consecutive rejected detections must advance along the needle by the
/// robot's travel to within the larger of these [m] and this fraction of the travel.
constexpr double kReacquireAdvanceTolerance_m = 0.5e-3;
constexpr double kReacquireAdvanceFraction = 0.3;
/// The filtered covariance never gets below these standard deviations (x, y [m]; heading
/// [rad]): the floor of errors that repeated frames share.
constexpr double kMinPositionStd_m = 0.03e-3;
constexpr double kMinHeadingStd_rad = 0.3 * kDeg;
/// Predicted tips within this distance outside the frame border still count as in view [px]
/// (none: a tip outside the pixels cannot be seen).
constexpr double kOutOfViewTolerance_px = 0.0;

Eigen::Vector3d poseVector(const needle_model::TipPose& p) {
  return {p.p_SceneTip.x(), p.p_SceneTip.y(), p.theta_rad};
}

Eigen::Matrix3d symmetrised(const Eigen::Matrix3d& m) {
  return 0.5 * (m + m.transpose());
}

void requireRange(bool ok, const char* field, double value) {
  if (!ok) {
    std::ostringstream s;
    s << "TrackerConfig: " << field << " = " << value << " is out of range";
    throw std::invalid_argument(s.str());
  }
}

}  // namespace

void TrackerConfig::validate() const {
  geometry.validate("TrackerConfig.geometry");
  const auto pos = [](double v) { return std::isfinite(v) && v > 0.0; };
  const auto nonneg = [](double v) { return std::isfinite(v) && v >= 0.0; };
  requireRange(pos(radius_of_curvature_m), "radius_of_curvature_m", radius_of_curvature_m);
  requireRange(pos(needle_diameter_m), "needle_diameter_m", needle_diameter_m);
  requireRange(nonneg(sigma_insert_rad), "sigma_insert_rad", sigma_insert_rad);
  requireRange(nonneg(sigma_flip_rad), "sigma_flip_rad", sigma_flip_rad);
  requireRange(pos(step_length_m), "step_length_m", step_length_m);
  requireRange(nonneg(search_margin_m), "search_margin_m", search_margin_m);
  requireRange(pos(gate_chi2), "gate_chi2", gate_chi2);
  requireRange(pos(confident_position_std_m), "confident_position_std_m", confident_position_std_m);
  requireRange(pos(confident_heading_std_rad), "confident_heading_std_rad",
               confident_heading_std_rad);
}

TrackerConfig trackerConfigFromScene(const scene::Scene& scene, const ImagerConfig& imager) {
  if (!scene.steering) {
    throw std::invalid_argument("trackerConfigFromScene: scene '" + scene.name +
                                "' has no steering section");
  }
  TrackerConfig c;
  c.modality = imager.modality;
  c.geometry = imager.geometry;
  c.radius_of_curvature_m = scene.needle.radius_of_curvature_m;
  c.needle_diameter_m = imager.needle_diameter_m;
  c.sigma_insert_rad = scene.steering->sigma_insert_rad;
  c.sigma_flip_rad = scene.steering->sigma_flip_rad;
  c.step_length_m = 2.0 * kPi * c.radius_of_curvature_m / scene.steering->orientations;
  c.validate();
  return c;
}

std::string toString(MotionModel model) {
  switch (model) {
    case MotionModel::kDrive:
      return "drive";
    case MotionModel::kAxis:
      return "axis";
    case MotionModel::kAuto:
      break;
  }
  return "auto";
}

std::optional<MotionModel> motionModelFromString(const std::string& name) {
  for (const MotionModel m : {MotionModel::kAuto, MotionModel::kDrive, MotionModel::kAxis}) {
    if (toString(m) == name) {
      return m;
    }
  }
  return std::nullopt;
}

MotionModel chooseMotionModel(MotionModel setting, bool drive_available) {
  if (setting != MotionModel::kAuto) {
    return setting;
  }
  return drive_available ? MotionModel::kDrive : MotionModel::kAxis;
}

std::string toString(TrackStatus status) {
  switch (status) {
    case TrackStatus::kUninitialized:
      return "uninitialized";
    case TrackStatus::kEntry:
      return "entry";
    case TrackStatus::kTracked:
      return "tracked";
    case TrackStatus::kPredicted:
      return "predicted";
    case TrackStatus::kOutOfView:
      return "out_of_view";
    case TrackStatus::kBadFrame:
      return "bad_frame";
  }
  return "unknown";
}

TipTracker::TipTracker(const TrackerConfig& config) : config_(config) {
  config_.validate();
  estimate_.message = "no entry pose yet";
}

void TipTracker::reset(const needle_model::TipPose& entry, double position_std_m,
                       double heading_std_rad) {
  if (!(entry.p_SceneTip.allFinite() && std::isfinite(entry.theta_rad)) ||
      !(std::isfinite(position_std_m) && position_std_m > 0.0) ||
      !(std::isfinite(heading_std_rad) && heading_std_rad > 0.0)) {
    throw std::invalid_argument(
        "TipTracker::reset: entry pose and standard deviations must be "
        "finite (and the deviations > 0)");
  }
  entry_ = entry;
  entry_covariance_ =
      Eigen::Vector3d(position_std_m * position_std_m, position_std_m * position_std_m,
                      heading_std_rad * heading_std_rad)
          .asDiagonal();
  have_entry_ = true;
  initialized_ = true;
  length_m_ = 0.0;
  flips_ = 0;
  flip_pending_ = false;
  step_origin_m_ = 0.0;
  deflected_until_m_ = 0.0;
  flip_length_m_ = -1.0;
  rejected_.reset();
  confirm_.reset();
  estimate_ = TipEstimate{};
  estimate_.status = TrackStatus::kEntry;
  estimate_.tip = entry;
  estimate_.covariance = entry_covariance_;
  estimate_.inserted_length_m = 0.0;
  estimate_.message = "entry pose from the needle guide";
  updateConfidence();
}

void TipTracker::move(double ds_m, needle_model::Bevel bevel) {
  needle_model::TipPose& tip = estimate_.tip;
  Eigen::Matrix3d& cov = estimate_.covariance;
  const double r = config_.radius_of_curvature_m;
  const double max_sub = kMaxSubstepFraction * config_.step_length_m;
  const int substeps = std::max(1, static_cast<int>(std::ceil(std::abs(ds_m) / max_sub)));
  const double ds = ds_m / substeps;
  for (int k = 0; k < substeps; ++k) {
    // Along the arc (backwards: the same circle traced with the reversed tangent).
    needle_model::TipPose from = tip;
    from.bevel = bevel;
    needle_model::TipPose to;
    if (ds >= 0.0) {
      to = needle_model::advanceTip(from, needle_model::Control::kInsert, 0.0, ds, r);
    } else {
      const needle_model::TipPose rev{from.p_SceneTip, from.theta_rad + kPi,
                                      needle_model::flipped(bevel)};
      to = needle_model::advanceTip(rev, needle_model::Control::kInsert, 0.0, -ds, r);
      to.theta_rad -= kPi;
      to.bevel = bevel;
    }
    // Jacobian of the end pose in the start pose: translations pass through, a heading change
    // rotates the whole arc about its start, moving the end by the rotated chord.
    const Point2 chord = to.p_SceneTip - from.p_SceneTip;
    Eigen::Matrix3d jac = Eigen::Matrix3d::Identity();
    jac(0, 2) = -chord.y();
    jac(1, 2) = chord.x();
    cov = symmetrised(jac * cov * jac.transpose());
    const double q_pos = kPositionNoisePerLength_m2_per_m * std::abs(ds);
    cov(0, 0) += q_pos;
    cov(1, 1) += q_pos;
    if (ds < 0.0) {
      cov(2, 2) += kRetractHeadingNoise_rad2_per_m * std::abs(ds);
    }
    tip = to;
  }
  tip.theta_rad = wrapAngle(tip.theta_rad);
  tip.bevel = bevel;
}

void TipTracker::predict(double from_m, double to_m, needle_model::Bevel bevel) {
  if (to_m < from_m) {
    move(to_m - from_m, bevel);
    // A later insertion starts a new step here.
    step_origin_m_ = to_m;
    deflected_until_m_ = to_m;
    if (flip_length_m_ > to_m) {
      flip_length_m_ = -1.0;  // retracted past the flip: its kink is no longer in the needle
    }
    return;
  }
  const double step = config_.step_length_m;
  constexpr double kTolerance_m = 1e-9;  // lengths this close count as equal
  double at = from_m;
  while (at < to_m) {
    if (deflected_until_m_ <= at + kTolerance_m) {
      // A new step begins at or before `at`: its deflection enters now, whole.
      const double sigma = flip_pending_ ? config_.sigma_flip_rad : config_.sigma_insert_rad;
      estimate_.covariance(2, 2) += sigma * sigma;
      flip_pending_ = false;
      deflected_until_m_ = std::max(deflected_until_m_, step_origin_m_);
      while (deflected_until_m_ <= at + kTolerance_m) {
        deflected_until_m_ += step;
      }
    }
    const double next = std::min(to_m, deflected_until_m_);
    move(next - at, bevel);
    at = next;
  }
}

bool TipTracker::stateFinite() const {
  return estimate_.tip.p_SceneTip.allFinite() && std::isfinite(estimate_.tip.theta_rad) &&
         estimate_.covariance.allFinite();
}

void TipTracker::updateConfidence() {
  const auto& cov = estimate_.covariance;
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> es(
      0.5 * (cov.topLeftCorner<2, 2>() + cov.topLeftCorner<2, 2>().transpose()));
  const double pos_std = std::sqrt(std::max(0.0, es.eigenvalues().maxCoeff()));
  const double heading_std = std::sqrt(std::max(0.0, cov(2, 2)));
  // A step's deflection kinks the needle where the step began; over the first few millimetres
  // after it the new heading is seen on too short an arc to be trusted.
  const bool step_known = deflected_until_m_ > step_origin_m_;
  const double since_step =
      step_known ? length_m_ - (deflected_until_m_ - config_.step_length_m) : 0.0;
  const bool heading_settled = !step_known || since_step >= kMinStepAdvanceForConfidence_m;
  estimate_.confident = (estimate_.status == TrackStatus::kEntry ||
                         (estimate_.status == TrackStatus::kTracked && heading_settled)) &&
                        initialized_ && stateFinite() && !confirm_ &&
                        pos_std <= config_.confident_position_std_m &&
                        heading_std <= config_.confident_heading_std_rad;
}

TipEstimate TipTracker::onDrive(double inserted_length_m, needle_model::Bevel bevel,
                                std::uint32_t flips) {
  if (!std::isfinite(inserted_length_m) || inserted_length_m < 0.0 ||
      inserted_length_m > kMaxInsertedLength_m) {
    TipEstimate out = estimate_;
    out.message = "drive ignored: inserted length " + fmt(inserted_length_m * 1e3) +
                  " mm is not a finite length in [0, " + fmt(kMaxInsertedLength_m * 1e3, 0) +
                  "] mm";
    return out;
  }
  if (flips != flips_) {
    // A flip: the next insertion step starts here and deflects with sigma_flip.
    flip_pending_ = true;
    step_origin_m_ = length_m_;
    deflected_until_m_ = length_m_;
    flip_length_m_ = length_m_;
    flips_ = flips;
  }
  estimate_.detection = Detection{};
  if (!initialized_) {
    length_m_ = inserted_length_m;
    estimate_.tip.bevel = bevel;
    estimate_.inserted_length_m = inserted_length_m;
    estimate_.message = "no entry pose and no acquisition yet";
    updateConfidence();
    return estimate_;
  }
  const double delta = inserted_length_m - length_m_;
  const TipEstimate before = estimate_;
  if (inserted_length_m == 0.0 && have_entry_) {
    // Back at (or still at) the needle guide: its pose is known.
    const needle_model::Bevel b = bevel;
    estimate_.tip = entry_;
    estimate_.tip.bevel = b;
    estimate_.covariance = entry_covariance_;
    estimate_.status = TrackStatus::kEntry;
    estimate_.message = "nothing inserted: the needle guide's pose";
    step_origin_m_ = 0.0;
    deflected_until_m_ = 0.0;
    flip_length_m_ = -1.0;
    confirm_.reset();
    rejected_.reset();
  } else if (delta == 0.0) {
    estimate_.tip.bevel = bevel;  // e.g. a flip in place: the tip does not move
    estimate_.message = "no insertion change";
  } else {
    predict(length_m_, inserted_length_m, bevel);
    estimate_.status = TrackStatus::kPredicted;
    estimate_.message = "predicted along the " + needle_model::toString(bevel) + " arc by " +
                        fmt(delta * 1e3) + " mm";
  }
  if (!stateFinite()) {
    estimate_ = before;
    estimate_.message = "drive ignored: the prediction was not finite";
    updateConfidence();
    return estimate_;
  }
  length_m_ = inserted_length_m;
  estimate_.inserted_length_m = inserted_length_m;
  updateConfidence();
  return estimate_;
}

TipEstimate TipTracker::onFrame(const cv::Mat& frame) {
  estimate_.detection = Detection{};
  const std::string problem = frameProblem(frame, config_.geometry);
  if (!problem.empty()) {
    estimate_.status = TrackStatus::kBadFrame;
    estimate_.message = "bad frame: " + problem;
    estimate_.detection.message = problem;
    updateConfidence();
    return estimate_;
  }
  if (!initialized_) {
    return acquireWithoutPrior(frame);
  }
  if (have_entry_ && length_m_ == 0.0) {
    estimate_.status = TrackStatus::kEntry;
    estimate_.message = "nothing inserted: the needle guide's pose";
    updateConfidence();
    return estimate_;
  }
  const ImageGeometry& g = config_.geometry;
  const cv::Point2d px = g.toPixel(estimate_.tip.p_SceneTip);
  if (px.x < -0.5 - kOutOfViewTolerance_px || px.y < -0.5 - kOutOfViewTolerance_px ||
      px.x > g.cols - 0.5 + kOutOfViewTolerance_px ||
      px.y > g.rows - 0.5 + kOutOfViewTolerance_px) {
    estimate_.status = TrackStatus::kOutOfView;
    estimate_.message = "predicted tip outside the frame (pixel " + fmt(px.x, 1) + ", " +
                        fmt(px.y, 1) + "): predicted only";
    updateConfidence();
    return estimate_;
  }
  const Detection d = detectTip(frame, config_, searchPrior());
  estimate_.detection = d;
  if (!d.found) {
    estimate_.status = TrackStatus::kPredicted;
    estimate_.message = "no detection (" + d.message + "): predicted only";
    updateConfidence();
    return estimate_;
  }
  // Chi-square gate on the innovation.
  const Eigen::Vector3d x = poseVector(estimate_.tip);
  Eigen::Vector3d nu(d.p_SceneTip.x() - x.x(), d.p_SceneTip.y() - x.y(),
                     wrapAngle(d.theta_rad - x.z()));
  const Eigen::Matrix3d innovation_cov = symmetrised(estimate_.covariance + d.covariance);
  const Eigen::LDLT<Eigen::Matrix3d> ldlt(innovation_cov);
  const double d2 = nu.dot(ldlt.solve(nu));
  if (!std::isfinite(d2) || d2 > config_.gate_chi2) {
    return onGatedOut(d, d2);
  }
  rejected_.reset();
  return fuse(d, nu, ldlt, d2);
}

TipEstimate TipTracker::acquireWithoutPrior(const cv::Mat& frame) {
  {  // (indented as it was inside onFrame)
    // Acquisition without any prior: the whole frame, both curvature senses.
    Detection d = detectTip(frame, config_, std::nullopt);
    estimate_.detection = d;
    if (!d.found) {
      estimate_.status = TrackStatus::kUninitialized;
      estimate_.message = "no acquisition: " + d.message;
      updateConfidence();
      return estimate_;
    }
    const needle_model::Bevel bevel = estimate_.tip.bevel;
    estimate_.tip = {d.p_SceneTip, d.theta_rad, bevel};
    estimate_.covariance = symmetrised(kReacquireInflation * d.covariance);
    estimate_.status = TrackStatus::kTracked;
    estimate_.message =
        "acquired without a prior (not confident until confirmed by the "
        "robot's motion): " +
        d.message;
    initialized_ = true;
    confirmWith(d, true);
    updateConfidence();
    return estimate_;
  }
}

SearchPrior TipTracker::searchPrior() const {
  SearchPrior prior;
  prior.tip = estimate_.tip;
  prior.covariance = estimate_.covariance;
  // The needle's last arc began at the last flip, or at the entry (the guide holds it straight
  // before), so the needle before it curves the other way or is not there.
  if (flip_length_m_ >= 0.0) {
    prior.length_since_flip_m = length_m_ - flip_length_m_;
  } else if (have_entry_) {
    prior.length_since_flip_m = length_m_;
  }
  if (deflected_until_m_ > step_origin_m_) {
    // Steps of step_length_m from the entry or the last flip, as the robot inserts them.
    prior.length_since_step_m = length_m_ - (deflected_until_m_ - config_.step_length_m);
  }
  return prior;
}

TipEstimate TipTracker::onGatedOut(const Detection& d, double d2) {
  // Gated out. Does it agree with the previous rejected detections (moved by the robot)?
  Rejected now;
  now.pose = {d.p_SceneTip, d.theta_rad, estimate_.tip.bevel};
  now.covariance = d.covariance;
  now.inserted_length_m = length_m_;
  now.agreeing = 1;
  if (rejected_) {
    const double travel = length_m_ - rejected_->inserted_length_m;
    needle_model::TipPose moved = rejected_->pose;
    moved.bevel = estimate_.tip.bevel;
    if (travel > 0.0) {
      moved = needle_model::advanceTip(moved, needle_model::Control::kInsert, 0.0, travel,
                                       config_.radius_of_curvature_m);
    }
    const double sig2 = std::max(config_.sigma_insert_rad, config_.sigma_flip_rad);
    Eigen::Matrix3d agree_cov = rejected_->covariance + d.covariance;
    agree_cov(2, 2) += sig2 * sig2 * std::max(travel, 0.0) / config_.step_length_m;
    const double q = std::max(travel, 0.0) * std::max(sig2, 1e-3);
    agree_cov(0, 0) += q * q;
    agree_cov(1, 1) += q * q;
    Eigen::Vector3d e(d.p_SceneTip.x() - moved.p_SceneTip.x(),
                      d.p_SceneTip.y() - moved.p_SceneTip.y(),
                      wrapAngle(d.theta_rad - moved.theta_rad));
    const double a2 = e.dot(symmetrised(agree_cov).ldlt().solve(e));
    // ... and they must move with the needle: the detected advance along the needle matches
    // the robot's (a static structure, e.g. where the needle enters an acoustic shadow, does
    // not move when the needle does).
    const Point2 dir(std::cos(rejected_->pose.theta_rad), std::sin(rejected_->pose.theta_rad));
    const double advance = (d.p_SceneTip - rejected_->pose.p_SceneTip).dot(dir);
    const bool moves_with_needle =
        std::abs(advance - travel) <=
        std::max(kReacquireAdvanceTolerance_m, kReacquireAdvanceFraction * travel);
    if (travel >= 0.0 && std::isfinite(a2) && a2 <= config_.gate_chi2 && moves_with_needle) {
      now.agreeing = rejected_->agreeing + 1;
      now.travel_m = rejected_->travel_m + travel;
    }
  }
  rejected_ = now;
  if (now.agreeing >= kReacquireAfter && now.travel_m >= kReacquireMinTravel_m) {
    estimate_.tip = now.pose;
    estimate_.covariance = symmetrised(kReacquireInflation * d.covariance);
    estimate_.status = TrackStatus::kTracked;
    estimate_.message = "re-acquired: " + std::to_string(now.agreeing) +
                        " consecutive detections agreed with each other but not with the "
                        "prediction (last d2 = " +
                        fmt(d2, 1) + "); covariance inflated";
    rejected_.reset();
    confirmWith(d, true);
    updateConfidence();
    return estimate_;
  }
  estimate_.status = TrackStatus::kPredicted;
  estimate_.message = "detection gated out (d2 = " + fmt(d2, 1) + " > " +
                      fmt(config_.gate_chi2, 2) + ", " + std::to_string(now.agreeing) +
                      " in a row agree): predicted only";
  updateConfidence();
  return estimate_;
}

TipEstimate TipTracker::fuse(const Detection& d, const Eigen::Vector3d& nu,
                             const Eigen::LDLT<Eigen::Matrix3d>& ldlt, double d2) {
  // Kalman update (Joseph form).
  const TipEstimate before = estimate_;
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> prior_es(
      estimate_.covariance.topLeftCorner<2, 2>());
  const bool wide_prior =
      std::sqrt(std::max(0.0, prior_es.eigenvalues().maxCoeff())) > kConfirmPriorStd_m;
  const Eigen::Matrix3d gain = ldlt.solve(estimate_.covariance.transpose()).transpose();
  const Eigen::Vector3d dx = gain * nu;
  const Eigen::Matrix3d i_kh = Eigen::Matrix3d::Identity() - gain;
  estimate_.covariance = symmetrised(i_kh * estimate_.covariance * i_kh.transpose() +
                                     gain * d.covariance * gain.transpose());
  estimate_.tip.p_SceneTip += dx.head<2>();
  estimate_.tip.theta_rad = wrapAngle(estimate_.tip.theta_rad + dx.z());
  // Floor: repeated frames of a needle that did not move share their errors (the static
  // speckle and anatomy), so fusing them must not shrink the covariance without bound.
  for (int k = 0; k < 3; ++k) {
    const double floor =
        k < 2 ? kMinPositionStd_m * kMinPositionStd_m : kMinHeadingStd_rad * kMinHeadingStd_rad;
    estimate_.covariance(k, k) = std::max(estimate_.covariance(k, k), floor);
  }
  if (!stateFinite()) {
    estimate_ = before;
    estimate_.status = TrackStatus::kPredicted;
    estimate_.message = "update skipped: not finite; predicted only";
    updateConfidence();
    return estimate_;
  }
  estimate_.status = TrackStatus::kTracked;
  estimate_.message = "fused (d2 = " + fmt(d2, 2) + "): " + d.message;
  if (wide_prior || confirm_) {
    confirmWith(d, wide_prior);
    if (confirm_) {
      estimate_.message +=
          " (wide prediction: not confident until " + std::to_string(kConfirmDetections) +
          " detections move with the robot; " + std::to_string(confirm_->count) + " so far)";
    }
  }
  updateConfidence();
  return estimate_;
}

void TipTracker::confirmWith(const Detection& d, bool start) {
  if (start || !confirm_) {
    confirm_ = Confirmation{d.p_SceneTip, d.theta_rad, length_m_, 0, 0.0};
    return;
  }
  const double travel = length_m_ - confirm_->inserted_length_m;
  const Point2 dir(std::cos(confirm_->theta_rad), std::sin(confirm_->theta_rad));
  const double advance = (d.p_SceneTip - confirm_->p_SceneTip).dot(dir);
  const bool moves = travel >= 0.0 &&
                     std::abs(advance - travel) <=
                         std::max(kReacquireAdvanceTolerance_m, kReacquireAdvanceFraction * travel);
  if (moves) {
    confirm_->count += 1;
    confirm_->travel_m += travel;
  } else {
    confirm_->count = 0;
    confirm_->travel_m = 0.0;
  }
  confirm_->p_SceneTip = d.p_SceneTip;
  confirm_->theta_rad = d.theta_rad;
  confirm_->inserted_length_m = length_m_;
  if (confirm_->count >= kConfirmDetections && confirm_->travel_m >= kConfirmTravel_m) {
    confirm_.reset();
  }
}

}  // namespace needle_guidance::imaging
