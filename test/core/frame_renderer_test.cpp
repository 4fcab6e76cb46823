// Tests of the simulated imager (imaging/frame_renderer.h): calibration, determinism, the needle's
// appearance in both modalities, dropped frames, clipping and refusals.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <vector>

#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/scene/scene.h"

namespace ng = needle_guidance;
namespace im = ng::imaging;
using ng::geometry::Point2;

namespace {

constexpr double kPixel_m = 0.2e-3;
/// Round trip pixel -> scene -> pixel [px].
constexpr double kRoundTripTol_px = 1e-9;
/// Contrast of the needle against the tissue around it, in grey levels, without noise.
constexpr double kMinNeedleContrast_grey = 40.0;
/// Binomial tolerance on the drop rate over kDropFrames frames (> 4 standard deviations).
constexpr int kDropFrames = 4000;
constexpr double kDropProbability = 0.3;
constexpr double kDropRateTol = 0.035;

ng::scene::Scene steeringScene() {
  return ng::scene::loadSceneSpec("steering_workspace");
}

im::ImagerConfig config(const ng::scene::Scene& scene, im::Modality modality, double noise) {
  im::ImagerConfig c = im::imagerConfigFromScene(scene, 7);
  c.modality = modality;
  c.geometry = im::fieldOfView(scene, kPixel_m, 640, 480);
  c.noise_std = noise;
  c.blur_sigma_m = 0.0;
  c.drop_probability = 0.0;
  return c;
}

/// A straight horizontal needle from x = 0 to x = 20 mm at y = 20 mm (clear of every obstacle).
std::vector<Point2> horizontalNeedle() {
  std::vector<Point2> points;
  for (int i = 0; i <= 40; ++i) {
    points.emplace_back(i * 0.5e-3, 0.02);
  }
  return points;
}

double grey(const cv::Mat& image, const im::ImageGeometry& g, const Point2& p) {
  const cv::Point2d px = g.toPixel(p);
  return image.at<std::uint8_t>(int(std::lround(px.y)), int(std::lround(px.x)));
}

/// Mean grey level of a 5 x 5 block around p.
double meanAround(const cv::Mat& image, const im::ImageGeometry& g, const Point2& p) {
  const cv::Point2d px = g.toPixel(p);
  const cv::Rect block(int(std::lround(px.x)) - 2, int(std::lround(px.y)) - 2, 5, 5);
  return cv::mean(image(block))[0];
}

}  // namespace

TEST(FrameRenderer, FieldOfViewIsCentredAndRoundTrips) {
  const auto scene = steeringScene();
  const im::ImageGeometry g = im::fieldOfView(scene, kPixel_m, 640, 480);
  EXPECT_EQ(g.cols, 640);
  EXPECT_EQ(g.rows, 480);
  // The workspace centre (5 cm, 5 cm) is the image centre (319.5, 239.5).
  const cv::Point2d centre = g.toPixel(Point2(0.05, 0.05));
  EXPECT_NEAR(centre.x, 319.5, kRoundTripTol_px);
  EXPECT_NEAR(centre.y, 239.5, kRoundTripTol_px);
  const Point2 back = g.toScene(cv::Point2d(12.25, 400.5));
  const cv::Point2d again = g.toPixel(back);
  EXPECT_NEAR(again.x, 12.25, kRoundTripTol_px);
  EXPECT_NEAR(again.y, 400.5, kRoundTripTol_px);
  // 0 x 0: the whole workspace.
  const im::ImageGeometry whole = im::fieldOfView(scene, kPixel_m);
  EXPECT_EQ(whole.cols, 500);
  EXPECT_EQ(whole.rows, 500);
  EXPECT_THROW(im::fieldOfView(scene, kPixel_m, -1, 10), std::invalid_argument);
  EXPECT_THROW(im::fieldOfView(scene, 0.0, 10, 10), std::invalid_argument);
}

TEST(FrameRenderer, SameIndexSameFrameOtherIndexOtherNoise) {
  const auto scene = steeringScene();
  const im::FrameRenderer renderer(scene, config(scene, im::Modality::kUltrasound, 0.1));
  const auto needle = horizontalNeedle();
  const im::Frame a = renderer.render(needle, 5);
  const im::Frame b = renderer.render(needle, 5);
  const im::Frame c = renderer.render(needle, 6);
  ASSERT_FALSE(a.dropped);
  EXPECT_EQ(a.image.type(), CV_8UC1);
  EXPECT_EQ(a.image.size(), cv::Size(640, 480));
  EXPECT_EQ(cv::countNonZero(a.image != b.image), 0);
  EXPECT_GT(cv::countNonZero(a.image != c.image), 640 * 480 / 4);
}

