// The Hessian ridge filter of both needle detectors (tip_detector.cpp on rendered frames,
// needle_acquisition.cpp on recorded B-mode frames); private to src/imaging. A bright line
// about as wide as the smoothing has a strongly negative Hessian eigenvalue across it and a small
// one along it; a blob has two negative ones, an edge none of that sign.
#pragma once

#include <opencv2/core.hpp>

namespace needle_guidance::imaging::detail {

/// Settings of ridgeFilter.
struct RidgeFilter {
  double sigma_px = 1.0;      ///< Gaussian smoothing before the Hessian [px], > 0
  double blob_penalty = 1.0;  ///< strength = max(0, -l1 - blob_penalty |l2|), >= 0
  /// Factor on the 3x3 Sobel second derivatives (0.25 makes them per pixel^2).
  double derivative_scale = 1.0;
  int border = cv::BORDER_DEFAULT;  ///< how smoothing and derivatives extend the image
};

/// The filter's images, all CV_32F of the input's size.
struct RidgeResponse {
  cv::Mat smooth;         ///< the smoothed image
  cv::Mat dxx, dyy, dxy;  ///< its second derivatives (columns x, rows y)
  cv::Mat half_diff;      ///< (dxx - dyy) / 2: with dxy, the line direction
  cv::Mat l1, l2;         ///< Hessian eigenvalues, l1 <= l2 (l1 most negative across the line)
  cv::Mat strength;       ///< max(0, -l1 - blob_penalty |l2|): high on a bright line only
};

/// The ridge filter of `image` (CV_32F, the needle bright).
RidgeResponse ridgeFilter(const cv::Mat& image, const RidgeFilter& filter);

}  // namespace needle_guidance::imaging::detail
