// The Hessian ridge filter of both needle detectors (ridge_filter.h).
#include "ridge_filter.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

namespace needle_guidance::imaging::detail {

RidgeResponse ridgeFilter(const cv::Mat& image, const RidgeFilter& filter) {
  RidgeResponse out;
  cv::GaussianBlur(image, out.smooth, cv::Size(0, 0), filter.sigma_px, filter.sigma_px,
                   filter.border);
  const double scale = filter.derivative_scale;
  cv::Sobel(out.smooth, out.dxx, CV_32F, 2, 0, 3, scale, 0.0, filter.border);
  cv::Sobel(out.smooth, out.dyy, CV_32F, 0, 2, 3, scale, 0.0, filter.border);
  cv::Sobel(out.smooth, out.dxy, CV_32F, 1, 1, 3, scale, 0.0, filter.border);
  const cv::Size size = out.smooth.size();
  out.half_diff.create(size, CV_32F);
  out.l1.create(size, CV_32F);
  out.l2.create(size, CV_32F);
  out.strength.create(size, CV_32F);
  const auto penalty = static_cast<float>(filter.blob_penalty);
  for (int r = 0; r < size.height; ++r) {
    const float* a = out.dxx.ptr<float>(r);
    const float* c = out.dyy.ptr<float>(r);
    const float* b = out.dxy.ptr<float>(r);
    float* hd = out.half_diff.ptr<float>(r);
    float* e1 = out.l1.ptr<float>(r);
    float* e2 = out.l2.ptr<float>(r);
    float* s = out.strength.ptr<float>(r);
    for (int k = 0; k < size.width; ++k) {
      const float half_tr = 0.5f * (a[k] + c[k]);
      hd[k] = 0.5f * (a[k] - c[k]);
      const float root = std::sqrt(hd[k] * hd[k] + b[k] * b[k]);
      e1[k] = half_tr - root;
      e2[k] = half_tr + root;
      s[k] = std::max(0.0f, -e1[k] - penalty * std::abs(e2[k]));
    }
  }
  return out;
}

}  // namespace needle_guidance::imaging::detail
