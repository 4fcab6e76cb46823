// 3-D mode of the tissue_sim node (a `kind: tissue_3d` scene): follows the insertion robot's
// x-y stage and insertion joints, moves the needle through the tetrahedral FEM tissue
// (tissue_3d::NeedleInsertion3) and publishes the deformed organs, the needle and the seeds.
#pragma once

#include <ros/ros.h>
#include <sensor_msgs/JointState.h>
#include <std_srvs/Trigger.h>

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/ImplantSeed.h"
#include "needle_guidance/ros/conversions_tissue_3d.h"
#include "needle_guidance/tissue_3d/needle_insertion_3d.h"

namespace needle_guidance {

/// Reads parameters once and meshes the scene (throws std::runtime_error or the loader's error
/// on a bad one), then moves the needle on a timer to the robot's latest joint state: tip x =
/// "insertion", lateral (y, z) = ("height", "lateral"). The seed does not depend on the timer
/// rate: every event between two joint states is located (docs/tissue_3d.md).
class TissueSim3Ros {
public:
  TissueSim3Ros(ros::NodeHandle& nh, ros::NodeHandle& private_nh, const std::string& scene_file);

private:
  void onJointState(const sensor_msgs::JointStateConstPtr& msg);
  void onStepTimer(const ros::TimerEvent& event);
  /// Moves the needle to the latest joint state; "" on success, else why not.
  std::string follow();
  bool onReset(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  bool onImplantSeed(ImplantSeed::Request& req, ImplantSeed::Response& res);
  void publishMarkers(const ros::Time& stamp);
  void publishSeeds(const ros::Time& stamp);

  tissue_3d::TissueScene3d scene_;
  std::unique_ptr<tissue_3d::TissueModel3> model_;
  std::unique_ptr<tissue_3d::NeedleInsertion3> needle_;
  std::vector<ros_conversions::EmbeddedSurface3> surfaces_;
  std::optional<double> height_m_, lateral_m_, depth_m_;
  std::optional<Eigen::Vector3d> followed_;  ///< joint state the needle is at (y, z, x)
  double marker_period_s_ = 0.5;
  double last_step_ms_ = 0.0;
  ros::Time last_markers_, last_seeds_;
  bool markers_stale_ = true;

  ros::Subscriber joint_sub_;
  ros::Publisher markers_pub_, status_pub_, seeds_pub_;
  ros::ServiceServer reset_srv_, implant_srv_;
  ros::Timer step_timer_;
};

}  // namespace needle_guidance
