// Two rendered fluoroscopy views of the 3-D needle, detected and triangulated (biplane_views.h).
#include "needle_guidance/imaging/biplane_views.h"

#include <cmath>
#include <stdexcept>

namespace needle_guidance::imaging {

namespace sd = steering_3d;

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

BiplaneViews3::BiplaneViews3(const sd::Scene3d& scene, const BiplaneViewsConfig& config)
    : config_(config) {
  config_.validate();
  const sd::CollisionWorld3 world = scene.collisionWorld();
  for (const sd::ViewAxis axis : {sd::ViewAxis::kAlongZ, sd::ViewAxis::kAlongY}) {
    // The view's plane as a 2-D scene over the tissue's projected bounds (the renderer draws its
    // background; the needle is what the detector looks for).
    scene::Scene plane;
    plane.name = scene.name + (axis == sd::ViewAxis::kAlongZ ? " (view along z)" : " (along y)");
    const Eigen::Matrix<double, 2, 3> rows = sd::viewRows(axis);
    const Eigen::Vector2d margin(config_.margin_m, config_.margin_m);
    plane.workspace_min = rows * world.tissueMin() - margin;
    plane.workspace_max = rows * world.tissueMax() + margin;
    plane.imaging.modality = "fluoroscopy";
    ImagerConfig imager;
    imager.modality = Modality::kFluoroscopy;
    imager.geometry = fieldOfView(plane, config_.pixel_size_m);
    imager.noise_std = config_.noise_std;
    imager.blur_sigma_m = config_.blur_sigma_m;
    imager.drop_probability = config_.drop_probability;
    imager.seed = config_.seed + (axis == sd::ViewAxis::kAlongZ ? 0 : 1);
    renderers_.emplace_back(plane, imager);
    TrackerConfig tracker;
    tracker.modality = Modality::kFluoroscopy;
    tracker.geometry = imager.geometry;
    tracker.radius_of_curvature_m = 1.0 / scene.needle.kappa_max_per_m;
    tracker.needle_diameter_m = imager.needle_diameter_m;
    tracker.step_length_m = scene.step_length_m;
    tracker.validate();
    trackers_.push_back(tracker);
  }
}

const ImageGeometry& BiplaneViews3::geometry(sd::ViewAxis axis) const {
  return trackers_[axis == sd::ViewAxis::kAlongZ ? 0 : 1].geometry;
}

BiplaneView3 BiplaneViews3::view(sd::ViewAxis axis, const std::vector<sd::Vector3>& needle,
                                 std::uint64_t index) const {
  const std::size_t k = axis == sd::ViewAxis::kAlongZ ? 0 : 1;
  const Eigen::Matrix<double, 2, 3> rows = sd::viewRows(axis);
  std::vector<Point2> points;
  points.reserve(needle.size());
  for (const sd::Vector3& p : needle) {
    points.emplace_back(rows * p);
  }
  BiplaneView3 out;
  out.axis = axis;
  out.frame = renderers_[k].render(points, index);
  if (out.frame.dropped) {
    out.detection.message = "frame dropped";
  } else {
    // The detector fits arcs of one known radius; a duty-cycled needle's projection bends less
    // than kappa_max. Fit each candidate radius and keep the closest fit.
    TrackerConfig tracker = trackers_[k];
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
  }
  return out;
}

BiplaneObservation3 BiplaneViews3::observe(const std::vector<sd::Vector3>& needle,
                                           const sd::TipPose3& predicted,
                                           std::uint64_t index) const {
  BiplaneObservation3 out;
  out.along_z = view(sd::ViewAxis::kAlongZ, needle, index);
  out.along_y = view(sd::ViewAxis::kAlongY, needle, index);
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
