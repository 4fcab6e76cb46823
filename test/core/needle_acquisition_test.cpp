// Hard cases of needle acquisition without a prior (imaging/needle_acquisition.h, issue 17) on
// synthetic B-mode frames made here (speckle from a random scatterer field convolved with an
// anisotropic point-spread function, specular interfaces between media of different
// echogenicity, a needle with an acoustic shadow beneath and a reverberation tail). Fixed seeds.
#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "needle_guidance/imaging/needle_acquisition.h"

namespace im = needle_guidance::imaging;

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kTipTolerance_px = 8.0;  // the median target
constexpr double kPsfReach_px = 3.0;  // blur of the drawn needle (sigma 1 px) and its 1 px radius
constexpr double kAngleTolerance_rad = 3.0 * kPi / 180.0;
const cv::Size kSize(720, 440);

struct Needle {
  cv::Point2d tail, tip;
  double brightness = 170.0;   ///< grey levels added on the shaft
  double fade_fraction = 0.0;  ///< last part of the shaft fading linearly to 0 (out of plane)
};
struct Interface {
  double y0, y1;              ///< rows at x = 0 and x = cols - 1
  double brightness = 230.0;  ///< brighter than the needle
  double below_gain = 0.4;    ///< echogenicity below it relative to above
};

/// Speckle: the envelope of two Gaussian scatterer fields convolved with a PSF that is longer
/// laterally (x) than axially (y), mean about 60 grey levels.
cv::Mat speckle(std::uint64_t seed) {
  cv::RNG rng(seed);
  cv::Mat a(kSize, CV_32F), b(kSize, CV_32F);
  rng.fill(a, cv::RNG::NORMAL, 0, 1);
  rng.fill(b, cv::RNG::NORMAL, 0, 1);
  cv::GaussianBlur(a, a, cv::Size(), 3.0, 1.0);
  cv::GaussianBlur(b, b, cv::Size(), 3.0, 1.0);
  cv::Mat env;
  cv::magnitude(a, b, env);
  const double m = cv::mean(env)[0];
  return env * (60.0 / m);
}

double rowOf(const Interface& f, double x) {
  return f.y0 + (f.y1 - f.y0) * x / (kSize.width - 1);
}

/// One frame: speckle, optional interface (a step in echogenicity with a bright specular line
/// across the whole width), optional needle (shadow below it, two reverberation copies).
cv::Mat frame(std::uint64_t seed, const std::optional<Interface>& iface,
              const std::optional<Needle>& needle) {
  cv::Mat img = speckle(seed);
  cv::Mat add = cv::Mat::zeros(kSize, CV_32F);
  if (iface) {
    for (int y = 0; y < kSize.height; ++y) {
      for (int x = 0; x < kSize.width; ++x) {
        if (y > rowOf(*iface, x))
          img.at<float>(y, x) *= static_cast<float>(iface->below_gain);
      }
    }
    cv::line(add, cv::Point2d(0, iface->y0), cv::Point2d(kSize.width - 1, iface->y1),
             iface->brightness, 3, cv::LINE_AA);
  }
  if (needle) {
    const cv::Point2d d = needle->tip - needle->tail;
    const double len = cv::norm(d);
    const cv::Point2d u = d / len;
    for (double s = 0; s <= len; s += 0.5) {
      const cv::Point2d p = needle->tail + s * u;
      const double fade_start = (1.0 - needle->fade_fraction) * len;
      const double w = s < fade_start ? 1.0 : 1.0 - (s - fade_start) / (len - fade_start + 1e-9);
      cv::circle(add, p, 1, needle->brightness * w, cv::FILLED, cv::LINE_AA);
      for (int k = 1; k <= 2; ++k) {  // reverberation: dimmer copies deeper
        cv::circle(add, p + cv::Point2d(0, 10.0 * k), 1, 0.25 * needle->brightness * w / k,
                   cv::FILLED);
      }
      for (int y = static_cast<int>(p.y) + 3; y < kSize.height; ++y) {  // shadow
        const int x = static_cast<int>(p.x);
        if (x >= 0 && x < kSize.width)
          img.at<float>(y, x) *= 0.995F;
      }
    }
  }
  cv::GaussianBlur(add, add, cv::Size(), 1.0);
  img += add;
  cv::Mat out;
  img.convertTo(out, CV_8U);
  return out;
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
