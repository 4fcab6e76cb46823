// Hard cases of needle acquisition without a prior (imaging/needle_acquisition.h) on
// synthetic B-mode frames (imaging/synthetic_bmode.h: speckle from a random scatterer field
// convolved with an anisotropic point-spread function, specular interfaces between media of
// different echogenicity, a needle with an acoustic shadow beneath and a reverberation tail). Fixed
// seeds.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/imaging/needle_acquisition.h"
#include "needle_guidance/imaging/synthetic_bmode.h"
#include "needle_guidance/math.h"
#include "needle_guidance/scene/scene.h"

namespace im = needle_guidance::imaging;

namespace {

using needle_guidance::kPi;
constexpr double kTipTolerance_px = 8.0;      // median tip error target
constexpr double kTipP90Tolerance_px = 15.0;  // and its 90th-percentile target
constexpr double kPsfReach_px = 3.0;  // blur of the drawn needle (sigma 1 px) and its 1 px radius
constexpr double kAngleTolerance_rad = 3.0 * kPi / 180.0;
const cv::Size kSize(720, 440);
constexpr double kConfidentWrong_px = 20.0;  // "confident and > 20 px off" counts as wrong
/// A coasting (predicted) tip's error bound [px]: kMaxCoast frames at a velocity error of up to
/// 5 px / frame; the still outlines of steering_workspace lie 200-450 px from the needle.
constexpr double kHiddenTipCoast_px = 40.0;
/// A tip from the motion alone lies among the needle's reverberation copies, up to 25 px beyond
/// the shaft at 0.1 mm pixels (5 copies 0.5 mm apart) [px].
constexpr double kHiddenTipMotion_px = 25.0;

using Needle = im::BModeNeedle;
using Interface = im::BModeInterface;

cv::Mat frame(std::uint64_t seed, const std::optional<Interface>& iface,
              const std::optional<Needle>& needle) {
  return im::syntheticBMode(kSize, seed, iface, needle);
}

Needle leftNeedle() {
  return {{150, 230}, {450, 188}};
}

void expectTip(const im::NeedleSegment& s, const Needle& n, double tol) {
  ASSERT_TRUE(s.found) << s.message;
  EXPECT_LT(cv::norm(s.tip_px - n.tip), tol) << s.message;
  const double truth = n.tipAngle();
  EXPECT_LT(std::abs(std::remainder(s.angle_rad - truth, 2.0 * kPi)), kAngleTolerance_rad)
      << s.message;
}

}  // namespace

TEST(NeedleAcquisition, FindsNeedleBesideBrighterLongerInterface) {
  const Needle n = leftNeedle();
  const Interface f{320, 300};
  expectTip(im::acquireNeedle(frame(1, f, n), {}), n, kTipTolerance_px);
}

TEST(NeedleAcquisition, FindsNeedleCrossingAnInterface) {
  const Needle n{{150, 300}, {480, 200}};
  const Interface f{230, 270};  // crosses the shaft near its middle
  expectTip(im::acquireNeedle(frame(2, f, n), {}), n, kTipTolerance_px);
}

TEST(NeedleAcquisition, TipFadingOutOfPlaneEndsInsideTheFadingPart) {
  Needle n = leftNeedle();
  n.fade_fraction = 0.25;  // the last quarter leaves the plane, its echo fading to nothing
  const im::NeedleSegment s = im::acquireNeedle(frame(3, std::nullopt, n), {});
  ASSERT_TRUE(s.found) << s.message;
  // Along the shaft: never past the needle's end (plus the PSF), never before the fading begins.
  const cv::Point2d u = (n.tip - n.tail) / cv::norm(n.tip - n.tail);
  const double along = (s.tip_px - n.tail).dot(u), length = cv::norm(n.tip - n.tail);
  EXPECT_LT(along, length + kPsfReach_px) << s.message;
  EXPECT_GT(along, (1.0 - n.fade_fraction) * length) << s.message;
  const cv::Point2d nrm(-u.y, u.x);
  EXPECT_LT(std::abs((s.tip_px - n.tail).dot(nrm)), kTipTolerance_px) << s.message;
}

TEST(NeedleAcquisition, FrameWithoutNeedleIsNotConfident) {
  const Interface f{300, 320};
  im::SequenceTracker tracker({});
  for (std::uint64_t i = 0; i < 6; ++i) {
    const auto out = tracker.onFrame(frame(10 + i, f, std::nullopt));
    EXPECT_FALSE(out.confident) << "frame " << i << ": " << out.segment.message;
  }
  const im::NeedleSegment s = im::acquireNeedle(frame(20, std::nullopt, std::nullopt), {});
  EXPECT_FALSE(s.found) << s.message;
}

