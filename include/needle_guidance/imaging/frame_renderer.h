// Simulated imaging device: frames of the scene plane rendered from the
// true needle shape, in a fluoroscopy-like and an ultrasound-like mode, with the device's pixel
// grid, noise, blur and dropped frames. The steering controller of dissertation 5.5 assumes the
// tip is localised in such an image after every insertion step (figure 5.8). Plain C++ and
// OpenCV; no ROS.
#pragma once

#include <cstdint>
#include <memory>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/imaging/convex_ultrasound.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue/image_warp.h"

namespace needle_guidance::imaging {

using geometry::Point2;
/// Pixel <-> scene calibration of a frame: top-left corner, square pixel size, rows x cols.
using tissue::ImageGeometry;

enum class Modality : std::uint8_t {
  /// Projection image as displayed: bright where little is absorbed; bone (the scene's rigid
  /// regions and obstacles) darker; the metal needle a thin, dark, high-contrast curve.
  kFluoroscopy,
  /// B-mode-like image from a linear probe on the workspace's lower face (y = min, beam along
  /// +y): speckle, depth attenuation, bright tissue boundaries with acoustic shadows behind
  /// obstacles, a needle that is bright where it faces the beam and faint where it does not, and
  /// reverberation echoes behind it. Bright is echogenic.
  kUltrasound,
};
/// "fluoroscopy" | "ultrasound".
std::string toString(Modality modality);

/// How the ultrasound mode renders. Both are pure functions of (seed, index, needle).
enum class UltrasoundModel : std::uint8_t {
  /// The classic renderer: Rayleigh speckle multiplied by echogenicity on a linear display
  /// scale, obstacle outlines, a needle brighter than anything else with three ghosts. The
  /// image-guided loop and its published figures were made on it (the default).
  kClassic,
  /// Closer to a clinical scanner (checked against the in-vitro set, bench tracking_real):
  /// scatterer amplitudes through an anisotropic point-spread function, log-compressed to a
  /// 55 dB display; two seeded specular tissue layers that span the frame (longer than the
  /// needle, brighter and wider than it) with a change of echogenicity across them; the needle's
  /// acoustic shadow beyond it, a reverberation tail of five fainter copies, and a seeded tilt
  /// out of the image plane that fades the shaft towards the tip (elevation beam profile). The
  /// noise (noise_std) enters before the log compression, as a scanner's electronic noise does,
  /// at noise_std times the mean tissue echo; the point-spread blur follows it.
  kRealistic,
  /// The realistic model on a convex (curvilinear) probe (convex_ultrasound.h): a fan under an
  /// arc-shaped probe face at the top of the frame (face radius convex_radius_m, half the
  /// sector's angle convex_half_angle_rad, its two ends on row kConvexFaceTop_px, its centre over
  /// the frame's centre), black outside it; speckle and the point-spread function in the
  /// probe's beam grid (the lateral resolution coarsens with depth), the needle's shadow and
  /// reverberation tail along the beams, the face's ring-down band; the scene's tissue is
  /// uniform (no layers). Frames drop with drop_probability; blur_sigma_m and tissue_motion_px
  /// do not apply (the point-spread function is the probe's; the tissue is still).
  kConvex,
};
/// "classic" | "realistic" | "convex".
std::string toString(UltrasoundModel model);
/// Inverse of toString(UltrasoundModel); nullopt for anything else.
std::optional<UltrasoundModel> ultrasoundModelFromString(const std::string& name);
/// Inverse of toString(Modality); nullopt for anything else.
std::optional<Modality> modalityFromString(const std::string& name);

/// Everything that defines the simulated device. Lengths in metres, intensities as fractions of
/// full scale (255 grey levels).
struct ImagerConfig {
  Modality modality = Modality::kUltrasound;
  ImageGeometry geometry;     ///< the pixel grid (calibration); validated
  double noise_std = 0.0;     ///< additive Gaussian noise per frame, fraction of full scale, >= 0
  double blur_sigma_m = 0.0;  ///< Gaussian point-spread function, >= 0 [m]
  double drop_probability = 0.0;      ///< probability that a frame is lost, in [0, 1)
  double needle_diameter_m = 0.5e-3;  ///< drawn width of the needle, > 0 [m]
  std::uint64_t seed = 1;             ///< seed of everything random (speckle, noise, drops)
  /// Ultrasound renderer (ignored in fluoroscopy).
  UltrasoundModel ultrasound_model = UltrasoundModel::kClassic;
  /// Tissue motion of the realistic ultrasound model (breathing, a hand-held probe): the
  /// tissue's speed [px / frame], >= 0 and <= 10; 0 = still tissue (the default). The tissue
  /// (speckle, layers, outlines) drifts at this speed in a seeded direction, sways along the
  /// beam by up to 1.5 times it (a 10-frame period), is compressed along the beam by up to 1 %,
  /// and its speckle decorrelates partly from frame to frame; the needle is drawn where it is.
  double tissue_motion_px = 0.0;
  /// The convex probe (UltrasoundModel::kConvex): radius of its face [m], > 0, and half the
  /// sector's angle [rad], in (0, 1.4]. The face's chord must fit in the frame's width and the
  /// face lie above its bottom (checked by FrameRenderer).
  double convex_radius_m = 0.05;
  double convex_half_angle_rad = 0.55;
  /// Throws std::invalid_argument naming the field and its value when anything is out of range.
  void validate() const;
};

/// The device of a scene: its imaging section (modality, pixel size, noise, blur, drops) over a
/// pixel grid covering the workspace (tissue::forWorkspace).
/// Throws std::invalid_argument for an unknown modality.
ImagerConfig imagerConfigFromScene(const scene::Scene& scene, std::uint64_t seed = 1);

/// A field of view of cols x rows pixels of pixel_size_m centred on the workspace's centre (the
/// whole workspace, tissue::forWorkspace, when cols or rows is 0). Throws std::invalid_argument
/// for a pixel size that is not positive and finite or a negative count.
ImageGeometry fieldOfView(const scene::Scene& scene, double pixel_size_m, int cols = 0,
                          int rows = 0);

/// The points FrameRenderer::render draws for a needle inserted from p_SceneEntry [m, frame
/// scene] at angle_rad above +x, length_m long, step_m apart: straight (kappa_per_m 0) or on an
/// arc of curvature kappa_per_m [1/m] (> 0 turning towards +y). Scenario generator of the tracking
/// benchmarks and tests.
std::vector<Point2> insertedNeedlePoints(Point2 p_SceneEntry, double angle_rad, double length_m,
                                         double kappa_per_m = 0.0, double step_m = 0.25e-3);

/// One frame. `image` is CV_8UC1 of config.geometry.size(); empty when dropped.
struct Frame {
  std::uint64_t index =
      0;                 ///< frame number (0, 1, 2, ...): with the seed it fixes every random draw
  bool dropped = false;  ///< true: the device lost this frame (image empty)
  cv::Mat image;
};

/// Renders frames of one scene. The static anatomy (background, obstacles, regions, and in
/// ultrasound the speckle pattern of the tissue, which does not change while the tissue does not
/// move) is made once at construction; each frame adds the needle, the blur and that frame's
/// noise. Deterministic: the same (config, needle, index) gives the same frame bit for bit.
class FrameRenderer {
public:
  /// Throws std::invalid_argument from config.validate().
  FrameRenderer(const scene::Scene& scene, const ImagerConfig& config);