TEST(FrameRenderer, FluoroscopyNeedleIsDarkOnBrightTissue) {
  const auto scene = steeringScene();
  const im::ImagerConfig c = config(scene, im::Modality::kFluoroscopy, 0.0);
  const im::FrameRenderer renderer(scene, c);
  const cv::Mat with = renderer.render(horizontalNeedle(), 0).image;
  const cv::Mat without = renderer.render({}, 0).image;
  const Point2 on_needle(0.01, 0.02);
  EXPECT_GT(grey(without, c.geometry, on_needle) - grey(with, c.geometry, on_needle),
            kMinNeedleContrast_grey);
  // Bone (an obstacle) is darker than soft tissue.
  EXPECT_LT(meanAround(without, c.geometry, Point2(0.035, 0.03)),
            meanAround(without, c.geometry, Point2(0.02, 0.03)) - kMinNeedleContrast_grey);
}

TEST(FrameRenderer, UltrasoundNeedleIsBrightWhereItFacesTheBeam) {
  const auto scene = steeringScene();
  const im::ImagerConfig c = config(scene, im::Modality::kUltrasound, 0.0);
  const im::FrameRenderer renderer(scene, c);
  const cv::Mat with = renderer.render(horizontalNeedle(), 0).image;
  const cv::Mat without = renderer.render({}, 0).image;
  // The tip's bevel echo is the brightest part; the tissue there is speckle around 0.25.
  const Point2 tip(0.0199, 0.02);
  EXPECT_GT(meanAround(with, c.geometry, tip) - meanAround(without, c.geometry, tip),
            kMinNeedleContrast_grey);
  // A reverberation ghost lies 1.6 mm deeper (+y) and is fainter than the needle.
  const Point2 shaft(0.01, 0.02), ghost(0.01, 0.0216);
  const double needle_gain =
      meanAround(with, c.geometry, shaft) - meanAround(without, c.geometry, shaft);
  const double ghost_gain =
      meanAround(with, c.geometry, ghost) - meanAround(without, c.geometry, ghost);
  EXPECT_GT(ghost_gain, 0.0);
  EXPECT_LT(ghost_gain, needle_gain);
}

TEST(FrameRenderer, DroppedFramesAreEmptyAtTheConfiguredRate) {
  const auto scene = steeringScene();
  im::ImagerConfig c = config(scene, im::Modality::kFluoroscopy, 0.0);
  c.geometry = im::fieldOfView(scene, 2e-3, 16, 16);  // small: only the drop draw matters
  c.drop_probability = kDropProbability;
  const im::FrameRenderer renderer(scene, c);
  int dropped = 0;
  for (int i = 0; i < kDropFrames; ++i) {
    const im::Frame f = renderer.render({}, std::uint64_t(i));
    EXPECT_EQ(f.dropped, renderer.dropped(std::uint64_t(i)));
    EXPECT_EQ(f.dropped, f.image.empty());
    dropped += f.dropped ? 1 : 0;
  }
  EXPECT_NEAR(double(dropped) / kDropFrames, kDropProbability, kDropRateTol);
}

TEST(FrameRenderer, NeedleOutsideTheFieldOfViewIsClipped) {
  const auto scene = steeringScene();
  const im::ImagerConfig c = config(scene, im::Modality::kUltrasound, 0.05);
  const im::FrameRenderer renderer(scene, c);
  const std::vector<Point2> far = {Point2(-1.0, -1.0), Point2(-0.5, 2.0), Point2(0.05, 0.05)};
  const im::Frame f = renderer.render(far, 0);
  EXPECT_EQ(f.image.size(), cv::Size(640, 480));
}

TEST(FrameRenderer, RefusesBadSettingsAndPoints) {
  const auto scene = steeringScene();
  const double nan = std::numeric_limits<double>::quiet_NaN();
  auto refused = [&](auto change) {
    im::ImagerConfig c = config(scene, im::Modality::kUltrasound, 0.0);
    change(c);
    EXPECT_THROW(im::FrameRenderer(scene, c), std::invalid_argument);
  };
  refused([](im::ImagerConfig& c) { c.noise_std = -0.1; });
  refused([&](im::ImagerConfig& c) { c.blur_sigma_m = nan; });
  refused([](im::ImagerConfig& c) { c.drop_probability = 1.0; });
  refused([](im::ImagerConfig& c) { c.needle_diameter_m = 0.0; });
  refused([](im::ImagerConfig& c) { c.geometry.cols = 0; });
  const im::FrameRenderer renderer(scene, config(scene, im::Modality::kUltrasound, 0.0));
  EXPECT_THROW(renderer.render({Point2(0.0, 0.02), Point2(nan, 0.02)}, 0), std::invalid_argument);
  EXPECT_EQ(im::modalityFromString("xray"), std::nullopt);
  EXPECT_EQ(im::modalityFromString("fluoroscopy"), im::Modality::kFluoroscopy);
}

