// The imager's realistic ultrasound model (UltrasoundModel::kRealistic, frame_renderer.h):
// the static echo amplitudes of the scene and the per-frame needle, combined and
// log-compressed. Internal to src/imaging (FrameRenderer calls it).
#pragma once

#include <opencv2/core.hpp>
#include <vector>

#include "needle_guidance/imaging/frame_renderer.h"

namespace needle_guidance::imaging::realistic {

/// Display: 20 log10(amplitude) over this dynamic range maps to 0..1 (clinical B-mode shows
/// 50-60 dB).
constexpr double kDynamicRange_dB = 55.0;
/// Mean speckle amplitude of the background tissue (echogenicity kTissueEcho): about 30 dB
/// below the needle's specular echo, mid-grey on the display.
constexpr double kTissueAmplitude = 0.03;
constexpr double kTissueEcho = 0.25;  // the echogenicity that kTissueAmplitude stands for
/// Needle: specular amplitude facing the beam and parallel to it (|cos|^2 between).
constexpr double kNeedleFacing = 1.0;
constexpr double kNeedleParallel = 0.12;
/// Acoustic shadow beyond the shaft (metal reflects most of the beam).
constexpr double kNeedleShadowGain = 0.35;
/// Reverberation tail: copies kReverbSpacing_m apart along the beam, the first at kReverbFirst
/// of the shaft's echo, each next one kReverbDecay of the one before.
constexpr int kReverbCopies = 5;
constexpr double kReverbSpacing_m = 0.5e-3;
constexpr double kReverbFirst = 0.35;
constexpr double kReverbDecay = 0.5;
/// Depth attenuation left after time-gain compensation [1/m].
constexpr double kAttenuation_per_m = 6.0;

/// 20 log10(amplitude) over kDynamicRange_dB, to 0..1 of the display.
double logCompress(double amplitude);

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
