// Needle tracking on convex-probe frames (convex_ultrasound.h): the imaging region worked out
// from the frames, steep needles from the top of the fan, and the hard cases: a 60 degree needle
// under a brighter, longer interface; the fan's edge at the needle's entry; a needle nearly
// along the beam; a needle appearing part-way; a sparse sequence; a fan without a needle; the
// priors (entry point, entry angle).
#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <string>
#include <vector>

#include "needle_guidance/imaging/convex_ultrasound.h"
#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/imaging/imaging_region.h"
#include "needle_guidance/imaging/needle_acquisition.h"
#include "needle_guidance/scene/scene.h"

namespace im = needle_guidance::imaging;

namespace {

constexpr double kTipTolerance_px = 15.0;  ///< a found tip this close to the truth is right
constexpr double kConfidentWrong_px = 20.0;
constexpr double kAngleTolerance_deg = 5.0;
constexpr double kRegionAgreement = 0.97;  ///< share of pixels the region and the probe agree on

im::ConvexInsertion insertion(std::uint64_t seed, double entry, double angle_deg) {
  im::ConvexInsertion c;
  c.seed = seed;
  c.entry = entry;
  c.angle_deg = angle_deg;
  return c;
}

struct Tracked {
  std::vector<im::SequenceTracker::Output> out;
  std::vector<cv::Point2d> truth;  ///< (-1, -1) where the frame has no needle
  std::vector<double> angle;
};

Tracked track(const im::ConvexInsertion& c, const im::AcquisitionOptions& options = {}) {
  Tracked t;
  const im::ConvexScene scene = c.scene();
  im::SequenceTracker tracker(options);
  for (int k = 0; k < c.frames; ++k) {
    cv::Point2d tip;
    double angle = 0.0;
    const std::vector<cv::Point2d> pts = c.needleAt(k, &tip, &angle);
    t.out.push_back(tracker.onFrame(im::renderConvexFrame(scene, c.size, pts, std::uint64_t(k))));
    const bool in_view = c.visibleLength(k) >= options.min_length_px;
    t.truth.push_back(in_view ? tip : cv::Point2d(-1, -1));
    t.angle.push_back(angle);
  }
  return t;
}

double angleDeg(double a, double b) {
  double d = std::fmod(std::abs(a - b), 2 * CV_PI);
  return std::min(d, 2 * CV_PI - d) * 180.0 / CV_PI;
}

/// Never a confident tip far from the truth, nor one in a frame without the needle.
void expectNoConfidentWrong(const Tracked& t, const std::string& what) {
  for (std::size_t k = 0; k < t.out.size(); ++k) {
    if (!t.out[k].confident)
      continue;
    ASSERT_GE(t.truth[k].x, 0.0) << what << ": confident in frame " << k << " without a needle";
    EXPECT_LT(cv::norm(t.out[k].segment.tip_px - t.truth[k]), kConfidentWrong_px)
        << what << ": frame " << k << ": " << t.out[k].segment.message;
  }
}

/// The last frame's tip and angle are right.
void expectLastTipRight(const Tracked& t, const std::string& what) {
  const auto& last = t.out.back();
  ASSERT_TRUE(last.segment.found) << what << ": " << last.segment.message;
  EXPECT_LT(cv::norm(last.segment.tip_px - t.truth.back()), kTipTolerance_px)
      << what << ": " << last.segment.message;
  EXPECT_LT(angleDeg(last.segment.angle_rad, t.angle.back()), kAngleTolerance_deg) << what;
}

TEST(ImagingRegion, FindsTheFanOfAConvexProbe) {
  const im::ConvexInsertion c = insertion(31, -0.8, 35);
  const im::ConvexScene scene = c.scene();
  const cv::Mat frame = im::renderConvexFrame(scene, c.size, {}, 0);
  const im::ImagingRegion region = im::findImagingRegion(frame);
  EXPECT_EQ(region.shape, im::ImagingRegion::Shape::kSector);
  int agree = 0;
  for (int y = 0; y < frame.rows; ++y)
    for (int x = 0; x < frame.cols; ++x)
      agree += (region.mask.at<std::uint8_t>(y, x) != 0) == scene.probe.inside(cv::Point2d(x, y));
  EXPECT_GT(agree, kRegionAgreement * frame.total());
}

TEST(ImagingRegion, AFrameWithoutBlackMarginIsTheWholeFrame) {
  cv::Mat frame(200, 300, CV_8U);
  cv::randu(frame, 20, 200);
  EXPECT_EQ(im::findImagingRegion(frame).shape, im::ImagingRegion::Shape::kFrame);
  cv::Mat boxed(200, 300, CV_8U, cv::Scalar(0));
  frame(cv::Rect(40, 0, 220, 200)).copyTo(boxed(cv::Rect(40, 0, 220, 200)));
  const im::ImagingRegion r = im::findImagingRegion(boxed);
  EXPECT_EQ(r.shape, im::ImagingRegion::Shape::kRectangle);
  EXPECT_NEAR(r.fraction, 220.0 / 300.0, 0.02);
  EXPECT_EQ(im::findImagingRegion(cv::Mat()).shape, im::ImagingRegion::Shape::kFrame);
}

TEST(ConvexTracking, SteepNeedleUnderABrighterLongerInterface) {
  im::ConvexInsertion c = insertion(33, -0.6, 60);
  c.layer_amplitude = 2.5;
  const Tracked t = track(c);
  expectLastTipRight(t, "60 degrees under a brighter interface");
  expectNoConfidentWrong(t, "60 degrees under a brighter interface");
}

TEST(ConvexTracking, FanEdgeNextToTheEntry) {
  const Tracked t = track(insertion(35, -1.1, 30));  // enters through the fan's straight edge
  expectLastTipRight(t, "entry at the fan's edge");
  expectNoConfidentWrong(t, "entry at the fan's edge");
}

TEST(ConvexTracking, NeedleNearlyAlongTheBeamIsRightOrRefused) {
  // 80 degrees to the rows near the fan's middle: about 20 degrees from the beam, a weak echo.
  const Tracked t = track(insertion(37, -0.3, 80));
  expectNoConfidentWrong(t, "along the beam");
  for (std::size_t k = 0; k < t.out.size(); ++k) {
    if (t.out[k].segment.found && t.out[k].confident) {
      EXPECT_LT(cv::norm(t.out[k].segment.tip_px - t.truth[k]), kTipTolerance_px);
    }
  }
}

TEST(ConvexTracking, NeedleAppearingPartWay) {
  im::ConvexInsertion c = insertion(39, 0.8, 40);
  c.appear_at = 6;
  const Tracked t = track(c);
  for (int k = 0; k < c.appear_at; ++k)
    EXPECT_FALSE(t.out[std::size_t(k)].confident) << "frame " << k << " has no needle";
  expectLastTipRight(t, "appearing part-way");
  expectNoConfidentWrong(t, "appearing part-way");
}

TEST(ConvexTracking, SparseSequence) {
  // Frames 0.2-0.5 s apart: the needle 20 px further each frame, the speckle largely new.
  im::ConvexInsertion c = insertion(41, -0.85, 35);
  c.step_px = 20;
  c.decorrelation = 0.6;
  c.frames = 10;
  const Tracked t = track(c);
  expectLastTipRight(t, "sparse");
  expectNoConfidentWrong(t, "sparse");
}

TEST(ConvexTracking, FanWithoutANeedleIsNeverConfident) {
  im::ConvexInsertion c = insertion(43, -0.8, 35);
  c.appear_at = -1;
  c.frames = 12;
  c.layer_amplitude = 2.5;
  const Tracked t = track(c);
  for (std::size_t k = 0; k < t.out.size(); ++k)
    EXPECT_FALSE(t.out[k].confident) << "frame " << k << ": " << t.out[k].segment.message;
}

TEST(ConvexTracking, FanWithoutANeedleMostlyAnswersNotFound) {
  // Interfaces a few degrees off the rows never rise to the skin beside the probe: "not found"
  // is the answer, not a tip on an interface.
  constexpr double kNotFoundShare = 0.8;
  im::ConvexInsertion c = insertion(47, 0.8, 35);
  c.appear_at = -1;
  c.frames = 10;
  const Tracked t = track(c);
  int not_found = 0;
  for (const auto& o : t.out)
    not_found += o.segment.found ? 0 : 1;
  EXPECT_GE(not_found, kNotFoundShare * static_cast<double>(t.out.size()));
}

TEST(ConvexTracking, TiltedInterfaceMeetingTheFanEdgeHalfWayDownIsNoNeedle) {
  // A bright interface from the fan's left edge at 0.45 of its depth, 8 degrees down to the
  // right, ending inside the fan: shaped like a shallow needle from that edge, but traced back
  // it meets the skin several fan widths from the probe.
  im::ConvexInsertion c = insertion(49, -0.8, 35);
  im::ConvexScene scene = c.scene();
  const im::ConvexProbe& p = scene.probe;
  const double r = p.face_radius_px + 0.45 * p.depth_px;
  im::ConvexLayer layer;
  layer.a = p.apex_px + r * cv::Point2d(std::sin(-p.half_angle_rad), std::cos(p.half_angle_rad));
  const double tilt = 8.0 * CV_PI / 180.0;
  layer.b = layer.a + 380.0 * cv::Point2d(std::cos(tilt), std::sin(tilt));
  layer.amplitude = 2.0;
  scene.layers = {layer};
  im::SequenceTracker tracker(im::AcquisitionOptions{});
  for (int k = 0; k < 8; ++k) {
    const auto out = tracker.onFrame(im::renderConvexFrame(scene, c.size, {}, std::uint64_t(k)));
    EXPECT_FALSE(out.segment.found) << "frame " << k << ": " << out.segment.message;
  }
}

TEST(ConvexTracking, PhasedSectorNeedleFadingWithDepthIsFollowedToItsTip) {
  // A small face and a wide sector: the shaft's echo fades as it runs towards the sector's
  // middle; its tip is where the tissue brightens as it advances, not where the trace stops.
  im::ConvexInsertion c = insertion(51, 0.75, 45);
  c.face_radius_px = 70;
  c.half_angle_rad = 0.65;
  const Tracked t = track(c);
  expectLastTipRight(t, "phased sector, fading shaft");
  expectNoConfidentWrong(t, "phased sector, fading shaft");
}

TEST(ConvexTracking, PriorsPickTheNeedleOverADecoyAndOrientIt) {
  const im::ConvexInsertion c = insertion(45, -0.8, 35);
  const im::ConvexScene scene = c.scene();
  cv::Point2d tip;
  double angle = 0.0;
  const std::vector<cv::Point2d> pts = c.needleAt(10, &tip, &angle);
  cv::Mat frame = im::renderConvexFrame(scene, c.size, pts, 0);
  // A brighter straight decoy across the other half of the fan.
  cv::line(frame, cv::Point(420, 120), cv::Point(600, 260), cv::Scalar(250), 5, cv::LINE_AA);
  im::AcquisitionOptions o;
  o.entry_point_px = pts[60];  // where the needle crosses the probe face
  o.entry_angle_rad = angle;
  const im::NeedleSegment s = im::acquireNeedle(frame, o);
  ASSERT_TRUE(s.found) << s.message;
  EXPECT_LT(cv::norm(s.tip_px - tip), kTipTolerance_px) << s.message;
  EXPECT_LT(angleDeg(s.angle_rad, angle), kAngleTolerance_deg);
  // An angle prior the other way round: the decoy's direction rules the needle out.
  im::AcquisitionOptions wrong;
  wrong.entry_angle_rad = angle + CV_PI / 2.0;
  const im::NeedleSegment w = im::acquireNeedle(frame, wrong);
  if (w.found) {
    EXPECT_GT(cv::norm(w.tip_px - tip), kTipTolerance_px);
  }
}

/// Single frames of needles just inserted from either end of the probe, each the first frame
/// with `inserted_px` of it in the fan (most of it inside the face's ring-down band).
struct JustInserted {
  std::vector<cv::Mat> frames;
  std::vector<cv::Point2d> tips;

