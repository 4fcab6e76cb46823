// Two rendered fluoroscopy views of the 3-D needle, detected and triangulated (biplane_views.h).
#include "needle_guidance/imaging/biplane_views.h"

#include <cmath>
#include <stdexcept>

namespace needle_guidance::imaging {

namespace sd = needle_model;

namespace {
/// Radii the detector tries, in units of the needle's smallest (1 / kappa_max).
constexpr double kRadiusFactors[] = {1.0, 2.0, 4.0, 16.0};
}  // namespace

void BiplaneViewsConfig::validate() const {
  const auto require = [](bool ok, const char* what) {
    if (!ok) {
      throw std::invalid_argument(std::string("BiplaneViewsConfig: ") + what);
    }
  };
  require(pixel_size_m > 0.0 && std::isfinite(pixel_size_m), "pixel_size_m must be > 0");
  require(noise_std >= 0.0 && std::isfinite(noise_std), "noise_std must be >= 0");
  require(blur_sigma_m >= 0.0 && std::isfinite(blur_sigma_m), "blur_sigma_m must be >= 0");
  require(drop_probability >= 0.0 && drop_probability < 1.0, "drop_probability must be in [0, 1)");
  require(margin_m >= 0.0 && std::isfinite(margin_m), "margin_m must be >= 0");
  require(min_sigma_m > 0.0 && std::isfinite(min_sigma_m), "min_sigma_m must be > 0");
  require(gate > 0.0, "gate must be > 0");
}

std::optional<ImagerView> imagerViewFromString(const std::string& name) {
  if (name == "plane") {
    return ImagerView::kPlane;
  }
  if (name == "along_z") {
    return ImagerView::kAlongZ;
  }
  if (name == "along_y") {
    return ImagerView::kAlongY;
  }
  return std::nullopt;
}

std::optional<sd::ViewAxis> viewAxis(ImagerView view) {
  switch (view) {
    case ImagerView::kAlongZ:
      return sd::ViewAxis::kAlongZ;
    case ImagerView::kAlongY:
      return sd::ViewAxis::kAlongY;
    case ImagerView::kPlane:
      break;
  }
  return std::nullopt;
}

BiplaneViewSetup biplaneViewSetup(const sd::Scene3d& scene, const BiplaneViewsConfig& config,
                                  sd::ViewAxis axis) {
  config.validate();
  const sd::CollisionWorld3 world = scene.collisionWorld();
  // The view's plane as a 2-D scene over the tissue's projected bounds (the renderer draws its
  // background; the needle is what the detector looks for).
  BiplaneViewSetup out;
  out.plane.name = scene.name + (axis == sd::ViewAxis::kAlongZ ? " (view along z)" : " (along y)");
  const Eigen::Matrix<double, 2, 3> rows = sd::viewRows(axis);
  const Eigen::Vector2d margin(config.margin_m, config.margin_m);
  out.plane.workspace_min = rows * world.tissueMin() - margin;
  out.plane.workspace_max = rows * world.tissueMax() + margin;
  out.plane.imaging.modality = "fluoroscopy";
  out.imager.modality = Modality::kFluoroscopy;
  out.imager.geometry = fieldOfView(out.plane, config.pixel_size_m);
  out.imager.noise_std = config.noise_std;
  out.imager.blur_sigma_m = config.blur_sigma_m;
  out.imager.drop_probability = config.drop_probability;
  out.imager.seed = config.seed + (axis == sd::ViewAxis::kAlongZ ? 0 : 1);
  out.tracker.modality = Modality::kFluoroscopy;
  out.tracker.geometry = out.imager.geometry;
  out.tracker.radius_of_curvature_m = 1.0 / scene.needle.kappa_max_per_m;
  out.tracker.needle_diameter_m = out.imager.needle_diameter_m;
  out.tracker.step_length_m = scene.step_length_m;
  out.tracker.validate();
  return out;
}

BiplaneFusion3::BiplaneFusion3(const sd::Scene3d& scene, const BiplaneViewsConfig& config)
    : config_(config) {
  for (const sd::ViewAxis axis : {sd::ViewAxis::kAlongZ, sd::ViewAxis::kAlongY}) {
    trackers_.push_back(biplaneViewSetup(scene, config_, axis).tracker);
  }
}

const ImageGeometry& BiplaneFusion3::geometry(sd::ViewAxis axis) const {
  return trackers_[axis == sd::ViewAxis::kAlongZ ? 0 : 1].geometry;
}

BiplaneView3 BiplaneFusion3::detect(sd::ViewAxis axis, const Frame& frame) const {
  BiplaneView3 out;
  out.axis = axis;
  out.frame = frame;
  if (frame.dropped || frame.image.empty()) {
    out.detection.message = "frame dropped";
    return out;
  }
  // The detector fits arcs of one known radius; a duty-cycled needle's projection bends less
  // than kappa_max. Fit each candidate radius and keep the closest fit.
  TrackerConfig tracker = trackers_[axis == sd::ViewAxis::kAlongZ ? 0 : 1];
  if (frame.image.cols != tracker.geometry.cols || frame.image.rows != tracker.geometry.rows) {
    throw std::invalid_argument(
        std::string("BiplaneFusion3: the frame along ") +
        (axis == sd::ViewAxis::kAlongZ ? "z" : "y") + " is " + std::to_string(frame.image.cols) +
        " x " + std::to_string(frame.image.rows) + " px; the view is " +
        std::to_string(tracker.geometry.cols) + " x " + std::to_string(tracker.geometry.rows) +
        " px (another pixel size or scene?)");
  }
  const double r_min = tracker.radius_of_curvature_m;
  for (const double factor : kRadiusFactors) {
    tracker.radius_of_curvature_m = r_min * factor;
    const Detection d = detectTip(out.frame.image, tracker, std::nullopt);
    if (d.found && (!out.detection.found || d.residual_rms_m < out.detection.residual_rms_m)) {
      out.detection = d;
    } else if (!out.detection.found && out.detection.message.empty()) {
      out.detection.message = d.message;
    }
  }
  return out;
}

BiplaneViews3::BiplaneViews3(const sd::Scene3d& scene, const BiplaneViewsConfig& config)
    : fusion_(scene, config) {
  for (const sd::ViewAxis axis : {sd::ViewAxis::kAlongZ, sd::ViewAxis::kAlongY}) {
    const BiplaneViewSetup setup = biplaneViewSetup(scene, config, axis);
    renderers_.emplace_back(setup.plane, setup.imager);
  }
}

BiplaneObservation3 BiplaneViews3::observe(const std::vector<sd::Vector3>& needle,
                                           const sd::TipPose3& predicted,
                                           std::uint64_t index) const {
  Frame frames[2];
  for (const sd::ViewAxis axis : {sd::ViewAxis::kAlongZ, sd::ViewAxis::kAlongY}) {
    const std::size_t k = axis == sd::ViewAxis::kAlongZ ? 0 : 1;
    const Eigen::Matrix<double, 2, 3> rows = sd::viewRows(axis);
    std::vector<Point2> points;
    points.reserve(needle.size());
    for (const sd::Vector3& p : needle) {
      points.emplace_back(rows * p);
    }
    frames[k] = renderers_[k].render(points, index);
  }
  return fusion_.observeFrames(frames[0], frames[1], predicted);
}

BiplaneObservation3 BiplaneFusion3::observeFrames(const Frame& along_z, const Frame& along_y,
                                                  const sd::TipPose3& predicted) const {
  BiplaneObservation3 out;
  out.along_z = detect(sd::ViewAxis::kAlongZ, along_z);
  out.along_y = detect(sd::ViewAxis::kAlongY, along_y);
  const BiplaneView3* missing = !out.along_z.detection.found   ? &out.along_z
                                : !out.along_y.detection.found ? &out.along_y
                                                               : nullptr;
  if (missing != nullptr) {
    out.tip = sd::BiplaneStatus(sd::BiplaneCode::kNoDetection,
                                std::string("biplane: no tip in the view along ") +
                                    (missing->axis == sd::ViewAxis::kAlongZ ? "z: " : "y: ") +
                                    missing->detection.message);
    return out;
  }
  sd::ViewDetection v[2];
  const BiplaneView3* views[2] = {&out.along_z, &out.along_y};
  const double floor_m2 = config_.min_sigma_m * config_.min_sigma_m;
  for (int k = 0; k < 2; ++k) {
    v[k].axis = views[k]->axis;
    v[k].p_m = views[k]->detection.p_SceneTip;
    const Eigen::Matrix2d c = views[k]->detection.covariance.topLeftCorner<2, 2>();
    v[k].covariance_m2 = 0.5 * (c + c.transpose()) + floor_m2 * Eigen::Matrix2d::Identity();
  }
  const auto fused = sd::triangulateBiplane(v[0], v[1], config_.gate);
  if (!fused) {
    out.tip = fused.status();
    return out;
  }
  out.covariance_m2 = fused.value().covariance_m2;
  out.tip = sd::tipFromViews(fused.value().p_SceneTip, out.along_z.detection.theta_rad,
                             out.along_y.detection.theta_rad, predicted.bevel());
  return out;
}

}  // namespace needle_guidance::imaging
