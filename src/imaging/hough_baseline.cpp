// Baseline needle-tip detector (tip_tracker.h, houghBaselineTip): the classical straight-line
// pipeline — Gaussian blur, Canny with thresholds from the window's own gradient statistics,
// probabilistic Hough transform — in the same search window and with the same prior checks as
// detectTip, so that the comparison measures the arc model and the tip profile, not the window.
// Canny marks both flanks of the needle; when the longest segment has a parallel partner one
// needle width away, the two are averaged to the centre line (a plain Hough pipeline would
// report a flank, half a needle off).
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "detection_util.h"
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/math.h"

namespace needle_guidance::imaging {
namespace {

using detail::fail;
using detail::wrapAngle;

constexpr double kDeg = kPi / 180.0;
/// Blur before Canny: half the needle's diameter, at least this [px].
constexpr double kMinBlur_px = 1.0;
/// Canny's high threshold is this quantile of the window's Sobel gradient magnitude; the low
/// one kCannyLowRatio of it.
constexpr double kCannyHighQuantile = 0.95;
constexpr double kCannyLowRatio = 0.5;
/// Hough: 1 px, 1 degree; a segment needs votes and length of kMinSegment_m, gaps up to
/// kMaxSegmentGap_m are bridged.
constexpr double kMinSegment_m = 2.0e-3;
constexpr double kMaxSegmentGap_m = 0.6e-3;
/// A partner flank is parallel within this angle and at most this many diameters away.
constexpr double kPartnerAngle_rad = 5.0 * kDeg;
constexpr double kPartnerDistanceDiameters = 1.8;
/// Same prior slack as detectTip's.
constexpr double kPriorHeadingSlack_rad = 30.0 * kDeg;
/// Covariance: position std of a segment end [px] and heading std floor [rad].
constexpr double kEndpointStd_px = 2.0;
constexpr double kHeadingStdFloor_rad = 1.0 * kDeg;

}  // namespace

namespace {

Detection houghUnguarded(const cv::Mat& frame, const TrackerConfig& config,
                         const std::optional<SearchPrior>& prior) {
  const ImageGeometry& g = config.geometry;
  if (!(std::isfinite(g.pixel_size_m) && g.pixel_size_m > 0.0 && g.rows > 0 && g.cols > 0)) {
    return fail("invalid tracker configuration (pixel grid)");
  }
  const std::string problem = frameProblem(frame, g);
  if (!problem.empty()) {
    return fail(problem);
  }
  const double ps = g.pixel_size_m;
  const cv::Rect window = searchWindow(config, prior);
  if (window.width < 8 || window.height < 8) {
    return fail("search window outside the frame or too small");
  }
  const double diameter_px = config.needle_diameter_m / ps;
  const double blur_px = std::max(kMinBlur_px, 0.5 * diameter_px);
  cv::Mat blurred;
  cv::GaussianBlur(frame(window), blurred, cv::Size(0, 0), blur_px, blur_px, cv::BORDER_REPLICATE);
  cv::Mat gx, gy, mag;
  cv::Sobel(blurred, gx, CV_32F, 1, 0, 3);
  cv::Sobel(blurred, gy, CV_32F, 0, 1, 3);
  cv::magnitude(gx, gy, mag);
  std::vector<float> m(mag.begin<float>(), mag.end<float>());
  const auto k = static_cast<std::size_t>(kCannyHighQuantile * static_cast<double>(m.size() - 1));
  std::nth_element(m.begin(), m.begin() + static_cast<std::ptrdiff_t>(k), m.end());
  const double high = std::max(static_cast<double>(m[k]), 1.0);
  cv::Mat edges;
  cv::Canny(blurred, edges, kCannyLowRatio * high, high, 3, true);
  std::vector<cv::Vec4i> lines;
  const int min_len_px = std::max(5, static_cast<int>(std::lround(kMinSegment_m / ps)));
  cv::HoughLinesP(edges, lines, 1.0, kDeg, min_len_px, min_len_px,
                  std::max(1.0, kMaxSegmentGap_m / ps));
  if (lines.empty()) {
    return fail("Hough found no segment");
  }
  // Orientation reference: the prior heading, else +x. Segments in q axes (x right, y up).
  const double ref_theta = prior ? prior->tip.theta_rad : 0.0;
  const Eigen::Vector2d ref(std::cos(ref_theta), std::sin(ref_theta));
  double heading_limit = kPi;
  if (prior) {
    heading_limit = std::min(
        kPi, 3.0 * std::sqrt(std::max(0.0, prior->covariance(2, 2))) + kPriorHeadingSlack_rad);
  }
  struct Seg {
    Eigen::Vector2d a, b;  // oriented along the reference direction, q axes [px]
    double length = 0.0;
  };
  std::vector<Seg> segs;
  for (const auto& l : lines) {
    Seg s;
    s.a = Eigen::Vector2d(l[0] + window.x, -(l[1] + window.y));
    s.b = Eigen::Vector2d(l[2] + window.x, -(l[3] + window.y));
    if ((s.b - s.a).dot(ref) < 0.0) {
      std::swap(s.a, s.b);
    }
    s.length = (s.b - s.a).norm();
    const Eigen::Vector2d d = (s.b - s.a) / std::max(s.length, 1e-9);
    if (std::abs(wrapAngle(std::atan2(d.y(), d.x()) - ref_theta)) > heading_limit) {
      continue;
    }
    segs.push_back(s);
  }
  if (segs.empty()) {
    return fail("no Hough segment consistent with the prior heading");
  }
  const auto longest = std::max_element(
      segs.begin(), segs.end(), [](const Seg& x, const Seg& y) { return x.length < y.length; });
  Seg best = *longest;
  const Eigen::Vector2d dir = (best.b - best.a).normalized();
  const Eigen::Vector2d nrm(-dir.y(), dir.x());
  // Parallel partner (the other flank): shift the segment to the midline.
  double best_partner = -1.0;
  double shift = 0.0;
  for (const auto& s : segs) {
    if (&s == &*longest) {
      continue;
    }
    const Eigen::Vector2d d = (s.b - s.a).normalized();
    if (std::abs(std::asin(std::clamp(d.x() * dir.y() - d.y() * dir.x(), -1.0, 1.0))) >
        kPartnerAngle_rad) {
      continue;
    }
    const double off = nrm.dot(0.5 * (s.a + s.b) - best.a);
    if (std::abs(off) < 0.5 || std::abs(off) > kPartnerDistanceDiameters * diameter_px) {
      continue;
    }
    if (s.length > best_partner) {
      best_partner = s.length;
      shift = 0.5 * off;
    }
  }
  best.a += shift * nrm;
  best.b += shift * nrm;
  const double theta = std::atan2(dir.y(), dir.x());
  Detection d;
  d.found = true;
  d.p_SceneTip = g.toScene(cv::Point2d(best.b.x(), -best.b.y()));
  d.theta_rad = theta;
  const double heading_std =
      std::max(kHeadingStdFloor_rad, std::atan(2.0 / std::max(best.length, 1.0)));
  d.covariance = Eigen::Matrix3d::Zero();
  d.covariance(0, 0) = d.covariance(1, 1) = kEndpointStd_px * kEndpointStd_px * ps * ps;
  d.covariance(2, 2) = heading_std * heading_std;
  d.inliers = static_cast<int>(std::lround(best.length));
  d.residual_rms_m = 0.0;
  std::ostringstream msg;
  msg << "Hough: " << lines.size() << " segments, longest " << best.length * ps * 1e3 << " mm"
      << (best_partner > 0.0 ? ", centred between its two flanks" : "");
  d.message = msg.str();
  if (!d.p_SceneTip.allFinite() || !std::isfinite(d.theta_rad)) {
    return fail("non-finite Hough result");
  }
  return d;
}

}  // namespace

Detection houghBaselineTip(const cv::Mat& frame, const TrackerConfig& config,
                           const std::optional<SearchPrior>& prior) {
  try {
    return houghUnguarded(frame, config, prior);
  } catch (const std::exception& e) {
    return fail(std::string("Hough baseline failed: ") + e.what());
  }
}

}  // namespace needle_guidance::imaging
