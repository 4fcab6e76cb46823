// Biplane fluoroscopy of the 3-D steerable needle: two orthogonal views of a
// steering_3d scene, one along z (it sees x, y) and one along y (it sees x, z), rendered with the
// imager's FrameRenderer in fluoroscopy mode over the tissue's bounds, the tip found in each with
// the tracker's single-frame detector (detectTip, no prior) and the two detections triangulated
// with steering_3d::triangulateBiplane: views whose shared x disagrees beyond the gate are
// refused, never fused. biplaneViewSetup is each view's device (the imager node's ~view along_z
// / along_y renders with it), BiplaneFusion3 detects and fuses two received frames (the ROS
// procedure, fed by two imager nodes), BiplaneViews3 renders both in process and fuses them (the
// ROS-free trial and tests). Plain C++ and OpenCV; no ROS.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/steering_3d/biplane_3d.h"
#include "needle_guidance/steering_3d/scene_3d.h"

namespace needle_guidance::imaging {

/// The two devices (the same settings for both).
struct BiplaneViewsConfig {
  double pixel_size_m = 2e-4;     ///< > 0 [m]
  double noise_std = 0.05;        ///< fraction of full scale, >= 0
  double blur_sigma_m = 2e-4;     ///< >= 0 [m]
  double drop_probability = 0.0;  ///< per frame and view, in [0, 1)
  double margin_m = 5e-3;         ///< field of view: the tissue's bounds plus this, >= 0 [m]
  double min_sigma_m = 1e-4;      ///< floor of a detection's position std [m], > 0
  double gate = steering_3d::kBiplaneGateChiSquare;  ///< chi-square gate (1 dof), > 0
  std::uint64_t seed = 1;  ///< the views' noise and drops (view along y: seed + 1)
  /// Throws std::invalid_argument naming the first value out of range.
  void validate() const;
};

/// One view of one instant.
struct BiplaneView3 {
  steering_3d::ViewAxis axis = steering_3d::ViewAxis::kAlongZ;
  Frame frame;          ///< empty image when dropped
  Detection detection;  ///< in the view's plane coordinates ((x, y) or (x, z)) [m, rad]
};

/// Both views and their fusion.
struct BiplaneObservation3 {
  BiplaneView3 along_z;
  BiplaneView3 along_y;
  /// The fused tip: position triangulated, tangent from the two detected headings, bevel from
  /// the caller's prediction (the views do not see the bevel's roll). kNoDetection when a view
  /// found no tip, kDisagree when the gate refused the pair.
  Result<steering_3d::TipPose3, steering_3d::BiplaneStatus> tip =
      steering_3d::BiplaneStatus(steering_3d::BiplaneCode::kNoDetection, "not observed");
  /// The fused position's covariance [m^2] (zero unless `tip` holds a value).
  steering_3d::Matrix3 covariance_m2 = steering_3d::Matrix3::Zero();
};

/// What an imager node renders (its ~view).
enum class ImagerView {
  kPlane,   ///< the 2-D scene's plane (the planar procedures)
  kAlongZ,  ///< the 3-D scene seen along z (x, y)
  kAlongY,  ///< the 3-D scene seen along y (x, z)
};
/// "plane" | "along_z" | "along_y"; nullopt for anything else.
std::optional<ImagerView> imagerViewFromString(const std::string& name);
/// The axis a 3-D view looks along; nullopt for kPlane.
std::optional<steering_3d::ViewAxis> viewAxis(ImagerView view);

/// One view's device and detector: the view's plane as a 2-D scene over the tissue's projected
/// bounds plus the margin, the fluoroscopy imager over it (seeded config.seed, along y seed + 1)
/// and the tracker's single-frame detector for its frames. Shared by BiplaneViews3 and the
/// imager node's ~view along_z / along_y, so both render and read the same geometry.
struct BiplaneViewSetup {
  scene::Scene plane;
  ImagerConfig imager;
  TrackerConfig tracker;
};
/// Throws std::invalid_argument for a bad config.
BiplaneViewSetup biplaneViewSetup(const steering_3d::Scene3d& scene,
                                  const BiplaneViewsConfig& config, steering_3d::ViewAxis axis);

/// The tip from two received frames: detected in each (detectTip, no prior) and triangulated
/// (the gate refuses views that disagree). No rendering: the frames come from elsewhere (two
/// imager nodes, or BiplaneViews3's renderers).
class BiplaneFusion3 {
public:
  /// Throws std::invalid_argument for a bad config.
  BiplaneFusion3(const steering_3d::Scene3d& scene, const BiplaneViewsConfig& config);
  /// Detects the tip in the frame along z and the frame along y (a dropped or empty frame finds
  /// none) and fuses them; `predicted` gives the bevel. Throws std::invalid_argument naming the
  /// view when a frame's size is not its view's (another pixel size or scene).
  BiplaneObservation3 observeFrames(const Frame& along_z, const Frame& along_y,
                                    const steering_3d::TipPose3& predicted) const;
  const ImageGeometry& geometry(steering_3d::ViewAxis axis) const;

private:
  BiplaneView3 detect(steering_3d::ViewAxis axis, const Frame& frame) const;

  BiplaneViewsConfig config_;
  std::vector<TrackerConfig> trackers_;  ///< along z, along y
};

/// Both views rendered in process (the ROS-free procedure, bench and tests), then fused.
class BiplaneViews3 {
public:
  /// Throws std::invalid_argument for a bad config.
  BiplaneViews3(const steering_3d::Scene3d& scene, const BiplaneViewsConfig& config);
  /// Renders frame `index` of both views of the needle `needle` (entry -> tip, frame scene [m]),
  /// detects the tip in each and fuses them; `predicted` gives the bevel.
  BiplaneObservation3 observe(const std::vector<steering_3d::Vector3>& needle,
                              const steering_3d::TipPose3& predicted, std::uint64_t index) const;
  const ImageGeometry& geometry(steering_3d::ViewAxis axis) const { return fusion_.geometry(axis); }

private:
  BiplaneFusion3 fusion_;
  std::vector<FrameRenderer> renderers_;  ///< along z, along y
};

}  // namespace needle_guidance::imaging
