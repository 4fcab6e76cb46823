// The realistic ultrasound model (frame_renderer.h, UltrasoundModel::kRealistic) on a convex
// (curvilinear) probe, as a scanner displays it: the probe at the top, its beams fanning out
// from the centre of the face's curvature. The frame is acquired the way the probe does, in its
// own grid of beams x depth samples, and scan-converted into the displayed frame:
//   - the scene (echogenicity, long specular tissue interfaces, the needle) is drawn in the
//     frame's pixels and sampled into the beam grid; a specular echo is strongest where the
//     structure faces the beam (|sin| of its angle to the beam, squared);
//   - speckle and the point-spread function live in the beam grid: a fixed angular width makes
//     the lateral resolution coarser with depth, as a convex probe's is;
//   - along each beam: the needle's acoustic shadow beyond it, its reverberation tail (copies
//     deeper along the beam), the probe face's ring-down (a bright band under the face), depth
//     attenuation after time-gain compensation, the electronic noise before log compression;
//   - scan conversion (bilinear, cv::remap) into the frame: black outside the sector.
// Used by bench tracking_real (synthetic convex sequences) and the tracking tests. Plain C++ and
// OpenCV; no ROS.
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>
#include <vector>

namespace needle_guidance::imaging {

/// The probe's sector in the displayed frame (pixels; the fan opens towards +rows).
struct ConvexProbe {
  cv::Point2d apex_px{360.0, -300.0};  ///< centre of the face's curvature (may lie above the frame)
  double face_radius_px = 330.0;       ///< radius of the probe face [px], > 0
  double half_angle_rad = 0.55;        ///< half the sector's angle, in (0, 1.4]
  double depth_px = 420.0;             ///< imaging depth below the face [px], > 0
  int beams = 160;                     ///< scan lines across the sector, >= 16
  double pixel_size_m = 0.15e-3;       ///< the display's pixel size [m], > 0
  /// Throws std::invalid_argument naming the field when out of range.
  void validate() const;
  /// Direction of the beam through frame pixel p (unit, away from the probe).
  cv::Point2d beamAt(cv::Point2d p) const;
  /// Whether frame pixel p lies inside the sector.
  bool inside(cv::Point2d p) const;
};

/// A long specular tissue interface (fascia, a muscle or organ boundary): a straight line from
/// `a` to `b` [frame px], brighter and wider than the needle, the tissue beyond it (deeper)
/// `gain_below` times as echogenic.
struct ConvexLayer {
  cv::Point2d a, b;
  double amplitude = 1.6;  ///< echo where it faces the beam (1 = the needle's, full scale)
  double width_px = 5.0;
  double gain_below = 0.7;
};

struct ConvexScene {
  ConvexProbe probe;
  std::vector<ConvexLayer> layers;
  double gain_db = 0.0;    ///< overall display gain [dB]
  double noise_std = 0.1;  ///< electronic noise, times the mean tissue echo, >= 0
  double needle_width_px =
      1.0;  ///< the wall facing the probe, drawn this wide (the axial PSF does the rest)
  /// The needle's elevation slope out of the image plane (its echo fades along the shaft).
  double elevation_slope = 0.0;
  /// Share of the speckle drawn afresh in each frame (0: still tissue, a fixed probe; towards 1:
  /// a hand-held probe or frames far apart in time).
  double decorrelation = 0.0;
  std::uint64_t seed = 1;
};

/// One displayed frame (CV_8UC1 of `size`): the scene with the needle `needle_px` (polyline
/// entry -> tip in frame pixels, finely spaced; fewer than 2 points: no needle), frame `index`
/// (seeds the noise and the fresh speckle). Deterministic. Throws std::invalid_argument for an
/// invalid probe or a non-finite needle point.
cv::Mat renderConvexFrame(const ConvexScene& scene, cv::Size size,
                          const std::vector<cv::Point2d>& needle_px, std::uint64_t index);

}  // namespace needle_guidance::imaging

namespace needle_guidance::imaging {

/// A scenario of the tracking benchmark and tests: a needle inserted in-plane from the probe's
/// end, imaged by a convex probe, frame by frame.
struct ConvexInsertion {
  std::uint64_t seed = 1;       ///< seeds the layers' layout, the speckle and the noise
  cv::Size size{720, 440};      ///< displayed frame [px]
  double face_radius_px = 330;  ///< probe (ConvexProbe), the apex centred over the frame
  double half_angle_rad = 0.55;
  double depth_px = 420;
  double apex_dx_px = 0.0;   ///< apex this far right of the frame's centre (a crop off-centre)
  double face_top_px = 8.0;  ///< row of the face's two ends (its middle lies lower)
  double pixel_size_m = 0.15e-3;
  /// Where the needle crosses the probe face: -1 the left end, +1 the right end (beyond 1 in
  /// magnitude: it enters through the sector's straight edge).
  double entry = -0.8;
  double angle_deg = 35.0;  ///< to the rows, pointing down into the sector, away from the end
  double start_px = 60.0;   ///< inserted length inside the sector at the needle's first frame
  double step_px = 8.0;     ///< advance per frame [px] (a sparse sequence: large steps)
  int frames = 15;
  int appear_at = 0;  ///< first frame with the needle (before: no needle); -1: never
  int layers = 2;     ///< long bright interfaces below the needle's deepest tip
  double layer_amplitude = 1.6;
  double gain_db = 0.0;
  double noise_std = 0.1;
  double decorrelation = 0.0;
  double elevation_slope = 0.0;
  double needle_width_px = 1.0;
  /// The scene this describes (probe, seeded layers), for renderConvexFrame.
  ConvexScene scene() const;
  /// The needle's polyline at frame k (empty before it appears), and its true tip and angle
  /// (atan2(row step, column step) towards the tip).
  std::vector<cv::Point2d> needleAt(int k, cv::Point2d* tip, double* angle_rad) const;
  /// Length of the needle inside the sector at frame k [px] (0 before it appears): a needle
  /// with less than a few tens of pixels in view is not yet a needle to find.
  double visibleLength(int k) const;
};

}  // namespace needle_guidance::imaging
