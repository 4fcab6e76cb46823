// ROS wrapper of the rigid-needle offset planner (node rigid_planner).
#pragma once

#include <ros/ros.h>

#include <memory>

#include "needle_guidance/PlanRigid.h"
#include "needle_guidance/rigid_planning/rigid_planner.h"
#include "needle_guidance/ros/rigid_planner_3d_ros.h"

namespace needle_guidance {

/// Reads parameters once (throws std::runtime_error on a bad one) and serves `~plan`. A
/// `kind: tissue_3d` ~scene runs the 3-D mode (RigidPlanner3Ros) on the same service.
class RigidPlannerRos {
public:
  RigidPlannerRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);

private:
  bool onPlan(PlanRigid::Request& req, PlanRigid::Response& res);
  std::unique_ptr<rigid_planning::RigidPlanner> planner_;
  std::unique_ptr<RigidPlanner3Ros> planner3_;  ///< 3-D mode (planner_ is then null)
  ros::ServiceServer plan_srv_;
  double last_height_offset_m_ =
      0.0;  ///< warm start: the previous plan's release height - target height
};

}  // namespace needle_guidance
