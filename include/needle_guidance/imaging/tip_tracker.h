// Needle-tip tracking from images (dissertation 5.5: the tip is
// localised in an image after every insertion step). Per frame: enhance thin curvilinear
// structures (ridge filter) in a window around the predicted tip, fit a constant-curvature arc
// of the needle's known radius with RANSAC and least squares, and take the tip at the far end
// of the arc along the insertion direction; a filter over (x, y, theta) predicts from the
// robot's own motion (inserted length and bevel, dissertation 5.3's arcs) and fuses each
// detection that passes a chi-square gate, so dropped or unusable frames are bridged and a
// detection far from the prediction is never accepted silently. Baseline: OpenCV HoughLinesP.
// Plain C++ and OpenCV; no ROS.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <limits>
#include <opencv2/core.hpp>
#include <optional>
#include <string>

#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/needle_model/needle_2d.h"

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
  std::string message;                 ///< why not found, or a one-line summary of the fit
  Point2 p_SceneTip = Point2::Zero();  ///< [m]
  double theta_rad = 0.0;              ///< tangent at the tip, along the insertion direction [rad]
  /// Covariance of (x [m], y [m], theta [rad]) from the fit residuals and the tip profile.
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Identity();
  int inliers = 0;              ///< ridge points on the fitted arc
  double residual_rms_m = 0.0;  ///< RMS distance of the inliers from the arc [m]
};

/// Where to look: the predicted tip with its uncertainty, and which way the needle curves.
struct SearchPrior {
  needle_model::TipPose
      tip;  ///< predicted tip; tip.bevel sets the sign of the last arc's curvature
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Zero();  ///< of (x, y, theta)
  /// Inserted length since the bevel last flipped, or since the entry if it never did [m]: the
  /// needle's last arc (of tip.bevel's sense) is this long, and before it the needle curves the
  /// other way (the flip's kink in between) or is not in the tissue. +inf if unknown (then
  /// either sense is considered for the needle behind a kink).
  double length_since_flip_m = std::numeric_limits<double>::infinity();
  /// Inserted length since the current insertion step began [m] (its deflection kinks the
  /// needle there), +inf if unknown. Only a hint: kinks elsewhere are still considered.
  double length_since_step_m = std::numeric_limits<double>::infinity();
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
/// RANSAC arc of the known radius (both curvature signs without prior; in ultrasound a
/// reverberation echo is recognised as a dimmer copy deeper than the needle), least-squares
/// refit, the centre line traced along the arc through kinks, the tip at the far end along the
/// insertion direction (change point of the needle's cross-line contrast, which bridges the
/// gaps of a partly visible needle; sub-pixel at the end's steepest descent, minus the rounded
/// end's radius), the heading from a kink-aware refit of the last ~7 mm (kinks at a step's start
/// or a flip; see SearchPrior's lengths). The tip must lie in the frame. Never throws, never
/// returns NaN: a bad frame or a failed fit gives found = false with the reason. `frame` must be
/// CV_8UC1 of config.geometry.size(). Without a prior the whole frame is filtered (~15 ms for
/// 640 x 480); with one only its window (< 1 ms).
Detection detectTip(const cv::Mat& frame, const TrackerConfig& config,
                    const std::optional<SearchPrior>& prior);

/// Baseline: Gaussian blur, Canny (thresholds from the window's gradient quantiles),
/// cv::HoughLinesP in the same window as detectTip, the longest segment whose direction agrees
/// with the prior's heading (as detectTip's check), moved to the midline if Canny also found
/// the needle's other flank, its end farther along the prior heading (+x without prior) as the
/// tip and its direction as the heading. Same contract as detectTip.
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
/// How the tip is predicted between frames.
enum class MotionModel : std::uint8_t {
  kAuto,   ///< the robot's drive when it is available, otherwise the needle's own axis
  kDrive,  ///< TipTracker: the EKF predicts from the robot's drive (inserted length, bevel, flips)
  kAxis,   ///< SequenceTracker: acquisition without a prior, constant speed along the axis
};
/// "auto" | "drive" | "axis".
std::string toString(MotionModel model);
/// Inverse of toString(MotionModel); nullopt for anything else.
std::optional<MotionModel> motionModelFromString(const std::string& name);
/// The model a frame is tracked with: `setting` itself unless it is kAuto, which takes kDrive
/// when the robot's drive is available (a publisher of it or a message received) and kAxis
/// otherwise (a bag or a freehand recording). Never kAuto.
MotionModel chooseMotionModel(MotionModel setting, bool drive_available);

struct TipEstimate {
  TrackStatus status = TrackStatus::kUninitialized;
  std::string message;        ///< one line: what happened and why
  needle_model::TipPose tip;  ///< filtered pose; bevel from the robot [m, rad]
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Identity();  ///< of (x, y, theta), finite
  /// Position and heading standard deviations within the configured limits, and the status is
  /// kEntry or kTracked. Never true for a pose that was not confirmed by an image (or the guide).
  /// Also false (see TipTracker) after a re-acquisition or an acquisition until detections
  /// have moved with the robot, and over the first kMinStepAdvanceForConfidence_m of each
  /// insertion step (the new step's deflection is not yet measurable).
  bool confident = false;
  double inserted_length_m = 0.0;  ///< from the robot [m]
  Detection detection;             ///< this frame's raw detection (found = false if none)
};

/// Temporal filter (extended Kalman over x, y, theta) around detectTip.
///
/// Process model (dissertation 5.3): the tip moves along the arc of the current bevel by the
/// inserted length; each insertion step's deflection (sigma_insert, sigma_flip for the first
/// step after a flip) enters the heading variance whole where the step begins, steps of
/// step_length_m counted from the entry or the last flip (as the robot inserts them; if it
/// does not, the variance per length is still right on average). Measurement: detectTip with
/// the prediction as prior (and the lengths since the last flip and step as hints), fused if
/// its innovation passes the chi-square gate (3 dof, gate_chi2) on S = P + R; the covariance
/// never shrinks below a small floor (repeated frames of a needle at rest share their errors).
/// A detection that keeps being gated out although it follows the robot's motion re-acquires
/// the track (see kReacquireAfter); after a re-acquisition, an acquisition or a fusion into a
/// very wide prediction the estimate is not confident until detections have moved with the
/// robot (kConfirmPriorStd_m). Every output is finite: a non-finite update is discarded.
class TipTracker {
public:
  /// Throws std::invalid_argument from config.validate().
  explicit TipTracker(const TrackerConfig& config);

