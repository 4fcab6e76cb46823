#include "needle_guidance/ros/tissue_sim_ros.h"

#include <cv_bridge/cv_bridge.h>
#include <geometry_msgs/PoseArray.h>
#include <sensor_msgs/Image.h>
#include <visualization_msgs/MarkerArray.h>

#include <algorithm>
#include <chrono>

#include "needle_guidance/TissueStatus.h"
#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/implant_seed_answer.h"
#include "needle_guidance/ros/params.h"

namespace needle_guidance {
namespace {

tissue::IntegratorKind parseIntegrator(const std::string& name, const scene::Scene& scene) {
  if (name.empty()) {
    return tissue::optionsFromScene(scene).integrator;
  }
  if (name == "quasi_static") {
    return tissue::IntegratorKind::kQuasiStatic;
  }
  if (name == "newmark") {
    return tissue::IntegratorKind::kNewmark;
  }
  if (name == "explicit") {
    return tissue::IntegratorKind::kExplicit;
  }
  throw std::runtime_error("parameter 'integrator' = '" + name +
                           "' is not one of '', quasi_static, newmark, explicit");
}

}  // namespace

TissueSimRos::TissueSimRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh) {
  ROS_INFO("tissue_sim parameters:");
  const std::string scene_spec = ros_params::text(private_nh, "scene", "prostate_sagittal");
  if (scene::sceneKind(scene_spec) == "tissue_3d") {  // the 3-D mode, same topics and services
    sim3_ = std::make_unique<TissueSim3Ros>(nh, private_nh, scene_spec);
    return;
  }
  const scene::Scene scene = scene::loadSceneSpec(scene_spec);
  if (!scene.hasTissue()) {
    throw std::runtime_error("scene '" + scene.name +
                             "' has no tissue model (models.tissue: none)");
  }
  tissue::TissueSimOptions options = tissue::optionsFromScene(scene);
  options.integrator = parseIntegrator(ros_params::text(private_nh, "integrator", ""), scene);
  const std::string formulation = ros_params::text(private_nh, "formulation", "");
  if (formulation == "averaged_volumetric") {
    options.formulation = tissue::ElementFormulation::kAveragedVolumetric;
  } else if (formulation == "linear") {
    options.formulation = tissue::ElementFormulation::kLinear;
  } else if (!formulation.empty()) {
    throw std::runtime_error("parameter 'formulation' = '" + formulation +
                             "' is not one of '' (the scene's), linear, averaged_volumetric");
  }
  options.needle_model = tissue::needleModelFor(options);
  const double rate_hz = ros_params::number(private_nh, "rate_hz", 200.0, 1.0, 5000.0, "Hz");
  const double marker_rate_hz =
      ros_params::number(private_nh, "marker_rate_hz", 20.0, 0.1, rate_hz, "Hz");
  const double image_rate_hz =
      ros_params::number(private_nh, "image_rate_hz", 5.0, 0.0, 60.0, "Hz");
  const double pixel_size_m = ros_params::number(private_nh, "image_pixel_size_m",
                                                 scene.imaging.pixel_size_m, 1e-5, 0.01, "m");
  const int image_seed =
      static_cast<int>(ros_params::number(private_nh, "image_seed", 1, 0, 1e9, "1"));
  colour_by_ = ros_params::text(private_nh, "colour_by", "region");
  if (colour_by_ != "region" && colour_by_ != "stress") {
    throw std::runtime_error("parameter 'colour_by' = '" + colour_by_ +
                             "' is not region or stress");
  }
  const std::string robot = ros_params::text(private_nh, "robot", "insertion_robot");
  // The depth grid: every joint state is sub-stepped onto it, so the seed lands where
  // the planner's verifying simulation put it, whatever the message and timer rates.
  options.depth_grid.step_m = ros_params::number(
      private_nh, "depth_step_m", options.depth_grid.step_m, 0.0, 0.01, "m (0 = off)");
  marker_period_s_ = 1.0 / marker_rate_hz;
  rate_hz_ = rate_hz;

  const auto start = std::chrono::steady_clock::now();
  sim_ = std::make_unique<tissue::TissueSimulation>(scene, options);
  const double build_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  ROS_INFO_STREAM("tissue_sim: scene '" << scene.name << "', " << sim_->mesh().triangleCount()
                                        << " triangles, " << sim_->mesh().nodeCount() << " nodes, "
                                        << tissue::toString(options.integrator) << ", built in "
                                        << build_ms << " ms");
  image_geometry_ = tissue::forWorkspace(scene, pixel_size_m);
  reference_image_ =
      tissue::referenceImage(scene, image_geometry_, static_cast<std::uint32_t>(image_seed));

  markers_pub_ = private_nh.advertise<visualization_msgs::MarkerArray>("markers", 1);
  status_pub_ = private_nh.advertise<TissueStatus>("status", 10);
  seeds_pub_ = private_nh.advertise<geometry_msgs::PoseArray>("seeds", 1, true);
  image_pub_ = private_nh.advertise<sensor_msgs::Image>("image", 1);
  reset_srv_ = private_nh.advertiseService("reset", &TissueSimRos::onReset, this);
  implant_srv_ = private_nh.advertiseService("implant_seed", &TissueSimRos::onImplantSeed, this);
  joint_sub_ = nh.subscribe(robot + "/measured_js", 10, &TissueSimRos::onJointState, this);
  last_step_ = ros::Time::now();
  step_timer_ = nh.createTimer(ros::Duration(1.0 / rate_hz), &TissueSimRos::onStepTimer, this);
  if (image_rate_hz > 0.0) {
    image_timer_ =
        nh.createTimer(ros::Duration(1.0 / image_rate_hz), &TissueSimRos::onImageTimer, this);
  }
}