  /// Frame `index` of the needle whose inserted shape is `needle_points` (entry -> tip, frame
  /// scene [m], spaced finely enough to draw as a polyline; empty or one point = no needle in the
  /// image). Parts of the needle outside the field of view are clipped. Throws
  /// std::invalid_argument if a point is not finite.
  Frame render(const std::vector<Point2>& needle_points, std::uint64_t index) const;

  /// Whether frame `index` is dropped (the same draw render() uses).
  bool dropped(std::uint64_t index) const;

  const ImagerConfig& config() const { return config_; }
  /// The static anatomy before blur and noise, as fractions of full scale (CV_32FC1); with the
  /// realistic ultrasound model, echo amplitudes before log compression (1 = full scale).
  const cv::Mat& anatomy() const { return anatomy_; }

  /// Row of the convex probe face's two ends (UltrasoundModel::kConvex) [px].
  static constexpr double kConvexFaceTop_px = 8.0;

private:
  ImagerConfig config_;
  /// UltrasoundModel::kConvex: the probe and its (uniform) scene.
  std::shared_ptr<const ConvexScene> convex_;
  cv::Mat anatomy_;      ///< CV_32FC1, static part of the frame
  cv::Mat attenuation_;  ///< CV_32FC1, ultrasound: per-pixel gain of depth attenuation and shadows
};

}  // namespace needle_guidance::imaging