  /// A new insertion starts from the needle guide: the tip is at `entry` (inserted length 0)
  /// with the given standard deviations (the guide is known precisely; small but > 0).
  void reset(const needle_model::TipPose& entry, double position_std_m = 0.1e-3,
             double heading_std_rad = 0.005);
  /// The robot's proprioception: inserted length now and the current bevel; `flips` counts
  /// bevel flips since the entry. A longer length predicts the tip along an arc of the bevel's
  /// direction and grows the heading variance (sigma_flip for the first step_length_m after a
  /// flip, else sigma_insert, per step of step_length_m); a shorter one moves it back along
  /// the arc (back to 0: the guide's pose, kEntry). Status kPredicted after a move (not
  /// confident), unchanged without one. Non-finite, negative or implausible (> 10 m) lengths
  /// are ignored, the returned message saying so. Before reset() or an acquisition it only
  /// records the length and bevel.
  TipEstimate onDrive(double inserted_length_m, needle_model::Bevel bevel, std::uint32_t flips);
  /// One frame: validate (kBadFrame, state unchanged), nothing inserted (kEntry), predicted tip
  /// outside the frame (kOutOfView, no detection attempted), detect around the prediction, gate
  /// and fuse (kTracked) or keep the prediction (kPredicted, with the reason: no detection or
  /// gated out). Without reset() the first detection without a prior acquires the track (not
  /// confident until confirmed). Never throws.
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
  /// A detection fused into a wide prediction (largest position standard deviation above
  /// kConfirmPriorStd_m: after many frames without a detection), a re-acquisition and an
  /// acquisition without an entry could have locked onto something else that happened to pass
  /// the wide gate: the estimate is not confident until kConfirmDetections further fused
  /// detections have moved with the robot over at least kConfirmTravel_m of insertion.
  static constexpr double kConfirmPriorStd_m = 2e-3;
  static constexpr int kConfirmDetections = 2;
  static constexpr double kConfirmTravel_m = 1e-3;
  /// A tracked estimate is confident only once the needle has advanced this far since the
  /// current insertion step began (its deflection is seen over too short an arc before: 5-10
  /// degree heading errors with 1-2 degree standard deviations were measured on 2-4 mm arcs).
  static constexpr double kMinStepAdvanceForConfidence_m = 4.5e-3;

private:
  /// A gated-out detection kept to check whether the next ones agree with it.
  struct Rejected {
    needle_model::TipPose pose;
    Eigen::Matrix3d covariance = Eigen::Matrix3d::Identity();
    double inserted_length_m = 0.0;
    int agreeing = 0;       ///< how many consecutive rejected detections agree, this included
    double travel_m = 0.0;  ///< insertion travelled across them [m]
  };

