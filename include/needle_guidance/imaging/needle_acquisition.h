// Needle acquisition without a prior on B-mode frames, in pixels. Where detectTip
// (tip_tracker.h) assumes the needle the simulated imager draws, this finds a needle anywhere in
// a real frame and tells it from the structures that look like one:
//   step 1  grey conversion (8/16-bit, mono/colour; anything else refused with the reason);
//   step 2  ridge filter (Hessian, bright thin lines) and its orientation; in a fan, on the
//           frame less its depth profile (the probe face's ring-down band, attenuation);
//   step 3  candidate lines (cv::HoughLines on the strongest ridge pixels; near-duplicate lines
//           merged, and traced segments with the same ends kept once, so that a thick layer's
//           many lines do not take every candidate slot); in a fan, when none is strong enough,
//           the band along the fan's upper boundary where a needle enters searched on its own;
//   step 4  each candidate's visible segment along the line (gaps bridged), refit by weighted
//           least squares on the ridge pixels near it (a steerable needle, options.radius_px:
//           then bent into an arc of that radius either way, the circle's centre refit by
//           Gauss-Newton, the way that traces more ridge kept);
//   step 5  needle-vs-interface cues per candidate: cross-line contrast, orientation coherence
//           along the segment, symmetry of the tissue on both sides (an interface separates two
//           media: one side differs from the other; a needle lies inside one medium), length,
//           and distance from the image border;
//   step 6  the best candidate, if its evidence beats the thresholds (else "not found"),
//           and its tip: the end away from the entry side (calibrated or worked out; a tip on
//           the frame's border is no tip in view); over a sequence, a candidate whose tip end
//           brightens as a needle advancing along its own axis does beats every still one
//           (signed motion map); in still tissue the frame's one brightening blob is where the
//           needle has just gone: its front is the tip when no line moves (a needle hidden in a
//           saturated layer or a shadow), and a line traced short of it is extended to it.
// Plain C++ and OpenCV; no ROS.
#pragma once

#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/imaging/imaging_region.h"

