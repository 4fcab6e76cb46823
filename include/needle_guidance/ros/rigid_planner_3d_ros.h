// 3-D mode of the rigid_planner node (a `kind: tissue_3d` scene): serves ~plan (PlanRigid) with
// tissue_3d::OffsetPlanner3, the offset planner of dissertation ch. 4 in 3-D.
#pragma once

#include <ros/ros.h>

#include <memory>
#include <string>

#include "needle_guidance/PlanRigid.h"
#include "needle_guidance/tissue_3d/offset_planner_3d.h"

namespace needle_guidance {

/// Meshes the scene once (the same mesh as tissue_sim's 3-D mode) and plans each target: the
/// release is (tip x, lateral y, lateral z); every plan is verified by an independent full
/// simulation. A target the planner cannot place answers success = false with the physical
/// reason and code "unreachable" (outside the tissue, in or behind bone, out of the robot's
/// reach, no template hole close enough) or "out of tolerance" (verified miss).
class RigidPlanner3Ros {
public:
  RigidPlanner3Ros(ros::NodeHandle& private_nh, const std::string& scene_file, double tolerance_m);

private:
  bool onPlan(PlanRigid::Request& req, PlanRigid::Response& res);

  tissue_3d::TissueScene3d scene_;
  std::unique_ptr<tissue_3d::TissueModel3> model_;
  std::unique_ptr<tissue_3d::OffsetPlanner3> planner_;
  tissue_3d::PlannerOptions3 options_;
  ros::ServiceServer plan_srv_;
};

}  // namespace needle_guidance
