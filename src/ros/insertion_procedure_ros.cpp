#include "needle_guidance/ros/insertion_procedure_ros.h"

#include <actionlib/client/simple_action_client.h>
#include <geometry_msgs/PoseStamped.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <mutex>
#include <sstream>

#include "needle_guidance/LinearMoveAction.h"
#include "needle_guidance/ros/params.h"
#include "needle_guidance/scene/scene.h"

namespace needle_guidance {
namespace {

using LinearMoveClient = actionlib::SimpleActionClient<LinearMoveAction>;

struct MoveOutcome {
  bool ok = false;
  LinearMoveResult result;
  std::string state;
};

/// Sends a goal and waits for it with a timeout of twice the nominal duration plus a margin.
MoveOutcome move(LinearMoveClient& client, double target_m, double velocity_m_s, double from_m) {
  LinearMoveGoal goal;
  goal.target_m = target_m;
  goal.velocity_m_s = velocity_m_s;
  const double nominal_s = std::abs(target_m - from_m) / velocity_m_s;
  const actionlib::SimpleClientGoalState state =
      client.sendGoalAndWait(goal, ros::Duration(2.0 * nominal_s + 5.0), ros::Duration(1.0));
  MoveOutcome outcome;
  outcome.state = state.toString();
  outcome.ok = state == actionlib::SimpleClientGoalState::SUCCEEDED;
  if (client.getResult()) {
    outcome.result = *client.getResult();
  }
  if (!outcome.ok) {
    ROS_ERROR_STREAM("insertion_procedure: move to " << target_m << " m ended " << outcome.state
                                                     << ": " << outcome.result.message);
  }
  return outcome;
}

}  // namespace

InsertionProcedureRos::InsertionProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh)
    : nh_(nh) {
  ROS_INFO("insertion_procedure parameters:");
  scene_spec_ = ros_params::text(private_nh, "scene", "prostate_sagittal");
  const scene::Scene scene = scene::loadSceneSpec(scene_spec_);
  robot_ns_ = ros_params::text(private_nh, "robot", "insertion_robot");
  report_dir_ = ros_params::text(private_nh, "report_dir", "", true);
  insertion_velocity_m_s_ = ros_params::number(private_nh, "insertion_velocity_m_s",
                                               scene.needle.insertion_velocity_m_s, 1e-4, 1.0, "m/s");
  retract_velocity_m_s_ = ros_params::number(private_nh, "retract_velocity_m_s",
                                             2.0 * insertion_velocity_m_s_, 1e-4, 1.0, "m/s");
  height_velocity_m_s_ = ros_params::number(private_nh, "height_velocity_m_s", 0.01, 1e-4, 1.0, "m/s");
  retract_depth_m_ = ros_params::number(private_nh, "retract_depth_m", -0.005, -1.0, 0.0, "m");
  depth_tolerance_m_ = ros_params::number(private_nh, "depth_tolerance_m", 1e-6, 0.0, 0.01, "m");
  velocity_tolerance_ = ros_params::number(private_nh, "velocity_tolerance", 0.05, 0.0, 1.0, "1");
  max_targets_ = static_cast<int>(ros_params::number(private_nh, "max_targets", 0, 0, 1000, "targets"));
}