  /// Renders the first frame of `c` with at least `inserted_px` of the needle in view (its
  /// last frame if none has), with its true tip.
  void addFirstFrameWith(const im::ConvexInsertion& c, double inserted_px) {
    int f = 0;
    while (f + 1 < c.frames && c.visibleLength(f) < inserted_px)
      ++f;
    cv::Point2d tip;
    double angle = 0.0;
    const std::vector<cv::Point2d> pts = c.needleAt(f, &tip, &angle);
    frames.push_back(im::renderConvexFrame(c.scene(), c.size, pts, std::uint64_t(f)));
    tips.push_back(tip);
  }
};

JustInserted justInserted(double inserted_px, double layer_amplitude = 0.0) {
  const struct {
    std::uint64_t seed;
    double entry, angle_deg;
  } cases[] = {{81, -0.8, 35}, {82, 0.8, 30}, {83, -0.75, 45}, {84, 0.85, 40},
               {85, -0.9, 30}, {86, 0.7, 35}, {87, -0.8, 50},  {88, 0.75, 45}};
  JustInserted j;
  for (const auto& k : cases) {
    im::ConvexInsertion c = insertion(k.seed, k.entry, k.angle_deg);
    if (layer_amplitude > 0.0) {
      c.layer_amplitude = layer_amplitude;
      c.layers = 3;
    }
    j.addFirstFrameWith(c, inserted_px);
  }
  return j;
}

/// How many of the frames give a tip within kTipTolerance_px.
int foundRight(const JustInserted& j, const im::AcquisitionOptions& options) {
  int right = 0;
  for (std::size_t k = 0; k < j.frames.size(); ++k) {
    const im::NeedleSegment s = im::acquireNeedle(j.frames[k], options);
    right += s.found && cv::norm(s.tip_px - j.tips[k]) < kTipTolerance_px ? 1 : 0;
  }
  return right;
}

/// First frames (60 px inserted) of steeper needles, 45-52 degrees from either end of the
/// probe, under three bright interfaces, at a low gain with more electronic noise.
JustInserted steepJustInserted() {
  const double angles_deg[] = {45, 50, 48, 52, 45, 47, 50, 46};
  JustInserted j;
  for (int q = 0; q < 8; ++q) {
    im::ConvexInsertion c = insertion(91 + q, q % 2 ? 0.78 : -0.78, angles_deg[q]);
    c.gain_db = -6;
    c.noise_std = 0.2;
    c.layers = 3;
    c.layer_amplitude = 2.2;
    cv::Point2d tip;
    double angle = 0.0;
    const std::vector<cv::Point2d> pts = c.needleAt(0, &tip, &angle);
    j.frames.push_back(im::renderConvexFrame(c.scene(), c.size, pts, 0));
    j.tips.push_back(tip);
  }
  return j;
}

TEST(ConvexTracking, NeedleJustInsertedInTheFaceBandIsFound) {
  // 55 px of each needle in the fan, three bright interfaces below: most of the shaft lies in
  // the face's ring-down band, whose gradient and compression hide it, and the interfaces hold
  // the whole fan's strongest ridge. Without the depth profile's flattening fewer are found;
  // without the entry zone's own round, fewer of the steeper needles under brighter interfaces.
  constexpr int kAtLeast = 5;
  const JustInserted j = justInserted(55.0, 2.5);
  im::AcquisitionOptions no_flat, no_zone;
  no_flat.flatten_depth = false;
  no_zone.entry_zone = false;
  const int all_rules = foundRight(j, {});
  EXPECT_GE(all_rules, kAtLeast);
  EXPECT_GT(all_rules, foundRight(j, no_flat)) << "the depth profile's flattening finds more";
  const JustInserted steep = steepJustInserted();
  const int steep_all = foundRight(steep, {});
  EXPECT_GE(steep_all, kAtLeast);
  EXPECT_GT(steep_all, foundRight(steep, no_zone)) << "the entry zone's own round finds more";
}

/// Frames, of the first `frames` of a needle at 72 degrees to the rows (18 from the beam), found
/// with the tip within kTipTolerance_px.
int nearAxialFound(const im::AcquisitionOptions& options, std::uint64_t seed, int frames) {
  im::ConvexInsertion c = insertion(seed, -0.7, 72);
  c.step_px = 6;
  c.frames = frames;
  const Tracked t = track(c, options);
  int right = 0;
  for (std::size_t k = 0; k < t.out.size(); ++k) {
    const auto& s = t.out[k].segment;
    right += t.truth[k].x >= 0.0 && s.found && cv::norm(s.tip_px - t.truth[k]) < kTipTolerance_px;
  }
  return right;
}

TEST(ConvexTracking, NeedleNearlyAlongTheBeamIsFoundFromItsFirstFrames) {
  // 18 degrees from the beam: a weak echo, its ridge no stronger than the speckle's until each
  // depth is brought to the speckle's typical spread. Found in every one of its first 8 frames.
  constexpr int kFrames = 8;
  im::AcquisitionOptions no_flat;
  no_flat.flatten_depth = false;
  const int on = nearAxialFound(im::AcquisitionOptions{}, 92, kFrames);
  EXPECT_EQ(on, kFrames);
  EXPECT_GT(on, nearAxialFound(no_flat, 92, kFrames))
      << "the depth profile's flattening finds more";
}

/// First frames of needles meeting the probe face at 10-18 degrees, beside either end of the
/// probe (a large face, a crop off-centre, a small face), each with 55-65 px in the fan: for
/// its first 30-50 px the shaft stays within the strip along the face whose ridge is left out.
struct ShallowEntry {
  std::uint64_t seed;
  double entry, angle_deg, face_radius_px, half_angle_rad, apex_dx_px;
};

/// The probe of case k, its layout seeded by k.seed.
im::ConvexInsertion shallowInsertion(const ShallowEntry& k) {
  im::ConvexInsertion c = insertion(k.seed, k.entry, k.angle_deg);
  c.face_radius_px = k.face_radius_px;
  c.half_angle_rad = k.half_angle_rad;
  c.apex_dx_px = k.apex_dx_px;
  return c;
}

JustInserted shallowEntries(const std::vector<ShallowEntry>& cases, double inserted_px) {
  JustInserted j;
  for (const ShallowEntry& k : cases) {
    im::ConvexInsertion c = shallowInsertion(k);
    c.start_px = 20.0;
    c.step_px = 4.0;
    j.addFirstFrameWith(c, inserted_px);
  }
  return j;
}

TEST(ConvexTracking, NeedleEnteringAcrossTheFaceAtAShallowAngleIsFound) {
  // 60 px in the fan, in a single frame: the shaft's traced part lies within the band along the
  // boundary that holds the region's own edge, and its first part is hidden in the strip whose
  // ridge is left out. It enters across the boundary, steadily deeper: a needle, found.
  constexpr int kAtLeast = 7;
  const std::vector<ShallowEntry> cases = {
      {131, -0.8, 36, 330, 0.55, 0},   {132, 0.8, 37, 330, 0.55, 0}, {133, -0.7, 33, 330, 0.55, 0},
      {134, 0.75, 35, 330, 0.55, 40},  {135, -0.8, 40, 200, 0.6, 0}, {136, 0.85, 42, 200, 0.6, 0},
      {137, -0.7, 40, 330, 0.55, -60}, {138, 0.7, 32, 330, 0.55, 0}};
  const JustInserted j = shallowEntries(cases, 60.0);
  im::AcquisitionOptions off;
  off.entry_across_edge = false;
  const int on = foundRight(j, {});
  EXPECT_GE(on, kAtLeast);
  EXPECT_GT(on, foundRight(j, off)) << "a shaft entering across the fan's edge is found more";
}

TEST(ConvexTracking, TheFanEdgeAloneIsNoNeedle) {
  // Fans without a needle (large and small faces, crops, three interfaces): the face's arc, its
  // ring-down band and the straight sides are never taken for a needle entering across them.
  const std::vector<ShallowEntry> cases = {
      {141, -0.8, 36, 330, 0.55, 0},   {142, 0.8, 37, 330, 0.55, 0}, {143, -0.7, 33, 330, 0.55, 0},
      {144, 0.75, 35, 330, 0.55, 40},  {145, -0.8, 40, 200, 0.6, 0}, {146, 0.85, 42, 70, 0.65, 0},
      {147, -0.7, 40, 330, 0.55, -60}, {148, 0.7, 32, 60, 0.7, 0}};
  constexpr double kEdgeBand_px = 24.0;  // the band along the boundary that holds its own edge
  for (const ShallowEntry& k : cases) {
    im::ConvexInsertion c = shallowInsertion(k);
    c.appear_at = -1;
    c.layers = 3;
    for (int f = 0; f < 3; ++f) {
      const cv::Mat frame = im::renderConvexFrame(c.scene(), c.size, {}, std::uint64_t(f));
      const im::NeedleSegment s = im::acquireNeedle(frame, {});
      if (!s.found)
        continue;
      const im::ImagingRegion region = im::findImagingRegion(frame);
      EXPECT_GT(std::max(region.insetAt(s.tip_px), region.insetAt(s.tail_px)), kEdgeBand_px)
          << "seed " << k.seed << " frame " << f << ": " << s.message;
    }
  }
}

TEST(ConvexTracking, BadPriorIsRefusedByName) {
  im::AcquisitionOptions o;
  o.entry_angle_rad = std::nan("");
  EXPECT_THROW(o.validate(), std::invalid_argument);
  const im::NeedleSegment s = im::acquireNeedle(cv::Mat(100, 100, CV_8U, cv::Scalar(50)), o);
  EXPECT_FALSE(s.found);
  EXPECT_NE(s.message.find("entry_angle_rad"), std::string::npos) << s.message;
}

TEST(ConvexRenderer, RefusesABadProbeAndIsDeterministic) {
  im::ConvexInsertion c = insertion(47, -0.8, 35);
  im::ConvexScene scene = c.scene();
  cv::Point2d tip;
  double angle = 0.0;
  const auto pts = c.needleAt(3, &tip, &angle);
  const cv::Mat a = im::renderConvexFrame(scene, c.size, pts, 3);
  const cv::Mat b = im::renderConvexFrame(scene, c.size, pts, 3);
  EXPECT_EQ(cv::norm(a, b, cv::NORM_INF), 0.0);
  EXPECT_EQ(a.at<std::uint8_t>(c.size.height - 1, 0), 0) << "outside the fan is black";
  scene.probe.half_angle_rad = 0.0;
  EXPECT_THROW(im::renderConvexFrame(scene, c.size, pts, 0), std::invalid_argument);
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}

// The imager's convex model (UltrasoundModel::kConvex): the fan at the top of the frame, black
// above the probe face, a sector the tracker recognises; a probe that does not fit the frame
// and an out-of-range angle are refused naming them.
TEST(ConvexRenderer, TheImagerDrawsAConvexFanAndRefusesAProbeThatDoesNotFit) {
  const needle_guidance::scene::Scene scene =
      needle_guidance::scene::loadSceneSpec("steering_workspace");
  im::ImagerConfig c = im::imagerConfigFromScene(scene, 3);
  c.modality = im::Modality::kUltrasound;
  c.ultrasound_model = im::UltrasoundModel::kConvex;
  c.geometry = im::fieldOfView(scene, 0.15e-3, 720, 440);
  EXPECT_EQ(im::toString(c.ultrasound_model), "convex");
  EXPECT_EQ(im::ultrasoundModelFromString("convex"), im::UltrasoundModel::kConvex);
  const im::FrameRenderer renderer(scene, c);
  const cv::Mat frame = renderer.render({}, 0).image;
  ASSERT_EQ(frame.size(), cv::Size(720, 440));
  EXPECT_EQ(frame.at<std::uint8_t>(2, 2), 0) << "above the face's end: outside the fan";
  EXPECT_EQ(frame.at<std::uint8_t>(2, 717), 0);
  EXPECT_GT(cv::mean(frame(cv::Rect(300, 150, 120, 120)))[0], 20.0) << "tissue inside the fan";
  EXPECT_EQ(im::findImagingRegion(frame).shape, im::ImagingRegion::Shape::kSector);
  EXPECT_EQ(cv::norm(frame, renderer.render({}, 0).image, cv::NORM_INF), 0.0) << "deterministic";

  im::ImagerConfig wide = c;
  wide.convex_radius_m = 0.2;  // a face chord of 1393 px in a 720 px frame
  try {
    im::FrameRenderer bad(scene, wide);
    ADD_FAILURE() << "a face wider than the frame was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("convex probe"), std::string::npos) << e.what();
  }
  im::ImagerConfig steep = c;
  steep.convex_half_angle_rad = 2.0;
  try {
    steep.validate();
    ADD_FAILURE() << "a half angle of 2 rad was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("convex_half_angle_rad"), std::string::npos) << e.what();
  }
}
