// ROS wrapper of the simulated insertion stage (node insertion_robot).
#pragma once

#include <actionlib/server/simple_action_server.h>
#include <ros/ros.h>
#include <std_srvs/Trigger.h>

#include <memory>
#include <string>

#include "needle_guidance/FlipBevelAction.h"
#include "needle_guidance/LinearMoveAction.h"
#include "needle_guidance/robot/insertion_stage.h"

namespace needle_guidance {

/// Owns the NodeHandles, reads and validates parameters once, runs the stage's control loop on
/// a timer and exposes CRTK-style topics, the motion actions and the e-stop services.
/// Throws std::runtime_error from the constructor on a missing or invalid parameter.
class InsertionRobotRos {
public:
  InsertionRobotRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);

private:
  using LinearMoveServer = actionlib::SimpleActionServer<LinearMoveAction>;
  using FlipBevelServer = actionlib::SimpleActionServer<FlipBevelAction>;
  /// Which action owns the running motion.
  enum class Owner { kNone, kHeight, kInsert, kRetract, kFlip };

  void onLinearGoal(Owner owner);
  void onFlipGoal();
  void onPreempt(Owner owner);
  void onControlTimer(const ros::TimerEvent& event);
  bool onEstop(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  bool onResetEstop(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  void finishActiveGoal(bool success, const std::string& message);
  void publishState(const ros::Time& stamp);
  LinearMoveServer& linearServer(Owner owner);

  ros::NodeHandle nh_;
  std::unique_ptr<robot::InsertionStage> stage_;
  std::unique_ptr<robot::JournalFile> journal_file_;
  Owner owner_ = Owner::kNone;
  ros::Time goal_start_;
  double goal_start_position_ = 0.0;
  std::string last_message_;

  ros::Publisher measured_js_pub_;
  ros::Publisher measured_cp_pub_;
  ros::Publisher operating_state_pub_;
  ros::ServiceServer estop_srv_;
  ros::ServiceServer reset_estop_srv_;
  std::unique_ptr<LinearMoveServer> height_server_;
  std::unique_ptr<LinearMoveServer> insert_server_;
  std::unique_ptr<LinearMoveServer> retract_server_;
  std::unique_ptr<FlipBevelServer> flip_server_;
  ros::Timer control_timer_;
  ros::Time last_step_;
  ros::Time last_publish_;
  double publish_period_s_ = 0.01;
};

}  // namespace needle_guidance
