// ROS wrapper of the 3-D steerable-needle planner (node steering_planner_3d): loads a
// steering_3d scene, replans from every tip pose it receives (Planner3::planFromTip under
// ~time_budget_s) and publishes the plan's first control and the plan; serves ~plan (from the
// entry region). The planner is the core's (steering_3d/planner_3d.h); this class converts and
// wires only.
#pragma once

#include <geometry_msgs/PoseWithCovarianceStamped.h>
#include <ros/ros.h>
#include <tf2_ros/static_transform_broadcaster.h>

#include <cstdint>
#include <memory>
#include <string>

#include "needle_guidance/PlanSteering3.h"
#include "needle_guidance/SteeringControl3.h"
#include "needle_guidance/steering_3d/planner_3d.h"

namespace needle_guidance {

/// Subscribes `tip` (PoseWithCovarianceStamped, frame scene) and publishes one `~control`
/// (SteeringControl3, stamped with the tip's stamp) per tip: status "ok" with the plan's first
/// control, the planner's PlanCode name when it finds no plan, "bad_input" for a tip that is
/// refused (wrong frame, non-finite, not a unit quaternion, negative variance); never a NaN.
/// Publishes `~plan` (Marker LINE_STRIP, latched) after each plan and latched `~scene_markers`
/// (MarkerArray: tissue and obstacle meshes, target, entry). Serves `~plan` (PlanSteering3).
class SteeringPlanner3dRos {
public:
  /// Reads ~scene (a steering_3d YAML file, required), ~time_budget_s, ~entry_time_budget_s,
  /// ~max_plans, ~seed, ~noise_scale and ~scene_parent_frame (if set, a static identity
  /// transform parent -> scene is broadcast, for rviz without a robot) once; throws
  /// std::runtime_error naming a bad one and scene::SceneError for a bad scene file.
  SteeringPlanner3dRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);

private:
  void onTip(const geometry_msgs::PoseWithCovarianceStampedConstPtr& msg);
  bool onPlan(PlanSteering3::Request& req, PlanSteering3::Response& res);
  void publishPlan(const steering_3d::Plan3& plan);

  std::unique_ptr<needle_model::Scene3d> scene_;
  std::unique_ptr<needle_model::CollisionWorld3> world_;
  std::unique_ptr<steering_3d::Planner3> planner_;
  std::uint64_t seed_ = 1;
  std::uint64_t tips_ = 0;  ///< tips answered: the k-th replan's seed mixes seed_ and k
  ros::Publisher control_pub_;
  ros::Publisher plan_pub_;
  ros::Publisher scene_pub_;
  ros::Subscriber tip_sub_;
  ros::ServiceServer plan_srv_;
  tf2_ros::StaticTransformBroadcaster frame_broadcaster_;
};

}  // namespace needle_guidance
