// OpenCV dense optical flow baselines (cv::DISOpticalFlow, cv::calcOpticalFlowFarneback). They
// live in libopencv_video, which the core links only when CMake defines NG_HAVE_OPENCV_VIDEO
// (find_package(OpenCV ... video) and target_compile_definitions(needle_guidance_core PRIVATE
// NG_HAVE_OPENCV_VIDEO)); without it the methods report RegistrationStatus::kUnavailable.
#include "flow_mapping.h"

#ifdef NG_HAVE_OPENCV_VIDEO
#include <opencv2/video/tracking.hpp>
#endif

namespace needle_guidance::registration::detail {

bool opticalFlow(const cv::Mat& probe_in_u8, const cv::Mat& probe_out_u8, IntensityMethod method,
                 cv::Mat& flow) {
#ifdef NG_HAVE_OPENCV_VIDEO
  if (method == IntensityMethod::kDisOpticalFlow) {
    cv::Ptr<cv::DISOpticalFlow> dis = cv::DISOpticalFlow::create(cv::DISOpticalFlow::PRESET_MEDIUM);
    dis->calc(probe_in_u8, probe_out_u8, flow);
    return true;
  }
  if (method == IntensityMethod::kFarneback) {
    cv::calcOpticalFlowFarneback(probe_in_u8, probe_out_u8, flow, 0.5, 5, 21, 10, 7, 1.5, 0);
    return true;
  }
  return false;
#else
  (void)probe_in_u8;
  (void)probe_out_u8;
  (void)method;
  (void)flow;
  return false;
#endif
}

}  // namespace needle_guidance::registration::detail

namespace needle_guidance::registration {

bool intensityMethodAvailable(IntensityMethod method) {
#ifdef NG_HAVE_OPENCV_VIDEO
  (void)method;
  return true;
#else
  return method == IntensityMethod::kDemons;
#endif
}

}  // namespace needle_guidance::registration