// ---- the realistic ultrasound model ----

namespace {

/// Grey level of a bright specular structure (the display saturates at 255).
constexpr double kBright_grey = 200.0;
/// A layer spans the frame: bright over at least this fraction of its width.
constexpr double kLayerSpanFraction = 0.9;
/// Shadow: the tissue 2-8 mm beyond the needle keeps at most this fraction of its grey level.
constexpr double kShadowMaxRatio = 0.85;
/// Log compression: the speckle's mean over its standard deviation (Rayleigh on a linear
/// scale: 1.91; the in-vitro scanner's: about 6).
constexpr double kMinLogSpeckleSnr = 3.0;
/// Out of plane: some seed's tilt dims the tip by at least this against the entry [grey].
constexpr double kMinFade_grey = 15.0;

im::ImagerConfig realisticConfig(const ng::scene::Scene& scene, std::uint64_t seed) {
  im::ImagerConfig c = config(scene, im::Modality::kUltrasound, 0.0);
  c.ultrasound_model = im::UltrasoundModel::kRealistic;
  c.seed = seed;
  return c;
}

/// A straight horizontal needle from x = 0 to x = 40 mm at y = 20 mm (below both layers).
std::vector<Point2> longNeedle() {
  std::vector<Point2> points;
  for (int i = 0; i <= 80; ++i) {
    points.emplace_back(i * 0.5e-3, 0.02);
  }
  return points;
}

}  // namespace

TEST(FrameRenderer, UltrasoundModelNamesRoundTrip) {
  for (const auto m : {im::UltrasoundModel::kClassic, im::UltrasoundModel::kRealistic}) {
    EXPECT_EQ(im::ultrasoundModelFromString(im::toString(m)), m);
  }
  EXPECT_FALSE(im::ultrasoundModelFromString("Realistic").has_value());
  EXPECT_EQ(im::ImagerConfig().ultrasound_model, im::UltrasoundModel::kClassic);
}

TEST(FrameRenderer, RealisticTissueMotionMovesTheTissueNotTheNeedleAndIsValidated) {
  const auto scene = ng::scene::loadSceneSpec("steering_workspace");
  im::ImagerConfig c = realisticConfig(scene, 7);
  // Still tissue (the default): frames 0 and 6 without needle or noise are the same.
  const im::FrameRenderer still(scene, c);
  const cv::Mat s0 = still.render({}, 0).image, s6 = still.render({}, 6).image;
  EXPECT_EQ(cv::norm(s0, s6, cv::NORM_INF), 0.0);
  // Moving at 1.5 px / frame: frame 6 is the tissue moved by about 6 x 1.5 = 9 px of drift
  // plus the sway; phase correlation finds a shift of at least kMinMoved_px.
  constexpr double kMinMoved_px = 3.0;
  c.tissue_motion_px = 1.5;
  const im::FrameRenderer moving(scene, c);
  cv::Mat m0, m6;
  moving.render({}, 0).image.convertTo(m0, CV_32F);
  moving.render({}, 6).image.convertTo(m6, CV_32F);
  EXPECT_GT(cv::norm(cv::phaseCorrelate(m0, m6)), kMinMoved_px);
  for (const double bad : {-1.0, 11.0, std::nan("")}) {
    c.tissue_motion_px = bad;
    try {
      c.validate();
      ADD_FAILURE() << "tissue_motion_px " << bad << " accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("tissue_motion_px"), std::string::npos) << e.what();
    }
  }
}