TEST(NeedleAcquisition, RepeatedFrameEarnsNoConfidence) {
  const cv::Mat f = frame(4, std::nullopt, leftNeedle());
  im::SequenceTracker tracker({});
  for (int i = 0; i < 6; ++i) {
    const auto out = tracker.onFrame(f);
    EXPECT_TRUE(out.segment.found) << out.segment.message;
    EXPECT_FALSE(out.confident) << "frozen frame " << i << " counted as new evidence";
  }
}

TEST(NeedleAcquisition, NeedleEnteringFromTheRight) {
  const Needle n{{600, 220}, {300, 180}};
  expectTip(im::acquireNeedle(frame(5, std::nullopt, n), {}), n, kTipTolerance_px);
  im::AcquisitionOptions right;
  right.entry = im::EntrySide::kRight;
  expectTip(im::acquireNeedle(frame(5, std::nullopt, n), right), n, kTipTolerance_px);
}

TEST(NeedleAcquisition, SixteenBitAndColourFramesGiveTheSameTip) {
  const Needle n = leftNeedle();
  const cv::Mat grey = frame(6, std::nullopt, n);
  cv::Mat wide, colour, colour16;
  grey.convertTo(wide, CV_16U, 257.0);
  cv::cvtColor(grey, colour, cv::COLOR_GRAY2BGR);
  colour.convertTo(colour16, CV_16UC3, 257.0);
  const im::NeedleSegment ref = im::acquireNeedle(grey, {});
  expectTip(ref, n, kTipTolerance_px);
  for (const cv::Mat& m : {wide, colour, colour16}) {
    const im::NeedleSegment s = im::acquireNeedle(m, {});
    ASSERT_TRUE(s.found) << s.message;
    EXPECT_LT(cv::norm(s.tip_px - ref.tip_px), 1.0) << "type " << m.type();
  }
}

TEST(NeedleAcquisition, FloatAndEmptyFramesAreRefusedClearly) {
  cv::Mat f(kSize, CV_32F, cv::Scalar(0.5));
  const im::NeedleSegment s = im::acquireNeedle(f, {});
  EXPECT_FALSE(s.found);
  EXPECT_NE(s.message.find("depth"), std::string::npos) << s.message;
  const im::NeedleSegment e = im::acquireNeedle(cv::Mat(), {});
  EXPECT_FALSE(e.found);
  EXPECT_NE(e.message.find("empty"), std::string::npos) << e.message;
}

TEST(NeedleAcquisition, EntrySideNamesRoundTrip) {
  for (const char* name : {"auto", "left", "right", "top", "bottom"}) {
    ASSERT_TRUE(im::entrySideFromString(name).has_value()) << name;
    EXPECT_EQ(im::toString(*im::entrySideFromString(name)), name);
  }
  EXPECT_FALSE(im::entrySideFromString("sideways").has_value());
}

TEST(NeedleAcquisition, StillBrightLineNeverWinsOverAMovingNeedle) {
  // Still tissue (one speckle seed for every frame) with a still bright thin line inside one
  // medium (a wire, a calcified duct: needle-like in every single-frame cue, and brighter and
  // longer than the needle), and a fainter needle advancing 8 px a frame along its own axis.
  const cv::Point2d tail(120, 320), axis = cv::Point2d(300, -40) / cv::norm(cv::Point2d(300, -40));
  auto still_line = [](cv::Mat f) {
    cv::line(f, cv::Point(200, 110), cv::Point(600, 90), cv::Scalar(235), 2, cv::LINE_AA);
    cv::GaussianBlur(f, f, cv::Size(), 0.7);
    return f;
  };
  auto needle_at = [&](int k) {
    Needle n{tail, tail + (180.0 + 8.0 * k) * axis};
    n.brightness = 120.0;
    return n;
  };
  // Single frame: the still line wins (the case the sequence cue is for).
  const im::NeedleSegment single =
      im::acquireNeedle(still_line(frame(31, std::nullopt, needle_at(0))), {});
  ASSERT_TRUE(single.found) << single.message;
  ASSERT_LT(single.tip_px.y, 150.0)
      << "precondition: a single frame picks the still line; " << single.message;
  im::SequenceTracker tracker({});
  for (int k = 0; k < 8; ++k) {
    const Needle n = needle_at(k);
    const auto out = tracker.onFrame(still_line(frame(31, std::nullopt, n)));
    // On the needle: on its shaft's line, between its tail and just past its tip (the faint
    // tip of this needle may be traced a little short).
    const cv::Point2d rel = out.segment.tip_px - n.tail;
    const double along = rel.dot(axis), across = std::abs(rel.cross(axis));
    const bool on_needle = out.segment.found && across < kTipTolerance_px && along > 0.0 &&
                           along < cv::norm(n.tip - n.tail) + kTipTolerance_px;
    if (k >= 1) {  // from the second frame on there is a background to move against
      EXPECT_TRUE(on_needle) << "frame " << k << ": " << out.segment.message;
    }
    if (out.confident) {
      EXPECT_TRUE(on_needle) << "frame " << k
                             << " confident off the needle: " << out.segment.message;
    }
  }
}

