// The Hessian ridge filter shared by the two tip detectors; see ridge_filter.h.
#include "ridge_filter.h"

#include <cmath>
#include <opencv2/imgproc.hpp>
#include <stdexcept>

namespace needle_guidance::imaging::detail {

double HessianRidge::direction(int x, int y) const {
  return 0.5 * std::atan2(2.0 * dxy.at<float>(y, x), 2.0 * half_diff.at<float>(y, x));
}

HessianRidge hessianRidge(const cv::Mat& image32f, double sigma_px, double blob_penalty,
                          int border) {
  if (image32f.type() != CV_32FC1 || !(sigma_px > 0.0) || !(blob_penalty >= 0.0))
    throw std::invalid_argument(
        "hessianRidge: needs a CV_32FC1 image, sigma_px > 0 and "
        "blob_penalty >= 0");
  HessianRidge h;
  cv::GaussianBlur(image32f, h.smooth, cv::Size(), sigma_px, sigma_px, border);
  // 3 x 3 Sobel second derivatives carry a gain of 4 (the [1 2 1] smoothing across): 0.25
  // makes them true derivatives, exactly (a power of two).
  cv::Mat dxx, dyy;
  cv::Sobel(h.smooth, dxx, CV_32F, 2, 0, 3, 0.25, 0.0, border);
  cv::Sobel(h.smooth, dyy, CV_32F, 0, 2, 3, 0.25, 0.0, border);
  cv::Sobel(h.smooth, h.dxy, CV_32F, 1, 1, 3, 0.25, 0.0, border);
  const cv::Mat half_trace = 0.5F * (dxx + dyy);
  h.half_diff = 0.5F * (dxx - dyy);
  cv::Mat root;
  cv::magnitude(h.half_diff, h.dxy, root);
  h.lambda_across = half_trace - root;
  h.lambda_along = half_trace + root;
  h.strength =
      cv::max(-h.lambda_across - static_cast<float>(blob_penalty) * cv::abs(h.lambda_along), 0.0F);
  return h;
}

}  // namespace needle_guidance::imaging::detail