void TissueSimRos::onJointState(const sensor_msgs::JointStateConstPtr& msg) {
  for (std::size_t i = 0; i < msg->name.size() && i < msg->position.size(); ++i) {
    if (msg->name[i] == "height") {
      height_m_ = msg->position[i];
    } else if (msg->name[i] == "insertion") {
      depth_m_ = msg->position[i];
    }
  }
}

void TissueSimRos::onStepTimer(const ros::TimerEvent& /*event*/) {
  const ros::Time now = ros::Time::now();
  const double dt_s = (now - last_step_).toSec();
  if (!height_m_ || !depth_m_ || dt_s <= 0.0) {
    return;
  }
  last_step_ = now;
  const auto start = std::chrono::steady_clock::now();
  const tissue::StepStatus status = sim_->advance(dt_s, *height_m_, *depth_m_);
  last_step_ms_ =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  if (!status) {
    ROS_ERROR_STREAM_THROTTLE_NAMED(2.0, "tissue_sim",
                                    "tissue_sim: step refused: " << status.toString());
  }
  const tissue::InsertionStepInfo& info = sim_->lastStep();
  TissueStatus msg;
  msg.header.stamp = now;
  msg.header.frame_id = "scene";
  msg.needle_in_tissue = sim_->needleInTissue();
  msg.tip_force_N = info.tip_force_N;
  msg.friction_force_N = info.friction_force_N;
  msg.shaft_nodes = sim_->shaftCount();
  msg.slipping_nodes = info.slipping;
  msg.cuts = info.cuts;
  msg.relocations = info.relocations;
  msg.seeds = static_cast<int>(sim_->seeds().size());
  msg.step_time_ms = last_step_ms_;
  msg.integrator = tissue::toString(sim_->options().integrator);
  status_pub_.publish(msg);
  if ((now - last_markers_).toSec() >= marker_period_s_) {
    last_markers_ = now;
    publishMarkers(now);
  }
}

void TissueSimRos::publishMarkers(const ros::Time& stamp) {
  visualization_msgs::MarkerArray markers =
      ros_conversions::tissueToMarkers(*sim_, colour_by_, "scene");
  for (auto& m : markers.markers) {
    m.header.stamp = stamp;
  }
  markers_pub_.publish(markers);
  geometry_msgs::PoseArray seeds;
  seeds.header.stamp = stamp;
  seeds.header.frame_id = "scene";
  for (const auto& seed : sim_->seeds()) {
    geometry_msgs::Pose pose;
    pose.position = ros_conversions::toMessage(sim_->seedPosition(seed));
    pose.orientation.w = 1.0;
    seeds.poses.push_back(pose);
  }
  seeds_pub_.publish(seeds);
}

void TissueSimRos::onImageTimer(const ros::TimerEvent& /*event*/) {
  if (image_pub_.getNumSubscribers() == 0) {
    return;
  }
  try {
    const cv::Mat warped =
        tissue::warpImage(reference_image_, image_geometry_, sim_->mesh(), sim_->displacement());
    cv_bridge::CvImage image(std_msgs::Header(), "mono8", warped);
    image.header.stamp = ros::Time::now();
    image.header.frame_id = "scene_image";
    image_pub_.publish(image.toImageMsg());
  } catch (const std::exception& e) {
    ROS_ERROR_STREAM_THROTTLE_NAMED(5.0, "tissue_sim",
                                    "tissue_sim: image warp failed: " << e.what());
  }
}

bool TissueSimRos::onReset(std_srvs::Trigger::Request& /*req*/, std_srvs::Trigger::Response& res) {
  sim_->reset();
  res.success = true;
  res.message = "tissue reset to the reference mesh; seeds removed";
  publishMarkers(ros::Time::now());
  return true;
}

bool TissueSimRos::onImplantSeed(ImplantSeed::Request& /*req*/, ImplantSeed::Response& res) {
  std::string why_not_followed;
  if (height_m_ && depth_m_) {  // catch up with the robot's last state before releasing
    const tissue::StepStatus status = sim_->advance(1.0 / rate_hz_, *height_m_, *depth_m_);
    if (!status) {
      why_not_followed = status.toString();
    }
  }
  const std::optional<int> id = ros_conversions::answerImplantSeed(
      why_not_followed, [this](std::string* why_not) { return sim_->implantSeed(why_not); }, res);
  if (!id) {
    return true;
  }
  res.position = ros_conversions::toMessage(sim_->seedPosition(sim_->seeds().back()));
  publishMarkers(ros::Time::now());
  return true;
}

}  // namespace needle_guidance