bool InsertionProcedureRos::run() {
  const scene::Scene scene = scene::loadSceneSpec(scene_spec_);
  LinearMoveClient height_client(nh_, robot_ns_ + "/move_to_height", true);
  LinearMoveClient insert_client(nh_, robot_ns_ + "/insert", true);
  LinearMoveClient retract_client(nh_, robot_ns_ + "/retract", true);
  for (LinearMoveClient* client : {&height_client, &insert_client, &retract_client}) {
    if (!client->waitForServer(ros::Duration(30.0))) {
      ROS_FATAL("insertion_procedure: robot action servers did not come up in 30 s");
      return false;
    }
  }
  std::mutex tip_mutex;
  geometry_msgs::PoseStamped last_tip;
  ros::Subscriber tip_sub = nh_.subscribe<geometry_msgs::PoseStamped>(
      robot_ns_ + "/measured_cp", 10, [&](const geometry_msgs::PoseStampedConstPtr& msg) {
        std::lock_guard<std::mutex> lock(tip_mutex);
        last_tip = *msg;
      });

  report::Table moves({"target", "target_x_mm", "target_y_mm", "height_mm", "depth_reached_mm",
                       "depth_error_mm", "tip_error_mm", "insert_s", "insert_velocity_mm_s",
                       "velocity_error_pct", "retract_s", "status"},
                      6);
  const ros::WallTime start = ros::WallTime::now();
  bool all_ok = true;
  double max_depth_error_mm = 0.0;
  double max_velocity_error_pct = 0.0;
  double max_tip_error_mm = 0.0;
  const std::size_t count = max_targets_ > 0
                                ? std::min<std::size_t>(scene.targets.size(), max_targets_)
                                : scene.targets.size();
  double depth_now = retract_depth_m_;
  for (std::size_t i = 0; i < count && ros::ok(); ++i) {
    const scene::Target& target = scene.targets[i];
    const double height = target.position.y();
    const double depth = target.position.x();
    std::string status = "ok";
    const MoveOutcome h = move(height_client, height, height_velocity_m_s_, 0.0);
    const MoveOutcome in = h.ok ? move(insert_client, depth, insertion_velocity_m_s_, depth_now)
                                : MoveOutcome{};
    ros::Duration(0.05).sleep();  // one more measured_cp at rest
    geometry::Point2 tip(NAN, NAN);
    {
      std::lock_guard<std::mutex> lock(tip_mutex);
      tip = {last_tip.pose.position.x, last_tip.pose.position.y};
    }
    const MoveOutcome out = move(retract_client, retract_depth_m_, retract_velocity_m_s_, depth);
    if (!h.ok || !in.ok || !out.ok) {
      status = !h.ok ? "height " + h.state : !in.ok ? "insert " + in.state : "retract " + out.state;
    }
    const double depth_error_mm = 1e3 * std::abs(in.result.reached_m - depth);
    const double tip_error_mm = 1e3 * (tip - target.position).norm();
    const double velocity_error_pct =
        100.0 * std::abs(in.result.mean_velocity_m_s - insertion_velocity_m_s_) / insertion_velocity_m_s_;
    if (status == "ok" && (depth_error_mm > 1e3 * depth_tolerance_m_ ||
                           velocity_error_pct > 100.0 * velocity_tolerance_)) {
      status = "out of tolerance";
    }
    all_ok = all_ok && status == "ok";
    max_depth_error_mm = std::max(max_depth_error_mm, depth_error_mm);
    max_velocity_error_pct = std::max(max_velocity_error_pct, velocity_error_pct);
    max_tip_error_mm = std::max(max_tip_error_mm, std::isfinite(tip_error_mm) ? tip_error_mm : 1e9);
    moves.addRow({target.name, 1e3 * depth, 1e3 * height, 1e3 * height, 1e3 * in.result.reached_m,
                  depth_error_mm, tip_error_mm, in.result.duration_s,
                  1e3 * in.result.mean_velocity_m_s, velocity_error_pct, out.result.duration_s,
                  status});
    depth_now = out.ok ? retract_depth_m_ : depth;
    ROS_INFO_STREAM("insertion_procedure: " << target.name << " " << status << " (depth error "
                                            << depth_error_mm << " mm, " << in.result.duration_s
                                            << " s)");
  }
  const double total_s = (ros::WallTime::now() - start).toSec();
  all_ok = all_ok && moves.rowCount() == count;

  std::ostringstream json;
  json.precision(9);
  json << "{\n  \"procedure\": \"robot_insertion\",\n  \"scene\": \"" << scene.name
       << "\",\n  \"success\": " << (all_ok ? "true" : "false") << ",\n  \"targets\": " << count
       << ",\n  \"max_depth_error_mm\": " << max_depth_error_mm
       << ",\n  \"max_tip_error_mm\": " << max_tip_error_mm
       << ",\n  \"max_velocity_error_pct\": " << max_velocity_error_pct
       << ",\n  \"insertion_velocity_mm_s\": " << 1e3 * insertion_velocity_m_s_
       << ",\n  \"wall_time_s\": " << total_s << "\n}\n";
  std::ostringstream md;
  md << "# Robot insertion procedure — scene `" << scene.name << "`\n\n"
     << "Each target: move to its height, insert to its depth at "
     << 1e3 * insertion_velocity_m_s_ << " mm/s, retract to " << 1e3 * retract_depth_m_
     << " mm. Rigid needle, no tissue model: tip error is the robot's positioning error.\n\n"
     << moves.toMarkdown() << "\nResult: " << (all_ok ? "all moves succeeded" : "FAILED")
     << ", wall time " << total_s << " s.\n";
  moves.writeCsv(report_dir_ + "/moves.csv");
  report::writeTextFile(report_dir_ + "/summary.json", json.str());
  report::writeTextFile(report_dir_ + "/summary.md", md.str());
  std::cout << "\n== Robot insertion on scene '" << scene.name << "' ==\n"
            << moves.toText() << (all_ok ? "PASS" : "FAIL") << ": " << count
            << " targets, max depth error " << max_depth_error_mm << " mm, max velocity error "
            << max_velocity_error_pct << " %, " << total_s << " s; report in " << report_dir_
            << "\n"
            << std::flush;
  return all_ok;
}

}  // namespace needle_guidance
