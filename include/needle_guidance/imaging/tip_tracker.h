// Needle-tip tracking from images (DESIGN.md, tip_tracker row; dissertation 5.5: the tip is
// localised in an image after every insertion step). Per frame: enhance thin curvilinear
// structures (ridge filter) in a window around the predicted tip, fit a constant-curvature arc
// of the needle's known radius with RANSAC and least squares, and take the tip at the far end
// of the arc along the insertion direction; a filter over (x, y, theta) predicts from the
// robot's own motion (inserted length and bevel, dissertation 5.3's arcs) and fuses each
// detection that passes a chi-square gate, so dropped or unusable frames are bridged and a
// detection far from the prediction is never accepted silently. Baseline: OpenCV HoughLinesP.
// Plain C++ and OpenCV; no ROS (STYLE.md rules 1-2).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <opencv2/core.hpp>
#include <optional>
#include <string>

#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance::imaging {

/// What the tracker knows of the device and the needle.
struct TrackerConfig {
  Modality modality = Modality::kUltrasound;  ///< polarity and clutter model of the frames
  ImageGeometry geometry;                     ///< calibration of the frames it will get
  /// Radius of curvature of the needle's arcs [m], > 0 (bevel left: counter-clockwise).
  double radius_of_curvature_m = 0.05;
  double needle_diameter_m = 0.5e-3;  ///< expected width of the needle in the image [m], > 0
  /// Motion model (dissertation 5.3): heading deflection per insertion step of length
  /// step_length_m, sigma_insert after a plain insertion, sigma_flip after a bevel flip [rad].
  double sigma_insert_rad = 0.0;
  double sigma_flip_rad = 0.0;
  double step_length_m = 0.00785;  ///< insertion distance delta the deflection is drawn over [m]
  /// Half size of the search window around the predicted tip beyond its 3-sigma ellipse [m].
  double search_margin_m = 5e-3;
  /// Chi-square gate (3 degrees of freedom) on the innovation of a detection; 16.27 = 99.9 %.
  double gate_chi2 = 16.27;
  /// An estimate is `confident` only if its position standard deviation (largest axis) and
  /// heading standard deviation are at most these.
  double confident_position_std_m = 0.5e-3;
  double confident_heading_std_rad = 0.035;  // 2 degrees
  /// Throws std::invalid_argument naming the field and value when out of range.
  void validate() const;
};

/// The tracker's configuration for a scene and the device that images it: radius of curvature,
/// sigmas and step length from the scene's needle and steering sections, modality and
/// calibration from `imager`. Throws std::invalid_argument if the scene is not a steering scene.
TrackerConfig trackerConfigFromScene(const scene::Scene& scene, const ImagerConfig& imager);

/// One frame's detection, before any filtering.
struct Detection {
  bool found = false;
  std::string message;  ///< why not found, or a one-line summary of the fit
  Point2 p_SceneTip = Point2::Zero();  ///< [m]
  double theta_rad = 0.0;              ///< tangent at the tip, along the insertion direction [rad]
  /// Covariance of (x [m], y [m], theta [rad]) from the fit residuals and the tip profile.
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Identity();
  int inliers = 0;              ///< ridge points on the fitted arc
  double residual_rms_m = 0.0;  ///< RMS distance of the inliers from the arc [m]
};

/// Where to look: the predicted tip with its uncertainty, and which way the needle curves.
struct SearchPrior {
  steering::TipPose tip;  ///< predicted tip; tip.bevel sets the sign of the last arc's curvature
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Zero();  ///< of (x, y, theta)
};

/// Why `frame` cannot be used as a frame of `geometry`, or "" if it can: empty (a dropped
/// frame), not CV_8UC1 (e.g. CV_16UC1 or CV_8UC3), not geometry.size(), or no contrast (every
/// pixel within a few grey levels of each other, e.g. all zeros). Never throws.
std::string frameProblem(const cv::Mat& frame, const ImageGeometry& geometry);

/// The pixel rectangle (clipped to the frame) that detectTip and houghBaselineTip search: the
/// whole frame without a prior; with one, the discs of radius 3 sigma (largest position axis) +
/// search_margin_m around the predicted tip and around points up to kSearchBackLength_m back
/// along the predicted arc (their radius also grows with 3 sigma of the heading times the
/// distance), so that enough of the shaft is inside to fit the arc. May be empty if the prior
/// lies far outside the frame. Never throws (non-finite priors give the whole frame).
cv::Rect searchWindow(const TrackerConfig& config, const std::optional<SearchPrior>& prior);
/// How far back along the predicted needle searchWindow reaches [m].
constexpr double kSearchBackLength_m = 10e-3;

/// Single-frame detector: ridge filter in the prior's window (the whole frame without prior),
/// RANSAC arc of the known radius (both curvature signs without prior), least-squares refit,
/// tip at the far end along the insertion direction (sub-pixel, half-maximum of the needle's
/// intensity profile along the arc). Never throws for a bad frame: returns found = false with the
/// reason. `frame` must be CV_8UC1 of config.geometry.size().
Detection detectTip(const cv::Mat& frame, const TrackerConfig& config,
                    const std::optional<SearchPrior>& prior);

/// Baseline: Gaussian blur, Canny, cv::HoughLinesP in the same window as detectTip, the longest
/// segment, its end farther along the prior heading (+x without prior) as the tip and its
/// direction as the heading. Same contract as detectTip.
Detection houghBaselineTip(const cv::Mat& frame, const TrackerConfig& config,
                           const std::optional<SearchPrior>& prior);

