// Simulated fluoroscopy / ultrasound frames of the scene plane (see frame_renderer.h).
#include "needle_guidance/imaging/frame_renderer.h"

#include "realistic_ultrasound.h"
#include "render_util.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::imaging {
namespace {

using render::fixedPoint;
using render::kShiftBits;
using render::kShiftScale;
using render::mix;
using render::streamSeed;
using render::uniform01;
constexpr double kMinBlurSigma_px = 0.05;  // a narrower Gaussian is the identity

// ---- fluoroscopy (fractions of full scale as displayed: bright = little absorbed) ----
constexpr double kFluoroSoftTissue = 0.78;
constexpr double kFluoroRegionContrast = 0.06;      // soft-tissue regions: +- this by echogenicity
constexpr double kFluoroBone = 0.42;                // rigid regions and obstacles
constexpr double kFluoroVignette = 0.18;            // brightness lost at the frame's corners
constexpr double kFluoroNeedleTransmission = 0.18;  // the metal needle keeps 18 % of the light

// ---- ultrasound ----
constexpr double kUsTissue = 0.25;            // background tissue echogenicity
constexpr double kUsObstacleInterior = 0.10;  // inside an obstacle (bone-like, little comes back)
constexpr double kUsBoundary = 0.85;          // specular tissue boundary (obstacle outline)
constexpr double kUsBoundaryWidth_m = 0.4e-3;
constexpr double kUsTargetEcho = 0.22;          // the target lesion is hypoechoic
constexpr double kUsSpeckleLateral_m = 0.4e-3;  // speckle grain across the beam (x)
constexpr double kUsSpeckleAxial_m = 0.15e-3;   // and along it (y)
constexpr double kUsAttenuation_per_m = 6.0;    // gain exp(-k d) after time-gain compensation
constexpr double kUsShadowGain = 0.3;           // behind an obstacle along the beam
constexpr double kUsNeedleMin = 0.45;           // needle echo when parallel to the beam
constexpr double kUsNeedleMax = 1.3;            // needle echo when facing the beam
constexpr double kUsNeedleSpecularPower = 2.0;  // echo ~ |cos(angle to the probe face)|^p
constexpr double kUsNeedleDropoutDepth = 0.5;   // partial visibility along the shaft
constexpr double kUsNeedleDropoutPeriod_m = 6e-3;
constexpr double kUsTipEcho = 1.3;  // the bevel reflects strongly
constexpr double kUsTipEchoLength_m = 0.8e-3;
constexpr int kUsReverberations = 3;  // comet-tail echoes behind the needle
constexpr double kUsReverberationSpacing_m = 1.6e-3;
constexpr double kUsReverberationDecay = 0.45;
constexpr double kUsEchoFullScale = 1.5;       // the needle echo canvas (8-bit) spans 0..1.5
constexpr double kNeedleDrawStep_m = 0.25e-3;  // the needle is drawn as pieces this long

void fillPolygon(cv::Mat& image, const geometry::Polygon& polygon, const ImageGeometry& g,
                 double value) {
  cv::fillPoly(image, std::vector<std::vector<cv::Point>>{fixedPoint(polygon.vertices(), g)},
               cv::Scalar(value), cv::LINE_AA, kShiftBits);
}

void blur(cv::Mat& image, double sigma_px) {
  if (sigma_px >= kMinBlurSigma_px) {
    cv::GaussianBlur(image, image, cv::Size(0, 0), sigma_px, sigma_px, cv::BORDER_REFLECT);
  }
}

// A smooth pseudo-random visibility in [1 - depth, 1] along the needle's arc length: the sum of
// two sinusoids with seeded phases (the needle's surface does not change between frames).
double shaftVisibility(double s_m, std::uint64_t seed) {
  constexpr double kTwoPi = 6.283185307179586;
  const double p1 = kTwoPi * uniform01(mix(seed ^ 0xA1U));
  const double p2 = kTwoPi * uniform01(mix(seed ^ 0xB2U));
  const double w = kTwoPi / kUsNeedleDropoutPeriod_m;
  const double v = 0.5 + 0.25 * std::sin(w * s_m + p1) + 0.25 * std::sin(1.7 * w * s_m + p2);
  return 1.0 - kUsNeedleDropoutDepth * std::clamp(v, 0.0, 1.0);
}

/// The frame's additive Gaussian noise (the device's electronics), fraction of full scale.
void addNoise(cv::Mat* image, const ImagerConfig& config, std::uint64_t index) {
  if (config.noise_std > 0.0) {
    cv::Mat noise(image->size(), CV_32F);
    cv::RNG rng(streamSeed(config.seed, index, 0x401));
    rng.fill(noise, cv::RNG::NORMAL, 0.0, config.noise_std);
    *image += noise;
  }
}

}  // namespace