namespace needle_guidance::imaging {

/// Side of the image the needle enters from. kAuto: the end of the segment nearer the image
/// border it points to is the entry (the tip is the end deeper inside the field of view).
enum class EntrySide : int { kAuto, kLeft, kRight, kTop, kBottom };
/// "auto" | "left" | "right" | "top" | "bottom".
std::string toString(EntrySide side);
/// Inverse of toString(EntrySide); nullopt for anything else.
std::optional<EntrySide> entrySideFromString(const std::string& name);

/// Settings of acquireNeedle, in pixels (none is fitted to a data set: each is a physical or
/// statistical statement, see the .cpp).
struct AcquisitionOptions {
  EntrySide entry = EntrySide::kAuto;
  double ridge_sigma_px = 2.0;  ///< scale of the ridge filter, about the needle's half width
  double min_length_px = 40.0;  ///< a visible needle shorter than this is not acquired
  double max_gap_px = 12.0;     ///< gaps along the shaft bridged when tracing it [px]
  /// Minimum contrast-to-noise of the line against the tissue beside it (z-score of the mean
  /// line intensity over the side bands' spread, times sqrt of the segment length in PSF
  /// lengths), below which the frame is "not found".
  double min_evidence = 6.0;
  /// Needle model: 0 = straight; > 0 = a constant-curvature (steerable) needle whose shaft is an
  /// arc of this radius [px] (from the scene, or track_frames --radius-mm over the pixel size).
  double radius_px = 0.0;
  /// Prior: where the needle enters the image [px] (track_frames --entry-point X,Y). A
  /// candidate whose curve passes more than 25 px from it is not the needle, and the end of the
  /// shaft nearer it is the tail. nullopt: worked out (the entry side, or the end with the
  /// shorter way out of the imaging region).
  std::optional<cv::Point2d> entry_point_px;
  /// Prior: the needle's rough direction towards its tip [rad], atan2(row step, column step)
  /// (track_frames --entry-angle DEG). A candidate more than 10 degrees off it is not the
  /// needle, and the shaft is oriented that way. nullopt: any direction.
  std::optional<double> entry_angle_rad;
  /// In a fan (convex or phased probe), the frame's depth profile (the median grey level at
  /// each depth: the probe face's ring-down band, attenuation, gain) is subtracted before the
  /// ridge filter, so a needle inside the band stands out against the band rather than its
  /// gradient. false: the frame as it is.
  bool flatten_depth = true;
  /// In a fan (auto entry, no entry point), when the whole fan's ridge gives no candidate strong
  /// enough: the band along the fan's upper boundary, where a needle just inserted lies, is
  /// searched on its own (its own ridge thresholds). false: the whole fan only.
  bool entry_zone = true;
  /// In a fan (auto entry, no entry point), a candidate that stays within the band along the
  /// fan's boundary is still the needle when it enters across that boundary (one end at the
  /// boundary, going steadily deeper at 8 degrees or more), and its part hidden in the strip
  /// along the boundary counts in its length: a needle just inserted beside the end of a convex
  /// probe meets the face at a shallow angle. false: every candidate within that band is the
  /// region's own edge.
  bool entry_across_edge = true;
  /// Throws std::invalid_argument naming the field when out of range.
  void validate() const;
};

/// One frame's acquisition: the needle's visible segment with its tip.
struct NeedleSegment {
  bool found = false;
  std::string message;            ///< why not found, or a one-line summary
  cv::Point2d tip_px{0.0, 0.0};   ///< tip, pixel coordinates (origin at pixel centre)
  cv::Point2d tail_px{0.0, 0.0};  ///< the other visible end
  double angle_rad = 0.0;         ///< direction towards the tip at the tip, atan2(drow, dcol)
  /// Signed curvature of the shaft [1/px] (0 = straight): > 0 turns from the direction towards
  /// the tip to its normal (-drow, dcol), i.e. clockwise on the screen (image y down).
  double curvature_per_px = 0.0;
  double contrast = 0.0;   ///< mean line minus side-band intensity [grey levels]
  double evidence = 0.0;   ///< score the candidate won with (see AcquisitionOptions)
  double symmetry = 0.0;   ///< 1 = same tissue on both sides, 0 = interface-like
  double coherence = 0.0;  ///< fraction of ridge pixels aligned with the line
  /// From the tail back along the shaft to the imaging region's boundary (or the frame's
  /// border) [px]: the part of the needle between its entry and the visible shaft.
  double entry_gap_px = 0.0;
  /// Sequence cue: signed frame difference against the background (brightening) at the tip
  /// end, less the unsigned difference along the rest of the shaft, both over the frame's mean
  /// difference (0 for a single frame; >= 3 counts as moving: a needle advancing along its own
  /// axis, not a flickering band or the moving edge of a shadow).
  double motion = 0.0;
  /// Sequence cue past the tip: the signed difference (brightening) over the frame's mean
  /// difference, 6 to 30 px beyond the tip along its direction (0 for a single frame; >= 3:
  /// the needle goes on past this tip, which is then traced short).
  double motion_ahead = 0.0;
  /// No line moved: the tip is the front of the frame's one brightening blob (a needle hidden in
  /// a layer's glare or a shadow, advancing); tail_px is the blob's back, the angle its axis.
  bool from_motion = false;
  /// The traced tip stopped short of the frame's one brightening blob ahead on the line: the tip
  /// was moved on along the line to the front of that motion.
  bool extended_by_motion = false;
  double length_px() const;
};

/// Keeps the memory the tracker frees in the process (glibc's malloc: no trimming, no mmap for
/// frame-sized blocks) instead of returning it to the system after every frame: SequenceTracker
/// allocates and frees frame-sized buffers each frame, and on a virtual machine the page faults
/// of fetching them back cost more than the tracking itself (720 x 440 convex frames: 60 ms of
/// CPU per frame without, 10 ms with). Call once in a program that tracks (track_frames, the
/// tip_tracker node, the benchmarks). A no-op without glibc.
void keepFreedMemory();

/// Step 1: `frame` as CV_8UC1 (CV_8UC1 as is; CV_16UC1 scaled by its own maximum; 3- or
/// 4-channel 8/16-bit converted to grey). Empty result with `problem` set for anything else
/// (empty frame, float, 2 channels), naming type and size. Never throws.
cv::Mat toGrey8(const cv::Mat& frame, std::string* problem);

/// Finds the needle in one frame, no prior. Never throws, never NaN: a frame it cannot use or
/// one without a needle gives found = false with the reason.
NeedleSegment acquireNeedle(const cv::Mat& frame, const AcquisitionOptions& options);

/// The same with the sequence cue: `motion` (CV_32FC1 of the frame's size, or empty for none)
/// is the frame's signed difference from a background model of the sequence over the mean of
/// its magnitude.
/// When a candidate strong enough to be a needle moves at its tip end (the needle advancing
/// along its own axis in still tissue), the still candidates drop out: a still bright line never
/// wins over a moving needle. Never throws.
NeedleSegment acquireNeedle(const cv::Mat& frame, const AcquisitionOptions& options,
                            const cv::Mat& motion);

/// The same inside a known imaging region (imaging_region.h; the other overloads find it from
/// the frame itself): ridges within 4 filter scales of a bounded region's boundary are left
/// out, a candidate that stays within 24 px of it is the region's own edge, and the region's
/// boundary is a border like the frame's (no tip on it; a line from border to border is an
/// interface; the entry is the end with the shorter way out of the region).
NeedleSegment acquireNeedle(const cv::Mat& frame, const AcquisitionOptions& options,
                            const cv::Mat& motion, const ImagingRegion& region);

/// Acquisition over a sequence: acquireNeedle per frame, a constant-velocity motion model of
/// the tip along the needle's own axis (no robot drive needed), a gate on the tip and the
/// angle, and confidence earned by consecutive agreeing detections. A still background plus a
/// tip moving along the axis is what a needle does; a candidate that jumps is gated out and
/// only replaces the track after kReacquireAfter agreeing frames. Each frame's acquisition uses
/// the sequence cue: the frame's difference from an exponential background of the previous
/// frames (acquireNeedle with a motion map), the background moved with the tissue's local motion
/// (optical flow, the needle's tip left out) when the tissue moves. Where no line shows the
/// needle, the frame's brightening blob continues a track of such tips, and a blob whose front
/// advances in line over three frames starts one (never confident: no shaft seen).
class SequenceTracker {
public:
  explicit SequenceTracker(const AcquisitionOptions& options);
  struct Output {
    NeedleSegment segment;  ///< this frame's estimate (found = false when nothing usable)
    /// Earned: kConfirmFrames agreeing detections in a row, of a track that has moved like a
    /// needle (its tip kEarnAdvance_px along its axis from where it was acquired, or a moving
    /// tip cue): a still bright line, however steady, never earns it; nor a tip with the
    /// tissue ahead of it still brightening (motion_ahead >= 3: traced short); nor a tip from
    /// the motion alone (NeedleSegment::from_motion: no shaft seen).
    bool confident = false;
    bool predicted = false;  ///< no gated detection: the tip is the motion model's prediction
  };
  /// One frame. Never throws. A frame identical to the previous one (a frozen or repeated
  /// frame) repeats the previous estimate, not confident, and is no new evidence.
  Output onFrame(const cv::Mat& frame);
  /// The imaging region worked out from the maximum of the frames so far.
  const ImagingRegion& region() const { return region_; }

