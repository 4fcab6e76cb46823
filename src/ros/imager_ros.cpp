#include "needle_guidance/ros/imager_ros.h"

#include <cv_bridge/cv_bridge.h>

#include <cmath>
#include <stdexcept>

#include "needle_guidance/ImageCalibration.h"
#include "needle_guidance/imaging/biplane_views.h"
#include "needle_guidance/math.h"
#include "needle_guidance/ros/params.h"
#include "needle_guidance/scene/scene.h"

namespace needle_guidance {
namespace {

constexpr const char* kName = "imager";
constexpr double kThrottle_s = 5.0;
constexpr double kMaxFrameRate_hz = 1000.0;
constexpr long kMaxImageSide_px = 8192;

}  // namespace

ImagerRos::ImagerRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh) {
  namespace rp = ros_params;
  ROS_INFO("imager parameters:");
  const auto seed = static_cast<std::uint64_t>(rp::integer(private_nh, "seed", 1, 0, 1L << 53, ""));
  const imaging::ImagerView view = rp::choice(
      private_nh, "view", "plane", imaging::imagerViewFromString, "plane, along_z or along_y");
  // One ~scene, dispatched on its kind: a steering_3d file is seen along one of its axes.
  const std::string scene_spec = rp::text(private_nh, "scene", "steering_workspace");
  const bool scene_is_3d = scene::sceneKind(scene_spec) == "steering_3d";
  if (scene_is_3d != imaging::viewAxis(view).has_value()) {
    throw std::runtime_error("parameter '" + private_nh.resolveName("scene") + "' = '" +
                             scene_spec + "': " +
                             (scene_is_3d ? "a steering_3d scene needs ~view along_z or along_y"
                                          : "~view along_z / along_y needs a steering_3d scene"));
  }
  scene::Scene scene;
  imaging::ImagerConfig config;
  if (const auto axis = imaging::viewAxis(view)) {  // one fluoroscopy view of a 3-D scene
    rows_ = needle_model::viewRows(*axis);
    imaging::BiplaneViewsConfig views;  // the biplane detector's geometry; along y seed + 1
    views.seed = seed;
    imaging::BiplaneViewSetup setup =
        imaging::biplaneViewSetup(needle_model::loadScene3d(scene_spec), views, *axis);
    scene = std::move(setup.plane);
    config = setup.imager;
  } else {  // every device setting defaults to the scene's imaging section
    scene = scene::loadSceneSpec(scene_spec);
    config = imaging::imagerConfigFromScene(scene, seed);
    config.modality = rp::choice(private_nh, "modality", imaging::toString(config.modality),
                                 imaging::modalityFromString, "ultrasound or fluoroscopy");
    config.ultrasound_model =
        rp::choice(private_nh, "ultrasound_model", "classic", imaging::ultrasoundModelFromString,
                   "classic, realistic or convex");
    // The convex probe's face (ultrasound_model convex): its radius and half the fan's angle.
    config.convex_radius_m =
        rp::number(private_nh, "convex_radius_m", config.convex_radius_m, 1e-3, 1.0, "m");
    config.convex_half_angle_rad =
        rp::number(private_nh, "convex_half_angle_deg", config.convex_half_angle_rad * 180.0 / kPi,
                   1.0, 80.0, "deg") *
        kPi / 180.0;
    config.tissue_motion_px =  // the realistic model's moving tissue
        rp::number(private_nh, "tissue_motion_px", config.tissue_motion_px, 0, 10, "px / frame");
    const double pixel_size_m =
        rp::number(private_nh, "pixel_size_m", config.geometry.pixel_size_m, 1e-6, 0.01, "m");
    const auto side_px = [&](const char* name) {  // 0 = the workspace's
      return int(rp::integer(private_nh, name, 0, 0, kMaxImageSide_px, "px (0 = workspace)"));
    };
    config.geometry =
        imaging::fieldOfView(scene, pixel_size_m, side_px("width_px"), side_px("height_px"));
  }
  config.noise_std = rp::number(private_nh, "noise_std", config.noise_std, 0.0, 10.0, "");
  config.blur_sigma_m = rp::number(private_nh, "blur_sigma_m", config.blur_sigma_m, 0.0, 0.01, "m");
  config.drop_probability =
      rp::number(private_nh, "drop_probability", config.drop_probability, 0.0, 0.99, "");
  frame_rate_hz_ = rp::number(private_nh, "frame_rate_hz", scene.imaging.frame_rate_hz, 0.1,
                              kMaxFrameRate_hz, "Hz");
  renderer_ = std::make_unique<imaging::FrameRenderer>(scene, config);

  ImageCalibration calibration;
  calibration.header.stamp = ros::Time::now();
  calibration.header.frame_id = "scene";
  calibration.modality = imaging::toString(config.modality);
  calibration.origin_x_m = config.geometry.origin_m.x();
  calibration.origin_y_m = config.geometry.origin_m.y();
  calibration.pixel_size_m = config.geometry.pixel_size_m;
  calibration.width = static_cast<std::uint32_t>(config.geometry.cols);
  calibration.height = static_cast<std::uint32_t>(config.geometry.rows);
  calibration.frame_rate_hz = frame_rate_hz_;
  calibration.noise_std = config.noise_std;
  calibration.blur_sigma_m = config.blur_sigma_m;
  calibration.drop_probability = config.drop_probability;
  calibration.seed = config.seed;
  calibration_pub_ = private_nh.advertise<ImageCalibration>("calibration", 1, true);
  calibration_pub_.publish(calibration);
  image_pub_ = private_nh.advertise<sensor_msgs::Image>("image", 5);
  shape_sub_ = nh.subscribe("needle_shape", 5, &ImagerRos::onShape, this);
  frame_timer_ =
      nh.createTimer(ros::Duration(1.0 / frame_rate_hz_), &ImagerRos::onFrameTimer, this);
  ROS_INFO_STREAM_NAMED(kName, "imager: " << calibration.modality << ", " << calibration.width
                                          << " x " << calibration.height << " px of "
                                          << config.geometry.pixel_size_m * 1e3 << " mm at "
                                          << frame_rate_hz_ << " Hz on '" << scene.name << "'");
}

