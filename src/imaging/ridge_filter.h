// The Hessian ridge filter shared by the tip detector (tip_detector.cpp) and the acquisition
// without a prior (needle_acquisition.cpp), private to src/imaging. A needle in a B-mode or
// fluoroscopy frame is a thin bright line once its polarity is made bright: across it the
// smoothed image's second derivative is strongly negative, along it nearly zero (Frangi et al.,
// MICCAI 1998, with the blob term as a penalty instead of a ratio).
#pragma once

#include <opencv2/core.hpp>

namespace needle_guidance::imaging::detail {

/// The Hessian of an image smoothed at a scale, its eigenvalues and the bright-line strength.
/// Derivatives are true ones (per px^2), so the strength does not depend on the kernel's gain.
struct HessianRidge {
  cv::Mat smooth;         ///< CV_32F, the image smoothed at sigma
  cv::Mat half_diff;      ///< CV_32F, (Ixx - Iyy) / 2
  cv::Mat dxy;            ///< CV_32F, Ixy
  cv::Mat lambda_across;  ///< CV_32F, the smaller eigenvalue (most negative across a bright line)
  cv::Mat lambda_along;   ///< CV_32F, the larger eigenvalue (near 0 along a line)
  cv::Mat strength;       ///< CV_32F, max(0, -lambda_across - blob_penalty |lambda_along|)

  /// The line's direction at pixel (x, y), in [-pi/2, pi/2] [rad]: the larger eigenvalue's
  /// eigenvector (along a bright line).
  double direction(int x, int y) const;
};

/// Gaussian smoothing at sigma_px (> 0) [px], 3 x 3 Sobel second derivatives, eigenvalues from
/// cv::magnitude. `border` (cv::BorderTypes) is used by both the smoothing and the derivatives.
/// A blob (both eigenvalues negative) scores less than a line by blob_penalty |lambda_along|.
HessianRidge hessianRidge(const cv::Mat& image32f, double sigma_px, double blob_penalty,
                          int border);

}  // namespace needle_guidance::imaging::detail
