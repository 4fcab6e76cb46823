// Baselines (3.3.4): rigid centre-of-mass translation, synthetic images, and intensity-based
// deformable registration (Thirion's demons; OpenCV optical flow in optical_flow.cpp).
#include "needle_guidance/registration/baselines.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <random>

#include "flow_mapping.h"

namespace needle_guidance::registration {
namespace detail {

FlowMapping::FlowMapping(cv::Mat flow_px, const Point2& origin_m, double pixel_m)
    : flow_(std::move(flow_px)), origin_(origin_m), pixel_m_(pixel_m) {}

std::optional<Point2> FlowMapping::displacement(const Point2& p_m) const {
  // Continuous pixel coordinates of p (pixel centres at integer + 0.5).
  const double col = (p_m.x() - origin_.x()) / pixel_m_ - 0.5;
  const double row = flow_.rows - 0.5 - (p_m.y() - origin_.y()) / pixel_m_;
  if (!std::isfinite(col) || !std::isfinite(row) || col < 0.0 || row < 0.0 ||
      col > flow_.cols - 1.0 || row > flow_.rows - 1.0) {
    return std::nullopt;
  }
  const int c0 = std::min(static_cast<int>(col), flow_.cols - 2),
            r0 = std::min(static_cast<int>(row), flow_.rows - 2);
  const double fc = col - c0, fr = row - r0;
  cv::Vec2d v(0.0, 0.0);
  for (int dr = 0; dr < 2; ++dr) {
    for (int dc = 0; dc < 2; ++dc) {
      const double w = (dr ? fr : 1.0 - fr) * (dc ? fc : 1.0 - fc);
      const cv::Vec2f f = flow_.at<cv::Vec2f>(r0 + dr, c0 + dc);
      v[0] += w * f[0];
      v[1] += w * f[1];
    }
  }
  return Point2(v[0] * pixel_m_, -v[1] * pixel_m_);
}

std::optional<Point2> FlowMapping::inverse(const Point2& probe_in_m) const {
  const auto v = displacement(probe_in_m);
  if (!v)
    return std::nullopt;
  return Point2(probe_in_m + *v);
}

std::optional<Point2> FlowMapping::forward(const Point2& probe_out_m) const {
  Point2 y = probe_out_m;
  for (int k = 0; k < 100; ++k) {
    const auto v = displacement(y);
    if (!v)
      return std::nullopt;
    const Point2 next = probe_out_m - *v;
    if ((next - y).norm() < 1e-7)
      return next;
    y = 0.5 * (y + next);  // damped fixed-point iteration
  }
  const auto v = displacement(y);
  if (v && (y + *v - probe_out_m).norm() < 5e-5)
    return y;
  return std::nullopt;
}

}  // namespace detail

namespace {

using Clock = std::chrono::steady_clock;

double secondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

Point2 areaCentroid(const Loops& loops) {
  double a2 = 0.0;
  Point2 c = Point2::Zero();
  for (const auto& loop : loops) {
    for (std::size_t i = 0; i < loop.size(); ++i) {
      const Point2& p = loop[i];
      const Point2& q = loop[(i + 1) % loop.size()];
      const double cross = p.x() * q.y() - q.x() * p.y();
      a2 += cross;
      c += (p + q) * cross;
    }
  }
  return a2 != 0.0 ? Point2(c / (3.0 * a2)) : Point2::Zero();
}

/// Densifies loops to at most max_edge_m between vertices (so that a nonlinear map of the
/// vertices follows the curve).
Loops densify(const Loops& loops, double max_edge_m) {
  Loops out;
  for (const auto& loop : loops) {
    std::vector<Point2> dense;
    for (std::size_t i = 0; i < loop.size(); ++i) {
      const Point2& p = loop[i];
      const Point2& q = loop[(i + 1) % loop.size()];
      const int pieces = std::max(1, static_cast<int>(std::ceil((q - p).norm() / max_edge_m)));
      for (int k = 0; k < pieces; ++k)
        dense.push_back(p + (q - p) * (static_cast<double>(k) / pieces));
    }
    out.push_back(std::move(dense));
  }
  return out;
}

double mappedDice(const PointMapping& mapping, const Loops& probe_out_prostate,
                  const Polygon& probe_in_prostate) {
  Loops mapped;
  for (const auto& loop : densify(probe_out_prostate, 0.0005)) {
    const auto m = mapPolygonForward(mapping, loop);
    if (!m)
      return 0.0;
    mapped.push_back(*m);
  }
  return diceSimilarity(mapped, toLoops(probe_in_prostate));
}

/// Smooth random texture field (sum of plane waves, wavelengths 3-12 mm) [grey levels].
struct Texture {
  explicit Texture(std::uint64_t seed) {
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> unit(0.0, 1.0);
    for (int k = 0; k < 24; ++k) {
      const double wavelength = 0.003 + 0.009 * unit(rng), angle = 2.0 * M_PI * unit(rng);
      waves.push_back({2.0 * M_PI / wavelength * std::cos(angle),
                       2.0 * M_PI / wavelength * std::sin(angle), 2.0 * M_PI * unit(rng)});
    }
  }
  double operator()(const Point2& p) const {
    double v = 0.0;
    for (const auto& w : waves)
      v += std::cos(w[0] * p.x() + w[1] * p.y() + w[2]);
    return 0.06 * v / std::sqrt(0.5 * static_cast<double>(waves.size()));
  }
  std::vector<std::array<double, 3>> waves;
};

/// T2-like grey level of the probe-out anatomy at p (nullopt outside the field of view).
std::optional<double> anatomyGrey(const SliceSegmentation& seg, const Point2& p) {
  if (!seg.domain.contains(p))
    return std::nullopt;
  if (seg.rectum.outer.contains(p))
    return 0.08;  // lumen
  if (seg.pz.outer.contains(p))
    return 0.78;  // PZ bright on T2
  if (seg.cg.outer.contains(p))
    return 0.52;
  if (seg.bladder && seg.bladder->outer.contains(p))
    return 0.95;
  for (const Outline& bone : seg.bones) {
    if (bone.outer.contains(p))
      return 0.2;
  }
  return 0.38;  // muscle / fat mixture
}

/// Thirion's demons (symmetric gradient), multi-resolution, Gaussian regularisation:
/// returns v (CV_32FC2, pixels) with fixed(x) ~ moving(x + v(x)).
cv::Mat demons(const cv::Mat& fixed, const cv::Mat& moving) {
  constexpr int kLevels = 4, kIterations = 80;
  constexpr double kSmoothSigmaPx = 1.5, kUpdateSigmaPx = 1.0, kMaxStepPx = 0.5;
  std::vector<cv::Mat> fixed_pyr{fixed}, moving_pyr{moving};
  for (int l = 1; l < kLevels; ++l) {
    cv::Mat f, m;
    cv::pyrDown(fixed_pyr.back(), f);
    cv::pyrDown(moving_pyr.back(), m);
    fixed_pyr.push_back(f);
    moving_pyr.push_back(m);
  }
  cv::Mat vx, vy;
  for (int l = kLevels - 1; l >= 0; --l) {
    const cv::Mat& f = fixed_pyr[static_cast<std::size_t>(l)];
    const cv::Mat& m = moving_pyr[static_cast<std::size_t>(l)];
    if (vx.empty()) {
      vx = cv::Mat::zeros(f.size(), CV_32F);
      vy = cv::Mat::zeros(f.size(), CV_32F);
    } else {
      cv::resize(vx, vx, f.size(), 0, 0, cv::INTER_LINEAR);
      cv::resize(vy, vy, f.size(), 0, 0, cv::INTER_LINEAR);
      vx *= 2.0;
      vy *= 2.0;
    }
    cv::Mat fgx, fgy;
    cv::Sobel(f, fgx, CV_32F, 1, 0, 3, 0.125);
    cv::Sobel(f, fgy, CV_32F, 0, 1, 3, 0.125);
    cv::Mat map_x(f.size(), CV_32F), map_y(f.size(), CV_32F), warped, wgx, wgy;
    for (int it = 0; it < kIterations; ++it) {
      for (int r = 0; r < f.rows; ++r) {
        for (int c = 0; c < f.cols; ++c) {
          map_x.at<float>(r, c) = static_cast<float>(c) + vx.at<float>(r, c);
          map_y.at<float>(r, c) = static_cast<float>(r) + vy.at<float>(r, c);
        }
      }
      cv::remap(m, warped, map_x, map_y, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
      cv::Sobel(warped, wgx, CV_32F, 1, 0, 3, 0.125);
      cv::Sobel(warped, wgy, CV_32F, 0, 1, 3, 0.125);
      cv::Mat ux(f.size(), CV_32F), uy(f.size(), CV_32F);
      for (int r = 0; r < f.rows; ++r) {
        for (int c = 0; c < f.cols; ++c) {
          const float diff = f.at<float>(r, c) - warped.at<float>(r, c);
          const float gx = 0.5f * (fgx.at<float>(r, c) + wgx.at<float>(r, c));
          const float gy = 0.5f * (fgy.at<float>(r, c) + wgy.at<float>(r, c));
          const float denom = gx * gx + gy * gy + diff * diff;
          float sx = 0.0f, sy = 0.0f;
          if (denom > 1e-9f) {
            // fixed(x) = moving(x + v + du) ~ warped + grad . du  =>  du = diff grad / |grad|^2
            sx = diff * gx / denom;
            sy = diff * gy / denom;
          }
          const float norm = std::sqrt(sx * sx + sy * sy);
          if (norm > kMaxStepPx) {
            sx *= static_cast<float>(kMaxStepPx) / norm;
            sy *= static_cast<float>(kMaxStepPx) / norm;
          }
          ux.at<float>(r, c) = sx;
          uy.at<float>(r, c) = sy;
        }
      }
      cv::GaussianBlur(ux, ux, cv::Size(0, 0), kUpdateSigmaPx);
      cv::GaussianBlur(uy, uy, cv::Size(0, 0), kUpdateSigmaPx);
      vx += ux;
      vy += uy;
      cv::GaussianBlur(vx, vx, cv::Size(0, 0), kSmoothSigmaPx);
      cv::GaussianBlur(vy, vy, cv::Size(0, 0), kSmoothSigmaPx);
    }
  }
  cv::Mat flow;
  cv::merge(std::vector<cv::Mat>{vx, vy}, flow);
  return flow;
}

}  // namespace

BaselineResult rigidCentreOfMass(const SliceSegmentation& probe_out,
                                 const ProbeInSegmentation& probe_in) {
  const Clock::time_point start = Clock::now();
  BaselineResult result;
  const SegmentationCheck check = checkSegmentation(probe_out, probe_in);
  if (!check.ok) {
    result.status = RegistrationStatus::kInvalidSegmentation;
    result.message = check.problem;
    result.seconds = secondsSince(start);
    return result;
  }
  const Loops out = prostateLoops(probe_out);
  const Loops in = toLoops(probe_in.prostate.outer);
  const auto mapping = std::make_shared<TranslationMapping>(areaCentroid(in) - areaCentroid(out));
  result.mapping = mapping;
  result.dice = mappedDice(*mapping, out, probe_in.prostate.outer);
  result.status = RegistrationStatus::kConverged;
  result.message = "centre-of-mass translation";
  result.seconds = secondsSince(start);
  return result;
}

const char* toString(IntensityMethod method) {
  switch (method) {
    case IntensityMethod::kDemons:
      return "demons";
    case IntensityMethod::kDisOpticalFlow:
      return "dis-flow";
    case IntensityMethod::kFarneback:
      return "farneback";
  }
  return "unknown";
}

SyntheticImagePair renderProbeImages(const ProbeCase& probe_case, double pixel_m, double noise_sd,
                                     std::uint64_t seed, TextureMode texture_mode) {
  SyntheticImagePair images;
  images.pixel_m = pixel_m;
  const SliceSegmentation& seg = probe_case.probe_out;
  images.origin = seg.domain.minCorner();
  const Point2 extent = seg.domain.maxCorner() - images.origin;
  const int cols = static_cast<int>(std::ceil(extent.x() / pixel_m));
  const int rows = static_cast<int>(std::ceil(extent.y() / pixel_m));
  images.probe_out = cv::Mat(rows, cols, CV_32F);
  images.probe_in = cv::Mat(rows, cols, CV_32F);
  const Texture texture(seed * 7919 + 1), texture_in(seed * 7919 + 2);
  const bool tracking = texture_mode == TextureMode::kTissueTracking;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> noise(0.0, noise_sd);
  const PointMapping* truth = probe_case.truth.mapping.get();
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < cols; ++c) {
      const Point2 p = images.origin + pixel_m * Point2(c + 0.5, rows - r - 0.5);
      const auto grey_out = anatomyGrey(seg, p);
      images.probe_out.at<float>(r, c) =
          static_cast<float>((grey_out ? *grey_out + texture(p) : 0.0) + noise(rng));
      double grey_in = 0.0;
      if (const auto x = truth ? truth->inverse(p) : std::nullopt) {
        const auto g = anatomyGrey(seg, *x);
        grey_in = g ? *g + (tracking ? texture(*x) : texture_in(p)) : 0.0;
      } else if (probe_case.truth.probe_outline.size() >= 3 &&
                 probe_case.truth.probe_outline.contains(p)) {
        grey_in = 0.05;  // probe
      } else if (probe_case.truth.probe_in_bladder.size() >= 3 &&
                 probe_case.truth.probe_in_bladder.contains(p)) {
        grey_in = 0.95 + (tracking ? 0.0 : texture_in(p));  // bladder cavity (not meshed)
      }
      images.probe_in.at<float>(r, c) = static_cast<float>(grey_in + noise(rng));
    }
  }
  return images;
}