// ---- constant-curvature (steerable) needles: options.radius_px ----

namespace {

/// A steerable needle at 0.2 mm pixels: radius 5 cm = 250 px; a 250 px chord bends 34 px.
constexpr double kRadius_px = 250.0;

Needle arcNeedle(cv::Point2d tail, cv::Point2d tip, double curvature) {
  Needle n{tail, tip};
  n.curvature_per_px = curvature;
  return n;
}

im::AcquisitionOptions arcOptions(im::EntrySide entry = im::EntrySide::kAuto) {
  im::AcquisitionOptions o;
  o.radius_px = kRadius_px;
  o.entry = entry;
  return o;
}

}  // namespace

TEST(NeedleAcquisition, ArcNeedleBendingEitherWayIsAcquiredWithItsTipAndHeading) {
  for (const double k : {1.0 / kRadius_px, -1.0 / kRadius_px}) {
    const Needle n = arcNeedle({130, 230}, {380, 230}, k);
    const cv::Mat f = frame(41, Interface{380, 400}, n);
    const im::NeedleSegment arc = im::acquireNeedle(f, arcOptions());
    expectTip(arc, n, kTipTolerance_px);
    EXPECT_NEAR(arc.curvature_per_px, k, 0.1 * std::abs(k)) << arc.message;
    // The straight model cannot follow the bend to the tip: its tip or heading is worse.
    const im::NeedleSegment straight = im::acquireNeedle(f, {});
    const double arc_heading = std::abs(std::remainder(arc.angle_rad - n.tipAngle(), 2 * kPi));
    const double straight_heading =
        std::abs(std::remainder(straight.angle_rad - n.tipAngle(), 2 * kPi));
    EXPECT_LT(arc_heading, straight_heading) << "curvature " << k;
  }
}

TEST(NeedleAcquisition, ArcNeedleFromTheRightWithStatedAndAutoEntry) {
  const Needle n = arcNeedle({620, 150}, {370, 200}, 1.0 / kRadius_px);
  const cv::Mat f = frame(42, std::nullopt, n);
  expectTip(im::acquireNeedle(f, arcOptions()), n, kTipTolerance_px);
  expectTip(im::acquireNeedle(f, arcOptions(im::EntrySide::kRight)), n, kTipTolerance_px);
  // Stated the wrong way, the tip is the other end: the entry is honoured, not guessed.
  const im::NeedleSegment left = im::acquireNeedle(f, arcOptions(im::EntrySide::kLeft));
  ASSERT_TRUE(left.found) << left.message;
  EXPECT_LT(cv::norm(left.tip_px - n.tail), 2.0 * kTipTolerance_px) << left.message;
}

TEST(NeedleAcquisition, ArcNeedleAdvancingAlongItsArcIsTrackedAndConfirmed) {
  // The needle grows along its own circle, 10 px of arc a frame, in still tissue.
  Needle full = arcNeedle({100, 300}, {420, 250}, -1.0 / kRadius_px);
  im::SequenceTracker tracker(arcOptions(im::EntrySide::kLeft));
  int confident = 0;
  std::vector<double> errors;
  for (int k = 0; k < 8; ++k) {
    const double s = 180.0 + 10.0 * k;
    Needle n = full;
    n.tip = full.at(s);
    // The same circle through the tail with a shorter chord: same curvature.
    const auto out = tracker.onFrame(frame(43, std::nullopt, n));
    ASSERT_TRUE(out.segment.found) << "frame " << k << ": " << out.segment.message;
    errors.push_back(cv::norm(out.segment.tip_px - n.tip));
    EXPECT_LT(errors.back(), kTipP90Tolerance_px) << "frame " << k;
    confident += out.confident ? 1 : 0;
  }
  EXPECT_GE(confident, 8 - im::SequenceTracker::kConfirmFrames);
  std::nth_element(errors.begin(), errors.begin() + 4, errors.end());
  EXPECT_LT(errors[4], kTipTolerance_px);  // the median (upper of the middle two)
}