std::string toString(UltrasoundModel model) {
  switch (model) {
    case UltrasoundModel::kRealistic:
      return "realistic";
    case UltrasoundModel::kConvex:
      return "convex";
    case UltrasoundModel::kClassic:
      break;
  }
  return "classic";
}

std::optional<UltrasoundModel> ultrasoundModelFromString(const std::string& name) {
  if (name == "classic") {
    return UltrasoundModel::kClassic;
  }
  if (name == "realistic") {
    return UltrasoundModel::kRealistic;
  }
  if (name == "convex") {
    return UltrasoundModel::kConvex;
  }
  return std::nullopt;
}

std::string toString(Modality modality) {
  return modality == Modality::kFluoroscopy ? "fluoroscopy" : "ultrasound";
}

std::optional<Modality> modalityFromString(const std::string& name) {
  if (name == "fluoroscopy") {
    return Modality::kFluoroscopy;
  }
  if (name == "ultrasound") {
    return Modality::kUltrasound;
  }
  return std::nullopt;
}

void ImagerConfig::validate() const {
  geometry.validate("ImagerConfig.geometry");
  std::ostringstream why;
  if (!(std::isfinite(noise_std) && noise_std >= 0.0)) {
    why << "noise_std " << noise_std << " is not >= 0 and finite";
  } else if (!(std::isfinite(blur_sigma_m) && blur_sigma_m >= 0.0)) {
    why << "blur_sigma_m " << blur_sigma_m << " is not >= 0 and finite";
  } else if (!(drop_probability >= 0.0 && drop_probability < 1.0)) {
    why << "drop_probability " << drop_probability << " is not in [0, 1)";
  } else if (!(std::isfinite(needle_diameter_m) && needle_diameter_m > 0.0)) {
    why << "needle_diameter_m " << needle_diameter_m << " is not > 0 and finite";
  } else if (!(tissue_motion_px >= 0.0 && tissue_motion_px <= 10.0)) {
    why << "tissue_motion_px " << tissue_motion_px << " is not in [0, 10]";
  } else if (!(std::isfinite(convex_radius_m) && convex_radius_m > 0.0)) {
    why << "convex_radius_m " << convex_radius_m << " is not > 0 and finite";
  } else if (!(convex_half_angle_rad > 0.0 && convex_half_angle_rad <= 1.4)) {
    why << "convex_half_angle_rad " << convex_half_angle_rad << " is not in (0, 1.4]";
  } else {
    return;
  }
  throw std::invalid_argument("ImagerConfig: " + why.str());
}

ImagerConfig imagerConfigFromScene(const scene::Scene& scene, std::uint64_t seed) {
  const std::optional<Modality> modality = modalityFromString(scene.imaging.modality);
  if (!modality) {
    throw std::invalid_argument("imagerConfigFromScene: scene '" + scene.name +
                                "' imaging.modality '" + scene.imaging.modality +
                                "' is not ultrasound or fluoroscopy");
  }
  ImagerConfig c;
  c.modality = *modality;
  c.geometry = tissue::forWorkspace(scene, scene.imaging.pixel_size_m);
  c.noise_std = scene.imaging.noise_std;
  c.blur_sigma_m = scene.imaging.blur_sigma_m;
  c.drop_probability = scene.imaging.drop_probability;
  if (scene.needle.diameter_m > 0.0) {
    c.needle_diameter_m = scene.needle.diameter_m;
  }
  c.seed = seed;
  c.validate();
  return c;
}

ImageGeometry fieldOfView(const scene::Scene& scene, double pixel_size_m, int cols, int rows) {
  if (cols < 0 || rows < 0) {
    throw std::invalid_argument("fieldOfView: size " + std::to_string(cols) + " x " +
                                std::to_string(rows) + " px is negative");
  }
  ImageGeometry g = tissue::forWorkspace(scene, pixel_size_m);
  if (cols == 0 || rows == 0) {
    return g;
  }
  const Point2 centre = 0.5 * (scene.workspace_min + scene.workspace_max);
  g.cols = cols;
  g.rows = rows;
  g.origin_m =
      Point2(centre.x() - 0.5 * cols * pixel_size_m, centre.y() + 0.5 * rows * pixel_size_m);
  return g;
}