BaselineResult intensityRegistration(const SyntheticImagePair& images,
                                     const Loops& probe_out_prostate,
                                     const Polygon& probe_in_prostate, IntensityMethod method) {
  const Clock::time_point start = Clock::now();
  BaselineResult result;
  if (!intensityMethodAvailable(method)) {
    result.status = RegistrationStatus::kUnavailable;
    result.message =
        std::string(toString(method)) + " needs opencv_video (build with NG_HAVE_OPENCV_VIDEO)";
    return result;
  }
  if (images.probe_in.empty() || images.probe_in.size() != images.probe_out.size() ||
      images.probe_in.type() != CV_32F || images.probe_out.type() != CV_32F ||
      !(images.pixel_m > 0.0)) {
    result.status = RegistrationStatus::kInvalidSegmentation;
    result.message = "images must be non-empty CV_32F of equal size with a positive pixel size";
    return result;
  }
  cv::Mat flow;
  if (method == IntensityMethod::kDemons) {
    flow = demons(images.probe_in, images.probe_out);
  } else {
    cv::Mat in8, out8;
    images.probe_in.convertTo(in8, CV_8U, 255.0);
    images.probe_out.convertTo(out8, CV_8U, 255.0);
    if (!detail::opticalFlow(in8, out8, method, flow)) {
      result.status = RegistrationStatus::kUnavailable;
      result.message = "optical flow not compiled in";
      return result;
    }
  }
  const auto mapping = std::make_shared<detail::FlowMapping>(flow, images.origin, images.pixel_m);
  result.mapping = mapping;
  result.seconds = secondsSince(start);
  result.dice = mappedDice(*mapping, probe_out_prostate, probe_in_prostate);
  result.status = RegistrationStatus::kConverged;
  result.message = toString(method);
  return result;
}

}  // namespace needle_guidance::registration