TEST(NeedleAcquisition, ArcRadiusShorterThanTheNeedleIsRefused) {
  im::AcquisitionOptions o;
  o.radius_px = 5.0;  // below min_length_px / pi
  EXPECT_THROW(o.validate(), std::invalid_argument);
  const im::NeedleSegment s = im::acquireNeedle(frame(4, std::nullopt, leftNeedle()), o);
  EXPECT_FALSE(s.found);
  EXPECT_NE(s.message.find("radius_px"), std::string::npos) << s.message;
}

// ---- sequences: a still line never earns confidence; the realistic renderer's layers ----

TEST(NeedleAcquisition, StillBrightLineIsNeverConfident) {
  // Still tissue with a bright thin line (needle-like in every single-frame cue) and no
  // needle; each frame has its own electronic noise (not a repeated frame). The line may be
  // reported, but it never moves like a needle, so it never earns confidence.
  const cv::Mat still = frame(31, std::nullopt, std::nullopt);
  cv::line(still, cv::Point(200, 110), cv::Point(600, 90), cv::Scalar(235), 2, cv::LINE_AA);
  im::SequenceTracker tracker({});
  cv::RNG rng(7);
  for (int k = 0; k < 10; ++k) {
    cv::Mat noise(still.size(), CV_16S), f;
    rng.fill(noise, cv::RNG::NORMAL, 0.0, 3.0);
    still.convertTo(f, CV_16S);
    f += noise;
    f.convertTo(f, CV_8U);
    const auto out = tracker.onFrame(f);
    EXPECT_FALSE(out.confident) << "frame " << k << ": " << out.segment.message;
  }
}

/// The imager's realistic ultrasound (frame_renderer.h) on steering_workspace at 0.1 mm
/// pixels: two specular layers spanning the frame, brighter and thicker than the needle,
/// obstacle outlines, speckle through a PSF, the needle's shadow and reverberation tail, the
/// needle partly out of plane. The needle advances 1 mm a frame from the left, from `entry`
/// [m] at `angle` [rad above +x]; tip errors [px] from the third frame on (the needle has
/// moved against the background by then), and a failure for any confident tip > 20 px off.
/// `worst_found_px` (optional): the largest error of a reported (found) tip from frame 2 on.
/// `kappa` [1/m]: a steerable needle on an arc, tracked with the arc model.
std::vector<double> realisticSequenceErrors(std::uint64_t seed, im::Point2 entry, double angle,
                                            int frames = 12, double* worst_found_px = nullptr,
                                            double kappa = 0.0, double tissue_motion_px = 0.0) {
  const auto scene = needle_guidance::scene::loadSceneSpec("steering_workspace");
  im::ImagerConfig c = im::imagerConfigFromScene(scene, seed);
  c.modality = im::Modality::kUltrasound;
  c.ultrasound_model = im::UltrasoundModel::kRealistic;
  c.geometry.pixel_size_m = 0.1e-3;
  c.geometry.cols = 720;
  c.geometry.rows = 440;
  c.geometry.origin_m = im::Point2(0.0, 0.05);
  c.noise_std = 0.1;
  c.blur_sigma_m = 0.1e-3;
  c.drop_probability = 0.0;
  c.tissue_motion_px = tissue_motion_px;
  const im::FrameRenderer renderer(scene, c);
  im::AcquisitionOptions o;
  o.entry = im::EntrySide::kLeft;
  if (kappa != 0.0)
    o.radius_px = 1.0 / std::abs(kappa) / c.geometry.pixel_size_m;
  im::SequenceTracker tracker(o);
  std::vector<double> errors;
  for (int k = 0; k < frames; ++k) {
    const auto pts = im::insertedNeedlePoints(entry, angle, 0.02 + 1e-3 * k, kappa);
    const auto out = tracker.onFrame(renderer.render(pts, static_cast<std::uint64_t>(k)).image);
    const double e =
        out.segment.found ? cv::norm(out.segment.tip_px - c.geometry.toPixel(pts.back())) : 1e9;
    if (out.confident) {
      EXPECT_LT(e, kConfidentWrong_px)
          << "frame " << k << " confident and wrong: " << out.segment.message;
    }
    if (k >= 2)
      errors.push_back(e);
    if (k >= 2 && out.segment.found && worst_found_px)
      *worst_found_px = std::max(*worst_found_px, e);
  }
  std::sort(errors.begin(), errors.end());
  return errors;
}

