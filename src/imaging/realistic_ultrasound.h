// The imager's realistic ultrasound model (UltrasoundModel::kRealistic, frame_renderer.h):
// the static echo amplitudes of the scene and the per-frame needle, combined and
// log-compressed. Internal to src/imaging (FrameRenderer calls it).
#pragma once

#include <opencv2/core.hpp>
#include <vector>

#include "needle_guidance/imaging/frame_renderer.h"

namespace needle_guidance::imaging::realistic {

/// The static part of the scene, made once: `amplitude` (CV_32FC1, echo amplitude of the tissue
/// speckle and of the specular interfaces, 1 = full scale) and `attenuation` (CV_32FC1, gain of
/// depth attenuation and of the obstacles' shadows).
void anatomy(const scene::Scene& scene, const ImagerConfig& config, cv::Mat* amplitude,
             cv::Mat* attenuation);

/// One frame as displayed (CV_32FC1, fractions of full scale): the tissue under the needle's
/// shadow, plus the needle's echo and its reverberation tail, plus the frame's electronic noise
/// (config.noise_std times the mean tissue echo, seeded by (config.seed, index)), blurred by the
/// configured point-spread function and log-compressed.
cv::Mat frame(const cv::Mat& amplitude, const cv::Mat& attenuation, const ImagerConfig& config,
              const std::vector<Point2>& needle_points, std::uint64_t index);

}  // namespace needle_guidance::imaging::realistic