ImagerRos::~ImagerRos() {
  ROS_INFO_STREAM_NAMED(kName, "imager: " << published_ << " frames sent, " << dropped_ << " lost");
}

void ImagerRos::onShape(const NeedleShapeConstPtr& msg) {
  std::vector<imaging::Point2> points;
  for (const geometry_msgs::Point& p : msg->points) {
    if (!(std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z))) {
      ROS_ERROR_STREAM_THROTTLE_NAMED(kThrottle_s, kName, "imager: non-finite shape ignored");
      return;
    }
    points.emplace_back(rows_ ? imaging::Point2(*rows_ * Eigen::Vector3d(p.x, p.y, p.z))
                              : imaging::Point2(p.x, p.y));
  }
  std::lock_guard<std::mutex> lock(mutex_);
  needle_points_ = std::move(points);
  shape_stamp_ = msg->header.stamp;
  have_shape_ = true;
}

void ImagerRos::onFrameTimer(const ros::TimerEvent& /*event*/) {
  std::vector<imaging::Point2> points;
  ros::Time stamp = ros::Time::now();
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (have_shape_) {
      points = needle_points_;
      stamp = shape_stamp_;  // the frame shows the needle as it was then
    }
  }
  const imaging::Frame frame = renderer_->render(points, next_index_++);
  if (frame.dropped) {
    ++dropped_;
    return;
  }
  std_msgs::Header header;
  header.stamp = stamp;
  header.frame_id = "imager";
  header.seq = static_cast<std::uint32_t>(frame.index);
  image_pub_.publish(cv_bridge::CvImage(header, "mono8", frame.image).toImageMsg());
  ++published_;
}

}  // namespace needle_guidance
