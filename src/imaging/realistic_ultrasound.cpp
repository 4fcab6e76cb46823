// Realistic simulated B-mode; see realistic_ultrasound.h and
// UltrasoundModel::kRealistic in frame_renderer.h. Every constant is a physical statement about
// a linear probe at about 7 MHz imaging a soft-tissue phantom; none is fitted to a data set.
// bench tracking_real compares the frames with the in-vitro set (speckle grain, speckle
// signal-to-noise, needle and interface contrast) and reports the figures.
#include "realistic_ultrasound.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

#include "render_util.h"

namespace needle_guidance::imaging::realistic {
namespace {

using render::fixedPoint;
using render::kShiftBits;
using render::streamSeed;
using render::uniform01;

/// Speckle grain: the point-spread function's Gaussian sigmas across the beam (x) and along it
/// (y): about 1.2 mm and 0.35 mm full width at 7 MHz.
constexpr double kPsfLateral_m = 0.5e-3;
constexpr double kPsfAxial_m = 0.15e-3;
/// Specular layers (fascia, gel or fat boundaries): they span the frame, thicker and brighter
/// than the needle (amplitude above full scale saturates), nearly parallel to the probe face.
constexpr int kLayers = 2;
constexpr double kLayerAmplitude = 1.6;
constexpr double kLayerWidth_m = 0.8e-3;
constexpr double kLayerMaxTilt_rad = 0.08;
constexpr double kLayerBandLow = 0.25, kLayerBandHigh = 0.75;  // rows, fraction of the height
/// Echogenicity beyond a layer relative to before it: one brighter, one darker medium.
constexpr double kLayerGains[kLayers] = {0.55, 1.5};
/// Obstacle and region outlines are specular too: amplitude x |cos(angle to the probe face)|^2.
constexpr double kOutlineAmplitude = 0.8;
constexpr double kOutlineWidth_m = 0.4e-3;
constexpr double kObstacleInteriorEcho = 0.08;
constexpr double kTargetEcho = 0.15;  // hypoechoic lesion
/// The shadow behind an obstacle (depth attenuation: realistic_ultrasound.h).
constexpr double kObstacleShadowGain = 0.2;
constexpr double kNeedleDrawStep_m = 0.25e-3;
/// Out of plane: the needle's elevation grows along the shaft at a seeded slope in
/// [0, kMaxElevationSlope]; the echo falls with the elevation beam profile exp(-(e / w)^2).
constexpr double kMaxElevationSlope = 0.012;
constexpr double kElevationHalfWidth_m = 0.6e-3;
/// The needle canvas (8-bit, anti-aliased) spans amplitudes 0..kCanvasFullScale.
constexpr double kCanvasFullScale = 1.2;
/// Tissue motion (ImagerConfig::tissue_motion_px = m): a drift at m px / frame, a sway along the
/// beam of kSwayRatio x m with a kSwayPeriod-frame period, a compression along the beam of up
/// to kCompression, and kDecorrelation of the speckle's amplitude fresh in each frame.
constexpr double kSwayRatio = 1.5;
constexpr double kSwayPeriod = 10.0;
constexpr double kCompression = 0.01;
constexpr double kDecorrelation = 0.3;

/// A layer's row (image y) at column x: through (0, y0) with slope.
struct Layer {
  double y0 = 0.0, slope = 0.0;
  double rowAt(double x) const { return y0 + slope * x; }
};

std::vector<Layer> seededLayers(const ImagerConfig& config) {
  const ImageGeometry& g = config.geometry;
  std::vector<Layer> layers;
  for (int k = 0; k < kLayers; ++k) {
    const double band = (kLayerBandHigh - kLayerBandLow) / kLayers;
    const double u = uniform01(streamSeed(config.seed, 0, 0x1A7E0 + std::uint64_t(k)));
    const double v = uniform01(streamSeed(config.seed, 0, 0x1A7F0 + std::uint64_t(k)));
    Layer l;
    l.slope = std::tan(kLayerMaxTilt_rad * (2.0 * v - 1.0));
    // Centre of the layer in its own band of rows; y0 so that the centre column lands there.
    const double centre = g.rows * (kLayerBandLow + band * (k + 0.25 + 0.5 * u));
    l.y0 = centre - l.slope * 0.5 * (g.cols - 1);
    layers.push_back(l);
  }
  return layers;
}

/// Echogenicity map: background, regions, targets, obstacle interiors; beyond each layer (away
/// from the probe on the bottom row: smaller rows) the echogenicity changes by its gain.
cv::Mat echogenicity(const scene::Scene& scene, const ImageGeometry& g,
                     const std::vector<Layer>& layers, cv::Mat* obstacle_mask) {
  cv::Mat echo(g.size(), CV_32F, cv::Scalar(kTissueEcho));
  for (const scene::Region& region : scene.regions) {
    cv::fillPoly(echo,
                 std::vector<std::vector<cv::Point>>{fixedPoint(region.polygon.vertices(), g)},
                 cv::Scalar(region.rigid ? tissue::meanEchogenicity("bone")
                                         : tissue::meanEchogenicity(region.material)),
                 cv::LINE_AA, kShiftBits);
  }
  for (int r = 0; r < g.rows; ++r) {
    float* row = echo.ptr<float>(r);
    for (int c = 0; c < g.cols; ++c) {
      for (std::size_t k = 0; k < layers.size(); ++k) {
        if (r < layers[k].rowAt(c)) {
          row[c] *= float(kLayerGains[k]);
        }
      }
    }
  }
  for (const scene::Target& target : scene.targets) {
    if (target.radius_m > 0.0) {
      const cv::Point2d c = g.toPixel(target.position);
      cv::circle(echo, c, int(std::lround(target.radius_m / g.pixel_size_m)),
                 cv::Scalar(kTargetEcho), cv::FILLED, cv::LINE_AA);
    }
  }
  *obstacle_mask = cv::Mat(g.size(), CV_8U, cv::Scalar(0));
  for (const scene::Obstacle& obstacle : scene.obstacles) {
    const std::vector<std::vector<cv::Point>> outline{fixedPoint(obstacle.polygon.vertices(), g)};
    cv::fillPoly(echo, outline, cv::Scalar(kObstacleInteriorEcho), cv::LINE_AA, kShiftBits);
    cv::fillPoly(*obstacle_mask, outline, cv::Scalar(255), cv::LINE_8, kShiftBits);
  }
  return echo;
}

/// Specular outline of a polygon: each edge at kOutlineAmplitude x |cos(angle to the face)|^2.
void drawOutline(const std::vector<Point2>& vertices, const ImageGeometry& g, int width_px,
                 cv::Mat* specular) {
  for (std::size_t i = 0; i < vertices.size(); ++i) {
    const Point2 a = vertices[i], b = vertices[(i + 1) % vertices.size()];
    const Point2 d = b - a;
    const double c = d.norm() > 0.0 ? std::abs(d.x()) / d.norm() : 0.0;
    const std::vector<cv::Point> ab = fixedPoint({a, b}, g);
    cv::line(*specular, ab[0], ab[1], cv::Scalar(kOutlineAmplitude * c * c), width_px, cv::LINE_AA,
             kShiftBits);
  }
}

/// Per column, the gain beyond obstacles (away from the probe on the bottom row) and depth.
cv::Mat attenuationMap(const ImageGeometry& g, const cv::Mat& obstacle_mask) {
  cv::Mat att(g.size(), CV_32F);
  for (int c = 0; c < g.cols; ++c) {
    bool shadowed = false, inside = false;
    for (int r = g.rows - 1; r >= 0; --r) {
      const bool in_obstacle = obstacle_mask.at<std::uint8_t>(r, c) != 0;
      shadowed = shadowed || (inside && !in_obstacle);
      inside = in_obstacle;
      const double depth_m = (g.rows - 1 - r) * g.pixel_size_m;
      att.at<float>(r, c) =
          float(std::exp(-kAttenuation_per_m * depth_m) * (shadowed ? kObstacleShadowGain : 1.0));
    }
  }
  cv::GaussianBlur(att, att, cv::Size(0, 0), 1.0);
  return att;
}

/// The tissue of frame `index` moved (see ImagerConfig::tissue_motion_px): the static amplitude
/// warped and partly decorrelated; `amplitude` itself when the tissue is still.
cv::Mat movedTissue(const cv::Mat& amplitude, const ImagerConfig& config, std::uint64_t index) {
  const double m = config.tissue_motion_px;
  if (m <= 0.0)
    return amplitude;
  const ImageGeometry& g = config.geometry;
  const double heading = 2.0 * M_PI * uniform01(streamSeed(config.seed, 0, 0x7155));
  const double phase = 2.0 * M_PI * uniform01(streamSeed(config.seed, 0, 0x7156));
  const double k = static_cast<double>(index), w = 2.0 * M_PI / kSwayPeriod;
  // The sway's amplitude so that its peak speed is kSwayRatio x m.
  const double sway = kSwayRatio * m / w;
  const double dx = m * k * std::cos(heading);
  const double dy = m * k * std::sin(heading) + sway * (std::sin(w * k + phase) - std::sin(phase));
  const double scale = 1.0 - kCompression * 0.5 * (1.0 - std::cos(w * k));
  // Compression along the beam about the probe face (the last row), then the shift.
  const double face = g.rows - 1.0;
  const cv::Matx23d warp(1.0, 0.0, dx, 0.0, scale, face * (1.0 - scale) + dy);
  cv::Mat moved;
  cv::warpAffine(amplitude, moved, warp, amplitude.size(), cv::INTER_LINEAR, cv::BORDER_REFLECT);
  const cv::Mat fresh = tissue::rayleighSpeckle(
      g.size(), kPsfLateral_m / g.pixel_size_m, kPsfAxial_m / g.pixel_size_m,
      std::uint32_t(streamSeed(config.seed, index, 0x5EC3)));
  return moved.mul((1.0 - kDecorrelation) + kDecorrelation * fresh);
}

}  // namespace

double logCompress(double amplitude) {
  const double db = 20.0 * std::log10(std::max(amplitude, 1e-9));
  return std::clamp((db + kDynamicRange_dB) / kDynamicRange_dB, 0.0, 1.0);
}

void anatomy(const scene::Scene& scene, const ImagerConfig& config, cv::Mat* amplitude,
             cv::Mat* attenuation) {
  const ImageGeometry& g = config.geometry;
  const std::vector<Layer> layers = seededLayers(config);
  cv::Mat obstacle_mask;
  const cv::Mat echo = echogenicity(scene, g, layers, &obstacle_mask);
  // Scatterers of random amplitude through the PSF: the envelope is Rayleigh (unit mean), its
  // grain the PSF's; scaled by the local echogenicity.
  const cv::Mat speckle = tissue::rayleighSpeckle(
      g.size(), kPsfLateral_m / g.pixel_size_m, kPsfAxial_m / g.pixel_size_m,
      std::uint32_t(streamSeed(config.seed, 0, 0x5EC2)));
  *amplitude = speckle.mul(echo) * (kTissueAmplitude / kTissueEcho);
  cv::Mat specular(g.size(), CV_32F, cv::Scalar(0.0));
  const int outline_px = std::max(1, int(std::lround(kOutlineWidth_m / g.pixel_size_m)));
  for (const scene::Obstacle& obstacle : scene.obstacles) {
    drawOutline(obstacle.polygon.vertices(), g, outline_px, &specular);
  }
  for (const scene::Region& region : scene.regions) {
    drawOutline(region.polygon.vertices(), g, outline_px, &specular);
  }
  const int layer_px = std::max(1, int(std::lround(kLayerWidth_m / g.pixel_size_m)));
  for (const Layer& l : layers) {
    cv::line(specular, cv::Point2d(0.0, l.rowAt(0.0)),
             cv::Point2d(g.cols - 1.0, l.rowAt(g.cols - 1.0)), cv::Scalar(kLayerAmplitude),
             layer_px, cv::LINE_AA);
  }
  *amplitude = cv::max(*amplitude, specular);
  *attenuation = attenuationMap(g, obstacle_mask);
}

cv::Mat frame(const cv::Mat& amplitude, const cv::Mat& attenuation, const ImagerConfig& config,
              const std::vector<Point2>& needle_points, std::uint64_t index) {
  const ImageGeometry& g = config.geometry;
  std::vector<Point2> pieces;
  std::vector<double> lengths;
  render::resampleNeedle(needle_points, kNeedleDrawStep_m, &pieces, &lengths);
  const int thickness_px = std::max(1, int(std::lround(config.needle_diameter_m / g.pixel_size_m)));
  const double slope = kMaxElevationSlope * uniform01(streamSeed(config.seed, 0, 0xE1E7));
  cv::Mat echo(g.size(), CV_8U, cv::Scalar(0)), reverb(g.size(), CV_8U, cv::Scalar(0));
  // Shadow: per column, the row nearest the probe where the needle is, and its echo strength.
  std::vector<double> shadow_row(std::size_t(g.cols), -1.0),
      shadow_strength(std::size_t(g.cols), 0.0);
  for (std::size_t i = 1; i < pieces.size(); ++i) {
    const Point2 d = pieces[i] - pieces[i - 1];
    const double cos_face = d.norm() > 0.0 ? std::abs(d.x()) / d.norm() : 0.0;
    const double elevation_m = slope * lengths[i];
    const double in_plane = std::exp(-std::pow(elevation_m / kElevationHalfWidth_m, 2.0));
    const double e =
        (kNeedleParallel + (kNeedleFacing - kNeedleParallel) * cos_face * cos_face) * in_plane;
    const std::vector<cv::Point> ab = fixedPoint({pieces[i - 1], pieces[i]}, g);
    cv::line(echo, ab[0], ab[1], cv::Scalar(255.0 * e / kCanvasFullScale), thickness_px,
             cv::LINE_AA, kShiftBits);
    for (int k = 1; k <= kReverbCopies; ++k) {
      const Point2 shift(0.0, k * kReverbSpacing_m);
      const std::vector<cv::Point> gh = fixedPoint({pieces[i - 1] + shift, pieces[i] + shift}, g);
      cv::line(
          reverb, gh[0], gh[1],
          cv::Scalar(255.0 * e * kReverbFirst * std::pow(kReverbDecay, k - 1) / kCanvasFullScale),
          1, cv::LINE_AA, kShiftBits);
    }
    const cv::Point2d px = g.toPixel(pieces[i]);
    const int c = int(std::lround(px.x));
    if (c >= 0 && c < g.cols && px.y > shadow_row[std::size_t(c)]) {
      shadow_row[std::size_t(c)] = px.y;
      shadow_strength[std::size_t(c)] = in_plane;
    }
  }
  cv::Mat shadow(g.size(), CV_32F, cv::Scalar(1.0));
  for (int c = 0; c < g.cols; ++c) {
    const double row = shadow_row[std::size_t(c)] - thickness_px;
    const float gain = float(1.0 - (1.0 - kNeedleShadowGain) * shadow_strength[std::size_t(c)]);
    for (int r = 0; r < g.rows && r < row; ++r) {
      shadow.at<float>(r, c) = gain;
    }
  }
  cv::GaussianBlur(shadow, shadow, cv::Size(0, 0), 1.5, 0.5);
  cv::Mat needle;
  echo = cv::max(echo, reverb);  // a copy never hides the shaft drawn before it
  echo.convertTo(needle, CV_32F, kCanvasFullScale / 255.0);
  cv::Mat a = (movedTissue(amplitude, config, index).mul(shadow) + needle).mul(attenuation);
  if (config.noise_std > 0.0) {
    // Electronic noise enters the echo before envelope detection (a complex Gaussian: the
    // envelope of echo plus noise is Rician) and before the display's log compression; its
    // level is noise_std times the mean tissue echo.
    cv::Mat re(a.size(), CV_32F), im(a.size(), CV_32F);
    cv::RNG rng(streamSeed(config.seed, index, 0x401));
    const double sigma = config.noise_std * kTissueAmplitude;
    rng.fill(re, cv::RNG::NORMAL, 0.0, sigma);
    rng.fill(im, cv::RNG::NORMAL, 0.0, sigma);
    re += a;
    cv::magnitude(re, im, a);
  }
  const double blur_px = config.blur_sigma_m / g.pixel_size_m;
  if (blur_px >= 0.05) {
    cv::GaussianBlur(a, a, cv::Size(0, 0), blur_px, blur_px, cv::BORDER_REFLECT);
  }
  for (int r = 0; r < a.rows; ++r) {
    float* row = a.ptr<float>(r);
    for (int c = 0; c < a.cols; ++c) {
      row[c] = float(logCompress(row[c]));
    }
  }
  return a;
}

}  // namespace needle_guidance::imaging::realistic
