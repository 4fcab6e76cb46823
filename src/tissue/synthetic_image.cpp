// Image geometry of the slice and its reference image: a file named by the scene or a synthetic
// B-mode-like image made from the segmented regions (the texture of dissertation 2.3.7).
#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdint>
#include <limits>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "needle_guidance/tissue/image_warp.h"

namespace needle_guidance::tissue {
namespace {

// Synthetic B-mode appearance (fractions of full scale and physical lengths).
constexpr double kCapsuleEchogenicity = 0.75;  // hyperechoic organ capsule
constexpr double kCapsuleWidth_m = 0.4e-3;
constexpr double kNoTissueEchogenicity = 0.02;  // workspace outside every region, no background
constexpr double kEchoBlurSigma_m = 0.1e-3;     // soften region edges before speckle
// Speckle grain: Gaussian sigma of the smoothing of the complex field. y is the beam axis of a
// probe on the y = 0 face (trans-rectal, 2.4), so the grain is short in y, long in x.
constexpr double kSpeckleSigmaLateral_m = 0.4e-3;
constexpr double kSpeckleSigmaAxial_m = 0.15e-3;
// Gaussian blur with a sigma below this many pixels is skipped (it would be the identity).
constexpr double kMinBlurSigma_px = 0.05;
constexpr int kPolygonShiftBits = 8;  // sub-pixel precision of cv::fillPoly / polylines vertices

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

// Vertices of a polygon as fixed-point pixel coordinates for cv::fillPoly (kPolygonShiftBits).
std::vector<cv::Point> fixedPointPixels(const geometry::Polygon& polygon, const ImageGeometry& g) {
  constexpr double kScale = 1 << kPolygonShiftBits;
  std::vector<cv::Point> points;
  points.reserve(polygon.size());
  for (const Point2& v : polygon.vertices()) {
    const cv::Point2d p = g.toPixel(v);
    points.emplace_back(static_cast<int>(std::lround(p.x * kScale)),
                        static_cast<int>(std::lround(p.y * kScale)));
  }
  return points;
}

// Standard normal pairs from std::mt19937 by Box-Muller: the same numbers with every standard
// library (std::normal_distribution's algorithm is implementation-defined).
class NormalPairs {
public:
  explicit NormalPairs(std::uint32_t seed) : rng_(seed) {}
  void next(float& a, float& b) {
    constexpr double kTwoPi = 6.283185307179586;
    constexpr double kInv2To32 = 1.0 / 4294967296.0;
    const double u1 = (static_cast<double>(rng_()) + 0.5) * kInv2To32;  // in (0, 1)
    const double u2 = (static_cast<double>(rng_()) + 0.5) * kInv2To32;
    const double r = std::sqrt(-2.0 * std::log(u1));
    a = static_cast<float>(r * std::cos(kTwoPi * u2));
    b = static_cast<float>(r * std::sin(kTwoPi * u2));
  }

private:
  std::mt19937 rng_;
};

void gaussianBlurIfWide(cv::Mat& image, double sigma_x_px, double sigma_y_px) {
  if (sigma_x_px < kMinBlurSigma_px && sigma_y_px < kMinBlurSigma_px) {
    return;
  }
  cv::GaussianBlur(image, image, cv::Size(0, 0), std::max(sigma_x_px, kMinBlurSigma_px),
                   std::max(sigma_y_px, kMinBlurSigma_px), cv::BORDER_REFLECT);
}

}  // namespace

cv::Point2d ImageGeometry::toPixel(const Point2& p_scene) const {
  return {(p_scene.x() - origin_m.x()) / pixel_size_m - 0.5,
          (origin_m.y() - p_scene.y()) / pixel_size_m - 0.5};
}

Point2 ImageGeometry::toScene(const cv::Point2d& p_px) const {
  return {origin_m.x() + (p_px.x + 0.5) * pixel_size_m,
          origin_m.y() - (p_px.y + 0.5) * pixel_size_m};
}

void ImageGeometry::validate(const char* where) const {
  std::ostringstream msg;
  msg << where << ": ImageGeometry ";
  if (!(std::isfinite(pixel_size_m) && pixel_size_m > 0.0)) {
    msg << "pixel_size_m " << pixel_size_m << " is not positive and finite";
  } else if (rows <= 0 || cols <= 0) {
    msg << "size " << cols << " x " << rows << " px is empty";
  } else if (!origin_m.allFinite()) {
    msg << "origin_m (" << origin_m.x() << ", " << origin_m.y() << ") is not finite";
  } else {
    return;
  }
  throw std::invalid_argument(msg.str());
}

ImageGeometry forWorkspace(const scene::Scene& scene, double pixel_size_m) {
  if (!(std::isfinite(pixel_size_m) && pixel_size_m > 0.0)) {
    throw std::invalid_argument("forWorkspace: pixel_size_m " + std::to_string(pixel_size_m) +
                                " is not positive and finite");
  }
  const Point2 extent_m = scene.workspace_max - scene.workspace_min;
  if (!(extent_m.allFinite() && extent_m.x() > 0.0 && extent_m.y() > 0.0)) {
    throw std::invalid_argument("forWorkspace: scene '" + scene.name + "' has an empty workspace");
  }
  // A whole number of pixels up to rounding (6 cm / 0.2 mm = 299.99999999999994) is exact.
  constexpr double kWholePixelTol = 1e-6;
  auto count = [&](double length_m) {
    const double n = length_m / pixel_size_m;
    if (n > static_cast<double>(std::numeric_limits<int>::max() / 2)) {
      throw std::invalid_argument("forWorkspace: pixel_size_m " + std::to_string(pixel_size_m) +
                                  " gives an image too large");
    }
    return std::max(1, static_cast<int>(std::ceil(n - kWholePixelTol)));
  };
  ImageGeometry g;
  g.origin_m = Point2(scene.workspace_min.x(), scene.workspace_max.y());
  g.pixel_size_m = pixel_size_m;
  g.cols = count(extent_m.x());
  g.rows = count(extent_m.y());
  return g;
}

double meanEchogenicity(const std::string& material_name) {
  const std::string name = lower(material_name);
  if (name == "fat")
    return 0.45;
  if (name == "prostate")
    return 0.22;
  if (name == "muscle")
    return 0.30;
  if (name == "bone")
    return 0.85;
  return 0.35;
}

cv::Mat rayleighSpeckle(cv::Size size, double sigma_x_px, double sigma_y_px, std::uint32_t seed) {
  // Fully developed speckle: |smoothed complex Gaussian field| is Rayleigh distributed; the
  // smoothing kernel sets the grain. Scaled to unit mean so it multiplies the echogenicity.
  cv::Mat re(size, CV_32F), im(size, CV_32F);
  NormalPairs normal(seed);
  for (int r = 0; r < size.height; ++r) {
    float* re_row = re.ptr<float>(r);
    float* im_row = im.ptr<float>(r);
    for (int c = 0; c < size.width; ++c) {
      normal.next(re_row[c], im_row[c]);
    }
  }
  gaussianBlurIfWide(re, sigma_x_px, sigma_y_px);
  gaussianBlurIfWide(im, sigma_x_px, sigma_y_px);
  cv::Mat speckle;
  cv::magnitude(re, im, speckle);
  const double mean_speckle = cv::mean(speckle)[0];
  if (mean_speckle > 0.0) {
    speckle *= 1.0 / mean_speckle;
  }
  return speckle;
}

cv::Mat syntheticUltrasound(const scene::Scene& scene, const ImageGeometry& g, std::uint32_t seed) {
  g.validate("syntheticUltrasound");

  // Mean echogenicity map: workspace background, then the regions in order.
  cv::Mat echo(g.rows, g.cols, CV_32F, cv::Scalar(0.0));
  const double background = scene.background_material.empty()
                                ? kNoTissueEchogenicity
                                : meanEchogenicity(scene.background_material);
  cv::fillPoly(echo,
               std::vector<std::vector<cv::Point>>{fixedPointPixels(scene.workspacePolygon(), g)},
               cv::Scalar(background), cv::LINE_8, kPolygonShiftBits);
  for (const scene::Region& region : scene.regions) {
    const double e = region.rigid ? meanEchogenicity("bone") : meanEchogenicity(region.material);
    cv::fillPoly(echo, std::vector<std::vector<cv::Point>>{fixedPointPixels(region.polygon, g)},
                 cv::Scalar(e), cv::LINE_8, kPolygonShiftBits);
  }
  const int capsule_px =
      std::max(1, static_cast<int>(std::lround(kCapsuleWidth_m / g.pixel_size_m)));
  for (const scene::Region& region : scene.regions) {
    cv::polylines(echo, std::vector<std::vector<cv::Point>>{fixedPointPixels(region.polygon, g)},
                  true, cv::Scalar(kCapsuleEchogenicity), capsule_px, cv::LINE_8,
                  kPolygonShiftBits);
  }
  const double echo_sigma_px = kEchoBlurSigma_m / g.pixel_size_m;
  gaussianBlurIfWide(echo, echo_sigma_px, echo_sigma_px);

  const cv::Mat speckle = rayleighSpeckle(g.size(), kSpeckleSigmaLateral_m / g.pixel_size_m,
                                          kSpeckleSigmaAxial_m / g.pixel_size_m, seed);
  cv::Mat image;
  cv::Mat(echo.mul(speckle)).convertTo(image, CV_8U, 255.0);  // rounds, saturates
  return image;
}

cv::Mat referenceImage(const scene::Scene& scene, const ImageGeometry& g, std::uint32_t seed) {
  g.validate("referenceImage");
  const std::string& path = scene.imaging.reference_image;
  if (path.empty()) {
    return syntheticUltrasound(scene, g, seed);
  }
  const cv::Mat loaded = cv::imread(path, cv::IMREAD_GRAYSCALE);
  if (loaded.empty()) {
    throw std::invalid_argument("referenceImage: cannot read imaging.reference_image '" + path +
                                "' as an image");
  }
  if (loaded.size() == g.size()) {
    return loaded;
  }
  const bool shrinking = loaded.cols >= g.cols && loaded.rows >= g.rows;
  cv::Mat resized;
  cv::resize(loaded, resized, g.size(), 0.0, 0.0, shrinking ? cv::INTER_AREA : cv::INTER_LINEAR);
  return resized;
}

}  // namespace needle_guidance::tissue
