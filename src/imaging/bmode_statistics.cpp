// B-mode frame statistics; see bmode_statistics.h.
#include "needle_guidance/imaging/bmode_statistics.h"

#include <algorithm>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <vector>

#include "needle_guidance/math.h"

namespace needle_guidance::imaging {
namespace {

constexpr int kTile_px = 32;
constexpr int kNeedleClearance_px = 10;
constexpr double kMinTissueGrey = 30.0, kMaxTissueGrey = 200.0, kDarkGrey = 10.0;
constexpr double kNeedleQuantile = 0.9, kOtherQuantile = 0.995;

/// Lag where the normalised autocorrelation along one axis first falls to 0.5 (interpolated).
double halfWidth(const cv::Mat& ac, bool along_x) {
  const int n = along_x ? ac.cols / 2 : ac.rows / 2;
  double prev = 1.0;
  for (int k = 1; k < n; ++k) {
    const double v = along_x ? ac.at<float>(0, k) : ac.at<float>(k, 0);
    if (v <= 0.5)
      return (k - 1) + (prev - 0.5) / std::max(prev - v, 1e-9);
    prev = v;
  }
  return n;
}

/// Normalised circular autocorrelation of a mean-free tile (Wiener-Khinchin).
cv::Mat autocorrelation(const cv::Mat& tile) {
  cv::Mat f;
  tile.convertTo(f, CV_32F);
  f -= cv::mean(f)[0];
  cv::Mat spectrum, power, ac;
  cv::dft(f, spectrum, cv::DFT_COMPLEX_OUTPUT);
  cv::mulSpectrums(spectrum, spectrum, power, 0, true);
  cv::dft(power, ac, cv::DFT_INVERSE | cv::DFT_REAL_OUTPUT | cv::DFT_SCALE);
  const float zero = ac.at<float>(0, 0);
  return zero > 0.0F ? cv::Mat(ac / zero) : ac;
}

}  // namespace

BModeStatistics bmodeStatistics(const cv::Mat& grey, const cv::Mat& needle_mask) {
  if (grey.empty() || grey.type() != CV_8UC1) {
    throw std::invalid_argument("bmodeStatistics: the frame must be CV_8UC1 and not empty");
  }
  if (!needle_mask.empty() &&
      (needle_mask.size() != grey.size() || needle_mask.type() != CV_8UC1)) {
    throw std::invalid_argument(
        "bmodeStatistics: the needle mask must be CV_8UC1 of the frame's size");
  }
  BModeStatistics s;
  cv::Mat near(grey.size(), CV_8U, cv::Scalar(0));
  if (!needle_mask.empty()) {
    cv::dilate(needle_mask > 0, near,
               cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * kNeedleClearance_px + 1,
                                                                     2 * kNeedleClearance_px + 1)));
  }
  std::vector<double> means, snrs, lateral, axial;
  for (int y = 0; y + kTile_px <= grey.rows; y += kTile_px) {
    for (int x = 0; x + kTile_px <= grey.cols; x += kTile_px) {
      const cv::Rect r(x, y, kTile_px, kTile_px);
      double lo = 0, hi = 0;
      cv::minMaxLoc(grey(r), &lo, &hi);
      cv::Scalar mean, sd;
      cv::meanStdDev(grey(r), mean, sd);
      if (cv::countNonZero(near(r)) > 0 || mean[0] < kMinTissueGrey || hi > kMaxTissueGrey ||
          sd[0] <= 0.0)
        continue;
      means.push_back(mean[0]);
      snrs.push_back(mean[0] / sd[0]);
      const cv::Mat ac = autocorrelation(grey(r));
      lateral.push_back(halfWidth(ac, true));
      axial.push_back(halfWidth(ac, false));
    }
  }
  s.tissue_patches = static_cast<int>(means.size());
  s.tissue_mean_grey = orderStatistic(means, 0.5);
  s.speckle_snr = orderStatistic(snrs, 0.5);
  s.speckle_lateral_px = orderStatistic(lateral, 0.5);
  s.speckle_axial_px = orderStatistic(axial, 0.5);
  std::vector<double> on, other;
  long dark = 0;
  for (int y = 0; y < grey.rows; ++y) {
    const std::uint8_t* g = grey.ptr<std::uint8_t>(y);
    const std::uint8_t* m = needle_mask.empty() ? nullptr : needle_mask.ptr<std::uint8_t>(y);
    const std::uint8_t* n = near.ptr<std::uint8_t>(y);
    for (int x = 0; x < grey.cols; ++x) {
      dark += g[x] < kDarkGrey ? 1 : 0;
      if (m && m[x])
        on.push_back(g[x]);
      else if (!n[x])
        other.push_back(g[x]);
    }
  }
  s.dark_fraction = static_cast<double>(dark) / static_cast<double>(grey.total());
  if (!on.empty()) {
    s.needle_grey = orderStatistic(on, kNeedleQuantile);
    s.needle_contrast = s.tissue_mean_grey > 0 ? s.needle_grey / s.tissue_mean_grey : 0.0;
    s.brightest_other_over_needle =
        orderStatistic(other, kOtherQuantile) / std::max(s.needle_grey, 1.0);
  }
  return s;
}

}  // namespace needle_guidance::imaging