namespace {

/// UltrasoundModel::kConvex: the probe over the frame (its face's ends on row kConvexFaceTop_px,
/// centred), imaging down to the frame's last row. Throws std::invalid_argument when the face's
/// chord is wider than the frame or the face reaches below it.
ConvexScene convexScene(const ImagerConfig& c) {
  const ImageGeometry& g = c.geometry;
  ConvexScene sc;
  ConvexProbe& p = sc.probe;
  p.pixel_size_m = g.pixel_size_m;
  p.face_radius_px = c.convex_radius_m / g.pixel_size_m;
  p.half_angle_rad = c.convex_half_angle_rad;
  p.apex_px = cv::Point2d(0.5 * (g.cols - 1), FrameRenderer::kConvexFaceTop_px -
                                                  p.face_radius_px * std::cos(p.half_angle_rad));
  p.depth_px = (g.rows - 1) - (p.apex_px.y + p.face_radius_px);
  const double chord_px = 2.0 * p.face_radius_px * std::sin(p.half_angle_rad);
  if (chord_px > g.cols || p.depth_px <= 0.0) {
    std::ostringstream why;
    why << "ImagerConfig: a convex probe of radius " << c.convex_radius_m << " m and half angle "
        << c.convex_half_angle_rad << " rad (face " << chord_px << " px wide, "
        << p.face_radius_px * (1.0 - std::cos(p.half_angle_rad))
        << " px deep) does not fit a frame of " << g.cols << " x " << g.rows << " px";
    throw std::invalid_argument(why.str());
  }
  p.validate();
  sc.noise_std = c.noise_std;
  sc.seed = c.seed;
  return sc;
}

}  // namespace

