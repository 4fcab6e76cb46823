#include "needle_guidance/ros/rigid_planner_ros.h"

#include <cmath>

#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/params.h"

namespace needle_guidance {

RigidPlannerRos::RigidPlannerRos(ros::NodeHandle& /*nh*/, ros::NodeHandle& private_nh) {
  ROS_INFO("rigid_planner parameters:");
  const std::string scene_spec = ros_params::text(private_nh, "scene", "prostate_sagittal");
  rigid_planning::PlannerOptions options;
  if (scene::sceneKind(scene_spec) == "tissue_3d") {  // the 3-D mode: same ~plan service
    options.tolerance_m =
        ros_params::number(private_nh, "tolerance_m", options.tolerance_m, 0.0, 0.01,
                           "m (0 = the scene's needle.placement_tolerance)");
    planner3_ = std::make_unique<RigidPlanner3Ros>(private_nh, scene_spec, options.tolerance_m);
    return;
  }
  const scene::Scene scene = scene::loadSceneSpec(scene_spec);
  options.height_window_m =
      ros_params::number(private_nh, "height_window_m", options.height_window_m, 1e-5, 0.05, "m");
  options.height_tolerance_m = ros_params::number(private_nh, "height_tolerance_m",
                                                  options.height_tolerance_m, 1e-6, 0.01, "m");
  options.depth_step_m =
      ros_params::number(private_nh, "depth_step_m", options.depth_step_m, 1e-5, 0.005, "m");
  options.approach_step_m =
      ros_params::number(private_nh, "approach_step_m", options.approach_step_m, 0.0, 0.005, "m");
  options.approach_zone_m =
      ros_params::number(private_nh, "approach_zone_m", options.approach_zone_m, 0.0, 0.05, "m");
  options.velocity_m_s =
      ros_params::number(private_nh, "velocity_m_s", options.velocity_m_s, 1e-4, 0.1, "m/s");
  options.depth_margin_m =
      ros_params::number(private_nh, "depth_margin_m", options.depth_margin_m, 0.0, 0.05, "m");
  options.error_goal_m =
      ros_params::number(private_nh, "error_goal_m", options.error_goal_m, 0.0, 0.01, "m");
  options.secant_iterations = static_cast<int>(ros_params::number(
      private_nh, "secant_iterations", options.secant_iterations, 0, 20, "steps"));
  options.work_budget = ros_params::number(private_nh, "work_budget", options.work_budget, 0.0, 1e7,
                                           "solver work units (0 = none)");
  options.time_budget_s = ros_params::number(private_nh, "time_budget_s", options.time_budget_s,
                                             0.0, 600.0, "s (0 = none)");
  options.tolerance_m = ros_params::number(private_nh, "tolerance_m", options.tolerance_m, 0.0,
                                           0.01, "m (0 = the scene's needle.placement_tolerance)");
  options.verify = ros_params::number(private_nh, "verify", 1.0, 0.0, 1.0, "(0 or 1)") > 0.5;
  planner_ = std::make_unique<rigid_planning::RigidPlanner>(scene, options);
  plan_srv_ = private_nh.advertiseService("plan", &RigidPlannerRos::onPlan, this);
  ROS_INFO_STREAM("rigid_planner: ready on scene '" << scene.name << "'");
}

bool RigidPlannerRos::onPlan(PlanRigid::Request& req, PlanRigid::Response& res) {
  const geometry::Point2 target(req.target.x, req.target.y);
  const std::string mode = req.mode.empty() ? "full" : req.mode;
  if (mode != "full" && mode != "depth_only" && mode != "unplanned") {
    res.success = false;
    res.message = "mode '" + req.mode + "' is not one of full, depth_only, unplanned";
    return true;
  }
  const rigid_planning::RigidPlan plan = mode == "full"
                                             ? planner_->plan(target, last_height_offset_m_)
                                         : mode == "depth_only" ? planner_->planDepthOnly(target)
                                                                : planner_->unplanned(target);
  res.success = static_cast<bool>(plan);
  res.message = plan.message;
  // A refusal the physics explains is "unreachable", as in 3-D; the message keeps the detail.
  res.code = rigid_planning::isPhysicalRefusal(plan.code) ? "unreachable"
                                                          : rigid_planning::toString(plan.code);
  res.tolerance_m = planner_->tolerance();
  res.verified_error_m = NAN;
  if (!plan) {
    ROS_WARN_STREAM_NAMED("rigid_planner", "plan refused: " << plan.message);
    return true;
  }
  res.release = ros_conversions::toMessage(plan.release);
  res.predicted_implant = ros_conversions::toMessage(plan.predicted_implant);
  res.predicted_error_m = plan.predicted_error_m;
  // The scan at the target height (always the first one) also predicts the unplanned error.
  const rigid_planning::DepthScan& first = plan.scans.front();
  res.unplanned_error_m =
      first.height_m == target.y() ? (first.implantAt(target.x()) - target).norm() : -1.0;
  res.simulations = plan.simulations;
  res.planning_time_s = plan.seconds;
  res.unimodal = plan.unimodal;
  res.verified = plan.verified;
  res.verified_implant = ros_conversions::toMessage(plan.verified_implant);
  res.verified_error_m = plan.verified ? plan.verified_error_m : NAN;
  res.within_tolerance = plan.within_tolerance;
  res.verifications = plan.verifications;
  res.budget_expired = plan.budget_expired;
  if (mode == "full") {
    last_height_offset_m_ = plan.release.y() - target.y();
  }
  ROS_INFO_STREAM_NAMED("rigid_planner",
                        "plan for (" << target.x() << ", " << target.y() << ") m: release ("
                                     << plan.release.x() << ", " << plan.release.y()
                                     << ") m, predicted error " << 1e3 * plan.predicted_error_m
                                     << " mm, verified " << 1e3 * plan.verified_error_m << " mm, "
                                     << plan.simulations << " simulations, " << plan.seconds
                                     << " s");
  return true;
}

}  // namespace needle_guidance
