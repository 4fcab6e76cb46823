// steering_planner_3d (steering_planner_3d_ros.h).
#include "needle_guidance/ros/steering_planner_3d_ros.h"

#include <geometry_msgs/TransformStamped.h>

#include "needle_guidance/needle_model/scene_3d.h"
#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/conversions_3d.h"
#include "needle_guidance/ros/params.h"
#include "needle_guidance/steering_3d/closed_loop_3d.h"

namespace needle_guidance {

namespace sd = steering_3d;

SteeringPlanner3dRos::SteeringPlanner3dRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh) {
  namespace rp = ros_params;
  ROS_INFO("steering_planner_3d parameters:");
  const std::string scene_path = rp::text(private_nh, "scene", "", true);
  sd::PlannerParams3 params;
  params.time_budget_s = rp::number(private_nh, "time_budget_s", 0.03, 1e-3, 10.0, "s");
  params.entry_time_budget_s = rp::number(private_nh, "entry_time_budget_s", 1.0, 1e-3, 60.0, "s");
  params.max_plans = static_cast<int>(rp::integer(private_nh, "max_plans", 8, 1, 1000, "plans"));
  seed_ = static_cast<std::uint64_t>(rp::integer(private_nh, "seed", 1, 0, 1L << 40, ""));
  const std::string parent_frame = rp::text(private_nh, "scene_parent_frame", "");
  const double noise_scale = rp::number(private_nh, "noise_scale", 1.0, 0.0, 10.0, "x scene sigma");
  scene_ = std::make_unique<needle_model::Scene3d>(needle_model::loadScene3d(scene_path));
  world_ = std::make_unique<needle_model::CollisionWorld3>(scene_->collisionWorld());
  planner_ =
      std::make_unique<sd::Planner3>(*scene_, *world_, params, scene_->noise.scaled(noise_scale));
  control_pub_ = private_nh.advertise<SteeringControl3>("control", 10);
  plan_pub_ = private_nh.advertise<visualization_msgs::Marker>("plan", 1, true);
  scene_pub_ = private_nh.advertise<visualization_msgs::MarkerArray>("scene_markers", 1, true);
  scene_pub_.publish(ros_conversions::sceneToMarkers(*scene_, "scene"));
  if (!parent_frame.empty()) {  // rviz needs frame scene in tf; identity under parent_frame
    geometry_msgs::TransformStamped t;
    t.header.stamp = ros::Time::now();
    t.header.frame_id = parent_frame;
    t.child_frame_id = "scene";
    t.transform.rotation.w = 1.0;
    frame_broadcaster_.sendTransform(t);
  }
  tip_sub_ = nh.subscribe("tip", 10, &SteeringPlanner3dRos::onTip, this);
  plan_srv_ = private_nh.advertiseService("plan", &SteeringPlanner3dRos::onPlan, this);
  ROS_INFO_STREAM("steering_planner_3d: scene '" << scene_->name << "' ("
                                                 << scene_->obstacles.size() << " obstacles)");
}

void SteeringPlanner3dRos::onTip(const geometry_msgs::PoseWithCovarianceStampedConstPtr& msg) {
  SteeringControl3 out;
  out.header.stamp = msg->header.stamp;
  out.header.frame_id = "scene";
  needle_model::TipPose3 tip;
  const std::string refusal = ros_conversions::fromMessage(*msg, "scene", tip);
  if (!refusal.empty()) {
    out.status = "bad_input";
    out.message = refusal;
    ROS_WARN_STREAM_THROTTLE(1.0, "steering_planner_3d: refused a tip: " << refusal);
    control_pub_.publish(out);
    return;
  }
  sd::PlanReport report;
  const Result<sd::Plan3, sd::PlanStatus> plan =
      planner_->planFromTip(tip, sd::callSeed(seed_, ++tips_), &report);
  out.plan_seconds = report.seconds;
  out.nodes = report.nodes;
  if (!plan) {
    out.status = sd::toString(plan.status().code());
    out.message = plan.status().toString();
  } else {
    const needle_model::Control3& c = plan.value().controls.front();
    out.status = "ok";
    out.rotate_rad = c.rotate_rad;
    out.curvature_per_m = c.curvature_per_m;
    out.insertion_m = c.length_m;
    out.plan_length_m = plan.value().length_m;
    out.p_success = plan.value().p_success;
    const std::vector<needle_model::Control3> later(plan.value().controls.begin() + 1,
                                                    plan.value().controls.end());
    ros_conversions::controlsToArrays(later, out.next_rotate_rad, out.next_curvature_per_m,
                                      out.next_insertion_m);
    publishPlan(plan.value());
  }
  control_pub_.publish(out);
}

bool SteeringPlanner3dRos::onPlan(PlanSteering3::Request& req, PlanSteering3::Response& res) {
  sd::PlanReport report;
  const Result<sd::Plan3, sd::PlanStatus> plan = planner_->planFromEntry(req.seed, &report);
  res.seconds = report.seconds;
  res.success = static_cast<bool>(plan);
  res.status = plan ? "ok" : sd::toString(plan.status().code());
  if (!plan) {
    res.message = plan.status().toString();
    res.start.orientation.w = 1.0;
    return true;
  }
  res.start = ros_conversions::toMessage(plan.value().start);
  res.p_success = plan.value().p_success;
  res.length_m = plan.value().length_m;
  ros_conversions::controlsToArrays(plan.value().controls, res.rotate_rad, res.curvature_per_m,
                                    res.insertion_m);
  publishPlan(plan.value());
  return true;
}

void SteeringPlanner3dRos::publishPlan(const sd::Plan3& plan) {
  visualization_msgs::Marker m = ros_conversions::lineStrip(
      plan.points(), "scene", "plan", ros_conversions::colour(0.2, 0.6, 1.0, 1.0), 6e-4);
  m.header.stamp = ros::Time::now();
  plan_pub_.publish(m);
}

}  // namespace needle_guidance