  static constexpr int kConfirmFrames = 3;
  /// The imaging region is worked out on each of the first kRegionSettle frames, then every
  /// kRegionRefresh frames (from the maximum of the frames so far).
  static constexpr int kRegionSettle = 5;
  static constexpr int kRegionRefresh = 10;
  static constexpr int kReacquireAfter = 3;
  static constexpr int kMaxPredicted = 3;  ///< frames bridged by prediction (a still track)
  /// Frames a track that has moved like a needle coasts on its motion model while its tip is
  /// hidden (the detection gated out or missing: the needle inside an obstacle's shadow or a
  /// saturated layer, where nothing of it shows), reported as predicted, never confident. A
  /// velocity error of 1.5 px / frame (the jitter of a detected tip) keeps the coasting tip
  /// within kAgreeTip_px over these frames. (A detection on the track's line whose tip stops
  /// short is taken as it is: a stopped needle looks the same as a hidden tip, and coasting
  /// then ran 30 px past the in-vitro needle's tip.)
  static constexpr int kMaxCoast = 8;
  /// Tip innovation gate along the axis [px]: a hand-held or recorded insertion moves the tip
  /// by tens of pixels between frames along its axis, while the shaft stays on its line.
  static constexpr double kGateTip_px = 60.0;
  /// The gate behind a moving track's prediction along its own line [px] (kGateTip_px ahead of
  /// it): the constant-velocity prediction runs ahead of a tip traced short (fading, in a
  /// layer's glare) or of a needle that slows; a detection that far back on the same line is
  /// the same needle. The wide gate applies behind the prediction only: ahead of it, it takes
  /// the worst tuning p90 from 28.7 to 79.5 px.
  static constexpr double kGateBehind_px = 2.0 * kGateTip_px;
  static constexpr double kGateLine_px = 8.0;  ///< tip's distance from the track's line [px]
  /// The same for a tip from the motion alone (NeedleSegment::from_motion), whose front lies
  /// among the needle's reverberation copies (5 of them, 0.5 mm apart: 25 px at 0.1 mm) [px].
  static constexpr double kGateMotionLine_px = 3.0 * kGateLine_px;
  static constexpr double kGateAngle_rad = 0.087;  ///< 5 degrees
  static constexpr double kAgreeTip_px = 12.0;     ///< agreement of consecutive detections [px]
  /// Advance along the axis that shows a track is a needle being inserted [px]: more than the
  /// agreement tolerance, so a still line's jitter never reaches it.
  static constexpr double kEarnAdvance_px = 2.0 * kAgreeTip_px;

private:
  /// b on a's line (both ways). Two shafts: b's tip from max(tip_px, far_px) behind a's tip to
  /// tip_px ahead of it. A tip from the motion alone against a shaft: from tip_px behind to
  /// max(tip_px, far_px) ahead (its front runs ahead of the shaft, among the reverberation
  /// copies). Two motion-only tips: within max(tip_px, far_px) of each other.
  bool agrees(const NeedleSegment& a, const NeedleSegment& b, double tip_px, double far_px) const;
  Output update(const NeedleSegment& detection);
  /// The frame's brightening blob (kBlobDominanceOnTrack of the change, see the .cpp) whose front
  /// agrees with the moving track's prediction `pred`: its tip when no line shows it.
  std::optional<NeedleSegment> blobOnTrack(const NeedleSegment& pred) const;
  /// The frame's brightening blob (kBlobDominanceChain of the change) when its front has advanced
  /// in line over the last kChainFrames frames (see the .cpp); updates chain_.
  std::optional<NeedleSegment> advancingBlob();
  /// The axis of a tip from the motion alone: its path since the track began once that is
  /// kEarnAdvance_px long, else the track's shaft, else the blob's own axis.
  double motionAxis(const NeedleSegment& d) const;
  /// d's tip kEarnAdvance_px along `axis` from the track's first tip, its tail (the shaft's far
  /// end) moved less than half that (a drifting layer of moving tissue moves at both ends); a
  /// tip from the motion alone has no tail to check.
  bool advancedLikeANeedle(const NeedleSegment& d, const cv::Point2d& axis) const;
  /// The track's motion model one frame on (the tip along the axis at the last speed).
  NeedleSegment predicted() const;
  /// A frame whose detection shows no tip of the moving track (gated out or missing): coast on
  /// the motion model within kMaxCoast frames and the frame.
  std::optional<Output> coast(const NeedleSegment& d, const std::string& why);
  /// A detection gated out of the track: re-acquire after kReacquireAfter agreeing frames (a
  /// moving track only for a moving detection).
  std::optional<Output> reacquire(const NeedleSegment& d);
  /// A new track from detection d (velocity 0, not yet moved unless d's tip moves).
  void startTrack(const NeedleSegment& d);
  /// frame - background over the mean of its magnitude (empty for the first frame), then the
  /// background takes the frame in.
  cv::Mat motionMap(const cv::Mat& frame);
  /// Takes the frame into the maximum frame and refreshes region_ (kRegionSettle, kRegionRefresh).
  void updateRegion(const cv::Mat& frame);
  cv::Mat max_frame_;  ///< CV_8U maximum of the frames so far
  ImagingRegion region_;
  int region_frames_ = 0;
  cv::Mat background_;  ///< CV_32F exponential average of the frames, moved with the tissue
  cv::Mat motion_;      ///< the last frame's motion map (empty for the first frame)
  std::vector<cv::Point2d> chain_;  ///< fronts of the last frames' blobs advancing in line
  cv::Mat last_frame_;
  cv::Size size_;  ///< the last frame's size
  Output last_output_;
  AcquisitionOptions options_;
  std::optional<NeedleSegment> track_;
  double velocity_px_ = 0.0;             ///< tip speed along the axis [px / frame]
  cv::Point2d start_tip_px_{0.0, 0.0};   ///< the track's tip when it was acquired
  cv::Point2d start_tail_px_{0.0, 0.0};  ///< the track's tail (far end) when it was acquired
  bool moved_ = false;                   ///< the track has moved like a needle
  /// A track has moved like a needle in this sequence: from then on a still line is not the
  /// needle (found = false) until it moves, and never replaces a moving track.
  bool seen_moving_ = false;
  int coasted_ = 0;  ///< consecutive frames the moving track coasted (tip hidden)
  int agreeing_ = 0;
  int missed_ = 0;
  std::optional<NeedleSegment> candidate_;
  int candidate_count_ = 0;
};

}  // namespace needle_guidance::imaging
