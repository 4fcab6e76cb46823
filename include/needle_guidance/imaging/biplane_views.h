// Biplane fluoroscopy of the 3-D steerable needle: two orthogonal views of a
// steering_3d scene, one along z (it sees x, y) and one along y (it sees x, z), rendered with the
// imager's FrameRenderer in fluoroscopy mode over the tissue's bounds, the tip found in each with
// the tracker's single-frame detector (detectTip, no prior) and the two detections triangulated
// with needle_model::triangulateBiplane: views whose shared x disagrees beyond the gate are
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
#include "needle_guidance/needle_model/biplane_3d.h"
#include "needle_guidance/needle_model/scene_3d.h"

namespace needle_guidance::imaging {

/// The two devices (the same settings for both).
struct BiplaneViewsConfig {
  double pixel_size_m = 2e-4;     ///< > 0 [m]
  double noise_std = 0.05;        ///< fraction of full scale, >= 0
  double blur_sigma_m = 2e-4;     ///< >= 0 [m]
  double drop_probability = 0.0;  ///< per frame and view, in [0, 1)
  double margin_m = 5e-3;         ///< field of view: the tissue's bounds plus this, >= 0 [m]
  double min_sigma_m = 1e-4;      ///< floor of a detection's position std [m], > 0
  double gate = needle_model::kBiplaneGateChiSquare;  ///< chi-square gate (1 dof), > 0
  std::uint64_t seed = 1;  ///< the views' noise and drops (view along y: seed + 1)
  /// Throws std::invalid_argument naming the first value out of range.
  void validate() const;
};

/// One view of one instant.
struct BiplaneView3 {
  needle_model::ViewAxis axis = needle_model::ViewAxis::kAlongZ;
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
  Result<needle_model::TipPose3, needle_model::BiplaneStatus> tip =
      needle_model::BiplaneStatus(needle_model::BiplaneCode::kNoDetection, "not observed");
  /// The fused position's covariance [m^2] (zero unless `tip` holds a value).
  needle_model::Matrix3 covariance_m2 = needle_model::Matrix3::Zero();
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
std::optional<needle_model::ViewAxis> viewAxis(ImagerView view);

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
BiplaneViewSetup biplaneViewSetup(const needle_model::Scene3d& scene,
                                  const BiplaneViewsConfig& config, needle_model::ViewAxis axis);

/// The tip from two received frames: detected in each (detectTip, no prior) and triangulated
/// (the gate refuses views that disagree). No rendering: the frames come from elsewhere (two
/// imager nodes, or BiplaneViews3's renderers).
class BiplaneFusion3 {
public:
  /// Throws std::invalid_argument for a bad config.
  BiplaneFusion3(const needle_model::Scene3d& scene, const BiplaneViewsConfig& config);
  /// Detects the tip in the frame along z and the frame along y (a dropped or empty frame finds
  /// none) and fuses them; `predicted` gives the bevel. Throws std::invalid_argument naming the
  /// view when a frame's size is not its view's (another pixel size or scene).
  BiplaneObservation3 observeFrames(const Frame& along_z, const Frame& along_y,
                                    const needle_model::TipPose3& predicted) const;
  const ImageGeometry& geometry(needle_model::ViewAxis axis) const;

private:
  BiplaneView3 detect(needle_model::ViewAxis axis, const Frame& frame) const;

  BiplaneViewsConfig config_;
  std::vector<TrackerConfig> trackers_;  ///< along z, along y
};

/// Both views rendered in process (the ROS-free procedure, bench and tests), then fused.
class BiplaneViews3 {
public:
  /// Throws std::invalid_argument for a bad config.
  BiplaneViews3(const needle_model::Scene3d& scene, const BiplaneViewsConfig& config);
  /// Renders frame `index` of both views of the needle `needle` (entry -> tip, frame scene [m]),
  /// detects the tip in each and fuses them; `predicted` gives the bevel.
  BiplaneObservation3 observe(const std::vector<needle_model::Vector3>& needle,
                              const needle_model::TipPose3& predicted, std::uint64_t index) const;
  const ImageGeometry& geometry(needle_model::ViewAxis axis) const {
    return fusion_.geometry(axis);
  }

private:
  BiplaneFusion3 fusion_;
  std::vector<FrameRenderer> renderers_;  ///< along z, along y
};

}  // namespace needle_guidance::imaging