FrameRenderer::FrameRenderer(const scene::Scene& scene, const ImagerConfig& config)
    : config_(config) {
  config_.validate();
  const ImageGeometry& g = config_.geometry;
  if (config_.modality == Modality::kFluoroscopy) {
    anatomy_ = cv::Mat(g.size(), CV_32F, cv::Scalar(kFluoroSoftTissue));
    for (const scene::Region& region : scene.regions) {
      const double v =
          region.rigid
              ? kFluoroBone
              : kFluoroSoftTissue + kFluoroRegionContrast *
                                        (0.35 - tissue::meanEchogenicity(region.material)) / 0.35;
      fillPolygon(anatomy_, region.polygon, g, v);
    }
    for (const scene::Obstacle& obstacle : scene.obstacles) {
      fillPolygon(anatomy_, obstacle.polygon, g, kFluoroBone);
    }
    // Vignetting: the image intensifier is darker towards the corners.
    const double cx = 0.5 * (g.cols - 1), cy = 0.5 * (g.rows - 1);
    const double r2max = cx * cx + cy * cy;
    for (int r = 0; r < g.rows; ++r) {
      float* row = anatomy_.ptr<float>(r);
      for (int c = 0; c < g.cols; ++c) {
        const double r2 = ((c - cx) * (c - cx) + (r - cy) * (r - cy)) / std::max(r2max, 1.0);
        row[c] = float(row[c] * (1.0 - kFluoroVignette * r2));
      }
    }
    return;
  }

  if (config_.ultrasound_model == UltrasoundModel::kRealistic) {
    realistic::anatomy(scene, config_, &anatomy_, &attenuation_);
    return;
  }
  if (config_.ultrasound_model == UltrasoundModel::kConvex) {
    convex_ = std::make_shared<const ConvexScene>(convexScene(config_));
    return;
  }
  // Ultrasound: echogenicity map x static speckle; attenuation and shadows as a separate gain
  // so that the needle, drawn per frame, is attenuated like the tissue around it.
  cv::Mat echo(g.size(), CV_32F, cv::Scalar(kUsTissue));
  for (const scene::Region& region : scene.regions) {
    fillPolygon(echo, region.polygon, g,
                region.rigid ? tissue::meanEchogenicity("bone")
                             : tissue::meanEchogenicity(region.material));
  }
  for (const scene::Target& target : scene.targets) {
    if (target.radius_m > 0.0) {
      const cv::Point2d c = g.toPixel(target.position);
      cv::circle(
          echo, cv::Point(int(std::lround(c.x * kShiftScale)), int(std::lround(c.y * kShiftScale))),
          int(std::lround(target.radius_m / g.pixel_size_m * kShiftScale)),
          cv::Scalar(kUsTargetEcho), cv::FILLED, cv::LINE_AA, kShiftBits);
    }
  }
  cv::Mat obstacle_mask(g.size(), CV_8U, cv::Scalar(0));
  const int boundary_px = std::max(1, int(std::lround(kUsBoundaryWidth_m / g.pixel_size_m)));
  for (const scene::Obstacle& obstacle : scene.obstacles) {
    const std::vector<std::vector<cv::Point>> outline{fixedPoint(obstacle.polygon.vertices(), g)};
    cv::fillPoly(echo, outline, cv::Scalar(kUsObstacleInterior), cv::LINE_AA, kShiftBits);
    cv::fillPoly(obstacle_mask, outline, cv::Scalar(255), cv::LINE_8, kShiftBits);
    cv::polylines(echo, outline, true, cv::Scalar(kUsBoundary), boundary_px, cv::LINE_AA,
                  kShiftBits);
  }
  for (const scene::Region& region : scene.regions) {
    cv::polylines(echo,
                  std::vector<std::vector<cv::Point>>{fixedPoint(region.polygon.vertices(), g)},
                  true, cv::Scalar(0.75), boundary_px, cv::LINE_AA, kShiftBits);
  }
  const cv::Mat speckle = tissue::rayleighSpeckle(
      g.size(), kUsSpeckleLateral_m / g.pixel_size_m, kUsSpeckleAxial_m / g.pixel_size_m,
      std::uint32_t(streamSeed(config_.seed, 0, 0x5EC)));
  anatomy_ = echo.mul(speckle);

  // The probe is on the lower face (the bottom row); the beam travels up the image (+y).
  // Shadow: every pixel beyond an obstacle along its column.
  attenuation_ = cv::Mat(g.size(), CV_32F);
  for (int c = 0; c < g.cols; ++c) {
    bool shadowed = false;
    bool inside = false;
    for (int r = g.rows - 1; r >= 0; --r) {
      const bool in_obstacle = obstacle_mask.at<std::uint8_t>(r, c) != 0;
      if (inside && !in_obstacle) {
        shadowed = true;
      }
      inside = in_obstacle;
      const double depth_m = (g.rows - 1 - r) * g.pixel_size_m;
      attenuation_.at<float>(r, c) =
          float(std::exp(-kUsAttenuation_per_m * depth_m) * (shadowed ? kUsShadowGain : 1.0));
    }
  }
  // Soften the shadow edges a little (diffraction).
  blur(attenuation_, 1.0);
}

bool FrameRenderer::dropped(std::uint64_t index) const {
  return config_.drop_probability > 0.0 &&
         uniform01(streamSeed(config_.seed, index, 0xD509)) < config_.drop_probability;
}