  /// Moves the state from inserted length `from_m` to `to_m` along the arc of `bevel`, growing
  /// the covariance: the heading deflection of an insertion step (sigma_flip for the first step
  /// after a flip, else sigma_insert) is added whole where its step begins — steps of
  /// step_length_m counted from the entry or the last flip, as the robot's steps are — and a
  /// small position noise per length travelled.
  void predict(double from_m, double to_m, needle_model::Bevel bevel);
  /// Propagates the state along the arc by ds (either sign) in sub-steps.
  void move(double ds_m, needle_model::Bevel bevel);
  /// Fills estimate_.confident from the status and the covariance.
  void updateConfidence();
  /// onFrame's parts: the first frame without any prior; the prior the detector searches
  /// around; a detection outside the gate (re-acquisition after agreeing ones); the fusion.
  TipEstimate acquireWithoutPrior(const cv::Mat& frame);
  SearchPrior searchPrior() const;
  TipEstimate onGatedOut(const Detection& d, double d2);
  TipEstimate fuse(const Detection& d, const Eigen::Vector3d& nu,
                   const Eigen::LDLT<Eigen::Matrix3d>& ldlt, double d2);
  /// Whether the mean and covariance are finite (and the covariance symmetric PSD-ish).
  bool stateFinite() const;

  TrackerConfig config_;
  TipEstimate estimate_;
  bool initialized_ = false;  ///< an entry pose or an acquisition gave the state a meaning
  bool have_entry_ = false;   ///< reset() gave a guide pose (used again when retracted to 0)
  needle_model::TipPose entry_;
  Eigen::Matrix3d entry_covariance_ = Eigen::Matrix3d::Identity();
  double length_m_ = 0.0;  ///< inserted length the state refers to [m]
  std::uint32_t flips_ = 0;
  bool flip_pending_ = false;       ///< the next step's deflection is drawn with sigma_flip
  double step_origin_m_ = 0.0;      ///< steps of step_length_m are counted from here [m]
  double flip_length_m_ = -1.0;     ///< inserted length at the last flip, < 0 if none [m]
  double deflected_until_m_ = 0.0;  ///< the deflection of travel up to here is in P [m]
  std::optional<Rejected> rejected_;
  /// Pending confirmation of a fused detection by the robot's motion (see kConfirmPriorStd_m).
  struct Confirmation {
    Point2 p_SceneTip = Point2::Zero();  ///< the last confirming detection [m]
    double theta_rad = 0.0;
    double inserted_length_m = 0.0;
    int count = 0;          ///< detections that moved with the robot since
    double travel_m = 0.0;  ///< insertion over them [m]
  };
  std::optional<Confirmation> confirm_;
  /// Starts or advances the confirmation with a fused detection; false if it was not moving
  /// with the robot.
  void confirmWith(const Detection& d, bool start);
};

}  // namespace needle_guidance::imaging
