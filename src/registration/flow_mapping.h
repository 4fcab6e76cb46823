// Private to the registration module: a point mapping from a dense displacement field on the
// probe-in pixel grid (intensity baselines), and the optical-flow entry points that need
// opencv_video (compiled only with NG_HAVE_OPENCV_VIDEO, see optical_flow.cpp).
#pragma once

#include <opencv2/core.hpp>
#include <optional>

#include "needle_guidance/registration/baselines.h"

namespace needle_guidance::registration::detail {

/// v (CV_32FC2, pixels: (dcol, drow)) on the probe-in grid with probe_in(y) ~ probe_out(y + v(y)).
class FlowMapping final : public PointMapping {
public:
  FlowMapping(cv::Mat flow_px, const Point2& origin_m, double pixel_m);
  /// T: fixed-point inversion y = x - v(y); nullopt if it leaves the image or does not converge.
  std::optional<Point2> forward(const Point2& probe_out_m) const override;
  /// T^-1(y) = y + v(y), bilinear; nullopt outside the image.
  std::optional<Point2> inverse(const Point2& probe_in_m) const override;

private:
  std::optional<Point2> displacement(const Point2& p_m) const;
  cv::Mat flow_;
  Point2 origin_;
  double pixel_m_;
};

/// Dense flow probe_in -> probe_out with OpenCV's video module; false when not compiled in.
bool opticalFlow(const cv::Mat& probe_in_u8, const cv::Mat& probe_out_u8, IntensityMethod method,
                 cv::Mat& flow);

}  // namespace needle_guidance::registration::detail
