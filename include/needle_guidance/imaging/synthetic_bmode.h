// Synthetic B-mode frames with the structures that fail a naive needle detector:
// speckle from a random scatterer field convolved with an anisotropic point-spread function,
// a specular interface between media of different echogenicity (longer and brighter than the
// needle, spanning the frame), and a needle with an acoustic shadow beneath, two reverberation
// copies deeper, and optionally a tip fading out of the image plane. Used by the acquisition
// tests and by bench_tracking_real when the recorded set is absent. Plain C++ and OpenCV.
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>
#include <optional>

namespace needle_guidance::imaging {

struct BModeNeedle {
  cv::Point2d tail, tip;       ///< visible ends [px]
  double brightness = 170.0;   ///< grey levels added on the shaft
  double fade_fraction = 0.0;  ///< last part of the shaft fading linearly to 0 (out of plane)
  /// 0: straight; otherwise the arc from tail to tip of radius 1 / |curvature| that turns
  /// clockwise on the screen (image y down) for > 0 (a steerable needle) [1/px]; |curvature|
  /// times the tail-tip distance must be below 2.
  double curvature_per_px = 0.0;
  /// Point at arc length s [px] from the tail, and the arc's length [px].
  cv::Point2d at(double s) const;
  double length() const;
  /// Direction towards the tip at the tip, atan2(drow, dcol) [rad].
  double tipAngle() const;
};
struct BModeInterface {
  double y0 = 0.0, y1 = 0.0;  ///< rows at the first and the last column
  double brightness = 230.0;  ///< of the specular line (brighter than the needle)
  double below_gain = 0.4;    ///< echogenicity below it relative to above
};

/// One CV_8UC1 frame of `size`; the same arguments give the same frame bit for bit.
cv::Mat syntheticBMode(cv::Size size, std::uint64_t seed,
                       const std::optional<BModeInterface>& interface_line,
                       const std::optional<BModeNeedle>& needle);

}  // namespace needle_guidance::imaging