TEST(FrameRenderer, RealisticLayersAreLongerAndBrighterThanTheNeedle) {
  // Without the obstacles (their shadows would cut the layers into pieces).
  auto scene = steeringScene();
  scene.obstacles.clear();
  const im::ImagerConfig c = realisticConfig(scene, 7);
  const im::FrameRenderer renderer(scene, c);
  const cv::Mat with = renderer.render(longNeedle(), 0).image;
  EXPECT_EQ(cv::norm(with, renderer.render(longNeedle(), 0).image, cv::NORM_INF), 0.0);
  // Bright structures as connected components: each layer spans the frame, the needle 40 mm of
  // its 128 mm.
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(with >= kBright_grey, labels, stats, centroids, 8);
  const cv::Point needle_px = c.geometry.toPixel(Point2(0.02, 0.02));
  const int needle_label = labels.at<int>(needle_px.y, needle_px.x);
  ASSERT_GT(needle_label, 0) << "the needle's shaft is not bright";
  const int needle_width = stats.at<int>(needle_label, cv::CC_STAT_WIDTH);
  const double needle_grey = cv::mean(with, labels == needle_label)[0];
  int layers = 0;
  for (int k = 1; k < n; ++k) {
    if (k != needle_label &&
        stats.at<int>(k, cv::CC_STAT_WIDTH) >= kLayerSpanFraction * with.cols) {
      ++layers;
      EXPECT_GT(stats.at<int>(k, cv::CC_STAT_WIDTH), 2 * needle_width);
      EXPECT_GT(cv::mean(with, labels == k)[0], needle_grey) << "layer " << k;
    }
  }
  EXPECT_EQ(layers, 2);
  EXPECT_LT(needle_width, 0.5 * with.cols);
}

TEST(FrameRenderer, RealisticNeedleCastsAShadowAndAReverberationTail) {
  const auto scene = steeringScene();
  const im::ImagerConfig c = realisticConfig(scene, 7);
  const im::FrameRenderer renderer(scene, c);
  const cv::Mat with = renderer.render(longNeedle(), 0).image;
  const cv::Mat without = renderer.render({}, 0).image;
  // Beyond the needle from the probe (on the bottom row): +y in the scene.
  const cv::Point2d a = c.geometry.toPixel(Point2(0.005, 0.028));
  const cv::Point2d b = c.geometry.toPixel(Point2(0.025, 0.023));
  const cv::Rect beyond(cv::Point(int(a.x), int(a.y)), cv::Point(int(b.x), int(b.y)));
  EXPECT_LT(cv::mean(with(beyond))[0], kShadowMaxRatio * cv::mean(without(beyond))[0]);
  // The tail: copies 0.5 and 1.0 mm deeper are brighter than the tissue there.
  for (const double dy : {0.5e-3, 1.0e-3}) {
    const Point2 p(0.01, 0.02 + dy);
    EXPECT_GT(meanAround(with, c.geometry, p), meanAround(without, c.geometry, p) + 10.0) << dy;
  }
}

TEST(FrameRenderer, RealisticSpeckleIsLogCompressedLikeAScanner) {
  const auto scene = steeringScene();
  const im::ImagerConfig c = realisticConfig(scene, 7);
  const cv::Mat frame = im::FrameRenderer(scene, c).render({}, 0).image;
  const cv::Mat classic =
      im::FrameRenderer(scene, config(scene, im::Modality::kUltrasound, 0.0)).render({}, 0).image;
  // A patch of plain tissue: below both layers, left of every obstacle.
  const cv::Point2d a = c.geometry.toPixel(Point2(0.002, 0.018));
  const cv::Rect patch(int(a.x), int(a.y), 60, 40);
  cv::Scalar mean, sd, mean_classic, sd_classic;
  cv::meanStdDev(frame(patch), mean, sd);
  cv::meanStdDev(classic(patch), mean_classic, sd_classic);
  EXPECT_GT(mean[0] / sd[0], kMinLogSpeckleSnr);
  EXPECT_LT(mean_classic[0] / sd_classic[0], kMinLogSpeckleSnr);
}

TEST(FrameRenderer, RealisticNeedleFadesTowardsTheTipOutOfPlane) {
  const auto scene = steeringScene();
  double deepest_fade = 0.0;
  for (std::uint64_t seed = 1; seed <= 10; ++seed) {
    const im::ImagerConfig c = realisticConfig(scene, seed);
    const im::FrameRenderer renderer(scene, c);
    const cv::Mat with = renderer.render(longNeedle(), 0).image;
    const double entry = meanAround(with, c.geometry, Point2(0.004, 0.02));
    const double tip = meanAround(with, c.geometry, Point2(0.038, 0.02));
    EXPECT_LE(tip, entry + 3.0) << "seed " << seed;  // never brighter towards the tip
    deepest_fade = std::max(deepest_fade, entry - tip);
  }
  EXPECT_GT(deepest_fade, kMinFade_grey);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
