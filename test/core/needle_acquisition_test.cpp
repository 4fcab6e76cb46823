// Hard cases of needle acquisition without a prior (imaging/needle_acquisition.h, issue 17) on
// synthetic B-mode frames (imaging/synthetic_bmode.h: speckle from a random scatterer field
// convolved with an anisotropic point-spread function, specular interfaces between media of
// different echogenicity, a needle with an acoustic shadow beneath and a reverberation tail). Fixed
// seeds.
#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "needle_guidance/imaging/needle_acquisition.h"
#include "needle_guidance/imaging/synthetic_bmode.h"

namespace im = needle_guidance::imaging;

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kTipTolerance_px = 8.0;  // the median target
constexpr double kPsfReach_px = 3.0;  // blur of the drawn needle (sigma 1 px) and its 1 px radius
constexpr double kAngleTolerance_rad = 3.0 * kPi / 180.0;
const cv::Size kSize(720, 440);

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
  const double truth = std::atan2(n.tip.y - n.tail.y, n.tip.x - n.tail.x);
  EXPECT_LT(std::abs(s.angle_rad - truth), kAngleTolerance_rad) << s.message;
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

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