/// Status of a tracker estimate.
enum class TrackStatus : std::uint8_t {
  kUninitialized,  ///< no entry pose and no acquisition yet: the pose means nothing
  kEntry,          ///< nothing inserted: the pose is the needle guide's (known)
  kTracked,        ///< this frame's detection passed the gate and was fused
  kPredicted,      ///< no usable detection in this frame (or it failed the gate): predicted only
  kOutOfView,      ///< the predicted tip is outside the frame: predicted only
  kBadFrame,       ///< the frame was unusable (empty, wrong size or encoding, no contrast)
};
/// "uninitialized" | "entry" | "tracked" | "predicted" | "out_of_view" | "bad_frame".
std::string toString(TrackStatus status);

/// The tracker's output for one frame (or one motion update).
struct TipEstimate {
  TrackStatus status = TrackStatus::kUninitialized;
  std::string message;                 ///< one line: what happened and why
  steering::TipPose tip;               ///< filtered pose; bevel from the robot [m, rad]
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Identity();  ///< of (x, y, theta), finite
  /// Position and heading standard deviations within the configured limits, and the status is
  /// kEntry or kTracked. Never true for a pose that was not confirmed by an image (or the guide).
  bool confident = false;
  double inserted_length_m = 0.0;  ///< from the robot [m]
  Detection detection;             ///< this frame's raw detection (found = false if none)
};

/// Temporal filter (extended Kalman over x, y, theta) around detectTip.
class TipTracker {
public:
  /// Throws std::invalid_argument from config.validate().
  explicit TipTracker(const TrackerConfig& config);

  /// A new insertion starts from the needle guide: the tip is at `entry` (inserted length 0)
  /// with the given standard deviations (the guide is known precisely; small but > 0).
  void reset(const steering::TipPose& entry, double position_std_m = 0.1e-3,
             double heading_std_rad = 0.005);
  /// The robot's proprioception: inserted length now and the current bevel; `flips` counts
  /// bevel flips since the entry. A longer length predicts the tip along an arc of the bevel's
  /// direction and grows the heading variance (sigma_flip if a flip came since the last
  /// advance, else sigma_insert, per step_length_m); a shorter one moves it back along the
  /// arc. Non-finite or negative lengths are ignored with the returned status saying so.
  TipEstimate onDrive(double inserted_length_m, steering::Bevel bevel, std::uint32_t flips);
  /// One frame: validate, detect around the prediction, gate, fuse. Bad frames and missed or
  /// gated detections leave the filter at its prediction and say why.
  TipEstimate onFrame(const cv::Mat& frame);

  /// The current estimate (status of the last update).
  const TipEstimate& estimate() const { return estimate_; }
  const TrackerConfig& config() const { return config_; }

  /// Consecutive gated-out detections that agree with each other (after the robot's motion
  /// between them, over at least kReacquireMinTravel_m of insertion) after which the tracker
  /// re-acquires from the latest one with its covariance inflated by kReacquireInflation
  /// (status kTracked, never confident on that frame, message "re-acquired ...").
  static constexpr int kReacquireAfter = 3;
  static constexpr double kReacquireInflation = 4.0;
  static constexpr double kReacquireMinTravel_m = 1e-3;

private:
  /// A gated-out detection kept to check whether the next ones agree with it.
  struct Rejected {
    steering::TipPose pose;
    Eigen::Matrix3d covariance = Eigen::Matrix3d::Identity();
    double inserted_length_m = 0.0;
    int agreeing = 0;           ///< how many consecutive rejected detections agree, this included
    double travel_m = 0.0;      ///< insertion travelled across them [m]
  };

  /// Moves the state from inserted length `from_m` to `to_m` along the arc of `bevel`, growing
  /// the covariance: the heading deflection of an insertion step (sigma_flip for the first step
  /// after a flip, else sigma_insert) is added whole where its step begins — steps of
  /// step_length_m counted from the entry or the last flip, as the robot's steps are — and a
  /// small position noise per length travelled.
  void predict(double from_m, double to_m, steering::Bevel bevel);
  /// Propagates the state along the arc by ds (either sign) in sub-steps.
  void move(double ds_m, steering::Bevel bevel);
  /// Fills estimate_.confident from the status and the covariance.
  void updateConfidence();
  /// Whether the mean and covariance are finite (and the covariance symmetric PSD-ish).
  bool stateFinite() const;

  TrackerConfig config_;
  TipEstimate estimate_;
  bool initialized_ = false;   ///< an entry pose or an acquisition gave the state a meaning
  bool have_entry_ = false;    ///< reset() gave a guide pose (used again when retracted to 0)
  steering::TipPose entry_;
  Eigen::Matrix3d entry_covariance_ = Eigen::Matrix3d::Identity();
  double length_m_ = 0.0;      ///< inserted length the state refers to [m]
  std::uint32_t flips_ = 0;
  bool flip_pending_ = false;       ///< the next step's deflection is drawn with sigma_flip
  double step_origin_m_ = 0.0;      ///< steps of step_length_m are counted from here [m]
  double deflected_until_m_ = 0.0;  ///< the deflection of travel up to here is in P [m]
  std::optional<Rejected> rejected_;
};

}  // namespace needle_guidance::imaging