/// A 20-frame realistic sequence (realisticSequenceErrors) followed: the median error from frame
/// 2 on under `median_px`, and no reported tip further off than `worst_px` [px].
void expectFollowed(std::uint64_t seed, im::Point2 entry, double angle, double kappa,
                    double median_px, double worst_px) {
  double worst_found_px = 0.0;
  const std::vector<double> e =
      realisticSequenceErrors(seed, entry, angle, 20, &worst_found_px, kappa);
  EXPECT_LT(e[e.size() / 2], median_px) << "median over frames 2-19, seed " << seed;
  EXPECT_LT(worst_found_px, worst_px)
      << "a reported tip far off (the still outline), seed " << seed;
}

TEST(NeedleAcquisition, RealisticLayersBrighterAndLongerThanTheNeedleAreRejected) {
  // The needle below both layers, which outscore it in any single frame (bench
  // tracking_real's tuning sequence tune_straight_b).
  const std::vector<double> e = realisticSequenceErrors(23, im::Point2(0.0, 0.010), 0.15);
  EXPECT_LT(e[e.size() / 2], kTipTolerance_px) << "median over frames 2-11";
}

TEST(NeedleAcquisition, RealisticNeedleWhoseTipRunsIntoALayerIsNeverConfidentlyWrong) {
  // The needle rises into a layer and its tip lies inside the saturated layer: the advancing
  // tip brightens no line, and the obstacle's still outline outscores the needle. Before the
  // motion-only tip the still outline was reported (400-500 px off); now the tip is followed by
  // what it brightens, within the reverberation copies' reach, and no wrong tip is confident
  // (checked per frame inside realisticSequenceErrors). Seeds and geometry used by no benchmark.
  for (const auto& e : {realisticSequenceErrors(5, im::Point2(0.0, 0.018), 0.12, 20),
                        realisticSequenceErrors(8, im::Point2(0.0, 0.030), 0.05, 20)}) {
    EXPECT_LT(e[e.size() / 2], kTipTolerance_px) << "median over frames 2-19";
    EXPECT_LT(e.back(), kHiddenTipMotion_px) << "worst over frames 2-19 (not found: 1e9)";
  }
}

TEST(NeedleAcquisition, NeedleHiddenInAnObstacleShadowIsFollowedNotReplacedByAStillLine) {
  // The needle runs into an obstacle's dark shadow column, where nothing of it shows, while the
  // obstacle's still outline (230 px long, brighter) outscores it in every frame (bench
  // tracking_real's tuning sequence tune_straight_d, 20 frames). The track coasts on its motion
  // model through the shadow (predicted, never confident), the still outline never takes its
  // place, and the needle is taken up again when it moves out.
  expectFollowed(203, im::Point2(0.0, 0.025), 0.02, 0.0, kTipTolerance_px, kHiddenTipCoast_px);
}

TEST(NeedleAcquisition, NeedleInsideASaturatedLayerIsFollowedByItsMotion) {
  // The needle runs inside the lower layer (bench tracking_real's tuning sequence
  // tune_straight_a): saturated, nothing of its shaft shows, and the obstacle's still outline
  // (230 px long) is the best line in every frame. Its advancing tip still brightens what it
  // reaches (its echo at the layer's edge, its reverberation copies): the frame's one
  // brightening blob. Reported from its front from frame 2 on, never confident.
  expectFollowed(11, im::Point2(0.0, 0.020), 0.05, 0.0, kHiddenTipMotion_px, kHiddenTipMotion_px);
}

TEST(NeedleAcquisition, TipTracedShortIsMovedOnToTheMotionFront) {
  // A visible shaft whose trace stops 20-80 px short of the advancing tip in every frame
  // (bench tracking_real's tuning sequence tune_straight_j: the tip under a layer's glare),
  // while the tissue ahead of the traced end brightens as the needle advances: the tip is moved
  // on along the line to the front of that brightening.
  const std::vector<double> e = realisticSequenceErrors(311, im::Point2(0.0, 0.027), 0.04, 20);
  EXPECT_LT(e[e.size() / 2], kTipTolerance_px) << "median over frames 2-19";
  EXPECT_LT(e[(e.size() * 9) / 10], kTipP90Tolerance_px) << "90th percentile over frames 2-19";
}