Frame FrameRenderer::render(const std::vector<Point2>& needle_points, std::uint64_t index) const {
  for (std::size_t i = 0; i < needle_points.size(); ++i) {
    if (!needle_points[i].allFinite()) {
      throw std::invalid_argument("FrameRenderer::render: needle point " + std::to_string(i) +
                                  " is not finite");
    }
  }
  Frame frame;
  frame.index = index;
  if (dropped(index)) {
    frame.dropped = true;
    return frame;
  }
  const ImageGeometry& g = config_.geometry;
  if (convex_) {
    std::vector<cv::Point2d> needle_px;
    for (const Point2& p : needle_points)
      needle_px.push_back(g.toPixel(p));
    frame.image = renderConvexFrame(*convex_, g.size(), needle_px, index);
    return frame;
  }
  if (config_.modality == Modality::kUltrasound &&
      config_.ultrasound_model == UltrasoundModel::kRealistic) {
    // The noise enters before the log compression (realistic_ultrasound.h).
    const cv::Mat image = realistic::frame(anatomy_, attenuation_, config_, needle_points, index);
    image.convertTo(frame.image, CV_8U, 255.0);
    return frame;
  }
  const int thickness_px =
      std::max(1, int(std::lround(config_.needle_diameter_m / g.pixel_size_m)));

  // The needle as short pieces: each piece's coverage (mask) and, in ultrasound, its echo.
  cv::Mat mask(g.size(), CV_8U, cv::Scalar(0));
  cv::Mat echo;  // ultrasound: needle echo x coverage, 0..255 = 0..kUsEchoFullScale
  if (config_.modality == Modality::kUltrasound) {
    echo = cv::Mat(g.size(), CV_8U, cv::Scalar(0));
  }
  std::vector<Point2> pieces;  // resampled every kNeedleDrawStep_m
  std::vector<double> lengths;
  render::resampleNeedle(needle_points, kNeedleDrawStep_m, &pieces, &lengths);
  const double total_m = lengths.empty() ? 0.0 : lengths.back();
  std::vector<std::vector<cv::Point>> ghosts(kUsReverberations);
  for (std::size_t i = 1; i < pieces.size(); ++i) {
    const std::vector<cv::Point> ab = fixedPoint({pieces[i - 1], pieces[i]}, g);
    cv::line(mask, ab[0], ab[1], cv::Scalar(255), thickness_px, cv::LINE_AA, kShiftBits);
    if (config_.modality != Modality::kUltrasound) {
      continue;
    }
    const Point2 d = pieces[i] - pieces[i - 1];
    const double cos_to_face = d.norm() > 0.0 ? std::abs(d.x()) / d.norm() : 0.0;
    double e = kUsNeedleMin +
               (kUsNeedleMax - kUsNeedleMin) * std::pow(cos_to_face, kUsNeedleSpecularPower);
    e *= shaftVisibility(lengths[i], config_.seed);
    if (total_m - lengths[i] <= kUsTipEchoLength_m) {
      e = std::max(e, kUsTipEcho);
    }
    cv::line(echo, ab[0], ab[1], cv::Scalar(255.0 * e / kUsEchoFullScale), thickness_px,
             cv::LINE_AA, kShiftBits);
    for (int k = 1; k <= kUsReverberations; ++k) {
      const Point2 shift(0.0, k * kUsReverberationSpacing_m);
      const std::vector<cv::Point> gh = fixedPoint({pieces[i - 1] + shift, pieces[i] + shift}, g);
      const double ge = e * std::pow(kUsReverberationDecay, k);
      cv::line(echo, gh[0], gh[1], cv::Scalar(255.0 * ge / kUsEchoFullScale),
               std::max(1, thickness_px - 1), cv::LINE_AA, kShiftBits);
    }
  }

  cv::Mat image;
  cv::Mat coverage;
  mask.convertTo(coverage, CV_32F, 1.0 / 255.0);
  if (config_.modality == Modality::kFluoroscopy) {
    // Transmission multiplies: I = I0 * (1 - coverage * (1 - T)).
    cv::Mat transmit = 1.0 - coverage * (1.0 - kFluoroNeedleTransmission);
    image = anatomy_.mul(transmit);
  } else {
    cv::Mat needle_echo;
    echo.convertTo(needle_echo, CV_32F, kUsEchoFullScale / 255.0);
    // The needle replaces the tissue it covers; its reverberation ghosts add to the tissue.
    image = anatomy_.mul(1.0 - coverage) + needle_echo;
    image = image.mul(attenuation_);
  }
  blur(image, config_.blur_sigma_m / g.pixel_size_m);
  addNoise(&image, config_, index);
  image.convertTo(frame.image, CV_8U, 255.0);  // rounds and saturates to 0..255
  return frame;
}

std::vector<Point2> insertedNeedlePoints(Point2 p_SceneEntry, double angle_rad, double length_m,
                                         double kappa_per_m, double step_m) {
  std::vector<Point2> pts;
  for (double s = 0.0; s <= length_m + 1e-12; s += step_m) {
    if (kappa_per_m == 0.0) {
      pts.push_back(p_SceneEntry + s * Point2(std::cos(angle_rad), std::sin(angle_rad)));
    } else {
      const double h = angle_rad + kappa_per_m * s;
      pts.push_back(p_SceneEntry +
                    Point2(std::sin(h) - std::sin(angle_rad), std::cos(angle_rad) - std::cos(h)) /
                        kappa_per_m);
    }
  }
  return pts;
}

}  // namespace needle_guidance::imaging
