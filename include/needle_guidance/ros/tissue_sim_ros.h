// ROS wrapper of the tissue simulation (node tissue_sim): follows the insertion robot's joint
// states, steps the FEM needle-insertion model and publishes what a user sees.
#pragma once

#include <ros/ros.h>
#include <sensor_msgs/JointState.h>
#include <std_srvs/Trigger.h>

#include <memory>
#include <opencv2/core.hpp>
#include <optional>
#include <string>

#include "needle_guidance/ImplantSeed.h"
#include "needle_guidance/ros/tissue_sim_3d_ros.h"
#include "needle_guidance/tissue/image_warp.h"
#include "needle_guidance/tissue/tissue_simulation.h"

namespace needle_guidance {

/// Reads parameters once (throws std::runtime_error on a bad one), then steps the simulation on
/// a timer with the latest robot joint state. A `kind: tissue_3d` ~scene runs the 3-D mode
/// (TissueSim3Ros) with the same topics and services.
class TissueSimRos {
public:
  TissueSimRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);

private:
  void onJointState(const sensor_msgs::JointStateConstPtr& msg);
  void onStepTimer(const ros::TimerEvent& event);
  void onImageTimer(const ros::TimerEvent& event);
  bool onReset(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  bool onImplantSeed(ImplantSeed::Request& req, ImplantSeed::Response& res);
  void publishMarkers(const ros::Time& stamp);

  std::unique_ptr<tissue::TissueSimulation> sim_;
  std::unique_ptr<TissueSim3Ros> sim3_;  ///< 3-D mode (sim_ is then null)
  std::string colour_by_;
  std::optional<double> height_m_;
  std::optional<double> depth_m_;
  ros::Time last_step_;
  double last_step_ms_ = 0.0;
  double marker_period_s_ = 0.05;
  double rate_hz_ = 200.0;
  ros::Time last_markers_;
  tissue::ImageGeometry image_geometry_;
  cv::Mat reference_image_;

  ros::Subscriber joint_sub_;
  ros::Publisher markers_pub_;
  ros::Publisher status_pub_;
  ros::Publisher seeds_pub_;
  ros::Publisher image_pub_;
  ros::ServiceServer reset_srv_;
  ros::ServiceServer implant_srv_;
  ros::Timer step_timer_;
  ros::Timer image_timer_;
};

}  // namespace needle_guidance