TEST(NeedleAcquisition, ArcNeedleWhoseTipMergesIntoALayerIsFollowed) {
  // A steerable needle (radius 14 cm) starting inside the lower layer and bending up out of it
  // (bench tracking_real's tuning sequence tune_arc_d): its traced arc runs on along the layer to
  // the border and is discarded, so only the still outline remained (400 px off). Now followed by
  // its motion; no reported tip far off.
  expectFollowed(209, im::Point2(0.0, 0.020), 0.02, 7.0, kTipTolerance_px, kHiddenTipCoast_px);
}

TEST(NeedleAcquisition, DriftingTissueLayerNeverEarnsConfidence) {
  // Moving tissue (ImagerConfig::tissue_motion_px: drift, sway, compression, partly fresh
  // speckle): a specular layer drifting along its own axis advances its end like a needle's
  // tip. Before the tail check it earned confidence 74 px off (bench tracking_real's
  // tune_motion_arc); now a track must advance its tip while its far end stays. No confident
  // tip > 20 px off (checked per frame inside realisticSequenceErrors), straight and arc, at
  // 1 and 2 px / frame. Seeds used by no benchmark.
  double worst = 0.0;
  realisticSequenceErrors(601, im::Point2(0.0, 0.020), 0.06, 20, &worst, 0.0, 2.0);
  realisticSequenceErrors(602, im::Point2(0.0, 0.016), 0.10, 20, &worst, -8.0, 2.0);
  realisticSequenceErrors(603, im::Point2(0.0, 0.024), 0.04, 20, &worst, 0.0, 1.0);
}

TEST(NeedleAcquisition, NeedleInMovingTissueIsFollowedByItsMotionRelativeToTheTissue) {
  // Moving tissue (drift, sway, compression, partly fresh speckle) around a needle that advances
  // 1 mm a frame. With one global shift compensated, the layers' edges and the compression left
  // residues over the frame and the still obstacle outline was reported in most frames (bench
  // tracking_real's tune_motion_straight 404 px median); the background now follows the tissue's
  // local motion (optical flow), so what changes is where the needle went. Median over frames
  // 2-19 within the target, no confident tip > 20 px off (checked per frame). Seeds and
  // geometry used by no benchmark, fixed before the run.
  for (const auto& e :
       {realisticSequenceErrors(611, im::Point2(0.0, 0.022), 0.05, 20, nullptr, 0.0, 1.5),
        realisticSequenceErrors(612, im::Point2(0.0, 0.014), 0.12, 20, nullptr, -8.0, 1.0)}) {
    EXPECT_LT(e[e.size() / 2], kTipTolerance_px) << "median over frames 2-19";
  }
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}

// A short needle from the right in a frame whose tissue beneath it is darkened by the needle's
// acoustic shadow (in-vivo frames: the textured tissue's spread makes the line's contrast-to-noise
// modest, and the shadow makes its sides unequal). The shadow is a needle's cue: the line is
// acquired. The same darkening on the shallow side (an interface's asymmetry, not a shadow) keeps
// the full symmetry penalty, and the line is not accepted on that evidence.
TEST(NeedleAcquisition, NeedleWithItsShadowBeneathIsAcquiredNotPenalisedAsAnInterface) {
  constexpr double kShadowGain = 0.7;  // tissue beneath the needle keeps this much of its echo
  const Needle n{{600, 296}, {440, 316}};
  Needle faint = n;
  faint.brightness = 60.0;
  const cv::Mat base = frame(44, std::nullopt, faint);
  const auto darken = [&](double side) {  // side +1: beneath the shaft (larger rows), -1: above
    cv::Mat f = base.clone();
    for (int x = 440; x <= 600; ++x) {
      const double y0 = 316.0 + (x - 440) * (296.0 - 316.0) / (600.0 - 440.0);
      for (int k = 4; k <= 40; ++k) {
        const int y = static_cast<int>(std::lround(y0 + side * k));
        f.at<std::uint8_t>(y, x) =
            cv::saturate_cast<std::uint8_t>(f.at<std::uint8_t>(y, x) * kShadowGain);
      }
    }
    return f;
  };
  const im::NeedleSegment below = im::acquireNeedle(darken(+1.0), im::AcquisitionOptions{});
  expectTip(below, n, kTipTolerance_px);
  const im::NeedleSegment above = im::acquireNeedle(darken(-1.0), im::AcquisitionOptions{});
  EXPECT_FALSE(above.found && cv::norm(above.tip_px - n.tip) < kTipTolerance_px) << above.message;
}
