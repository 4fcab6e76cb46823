// ROS wrapper of the simulated HDR remote afterloader (node afterloader).
#pragma once

#include <actionlib/server/action_server.h>
#include <ros/ros.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>
#include <tf2_ros/transform_broadcaster.h>

#include <memory>
#include <optional>
#include <string>

#include "needle_guidance/DeliverAction.h"
#include "needle_guidance/SetChannelObstruction.h"
#include "needle_guidance/delivery/afterloader.h"

namespace needle_guidance {

/// Reads parameters once (throws std::runtime_error on a bad one), steps the device on a wall
/// timer (device time = wall time x ~time_scale), serves the `deliver` action (one goal at a
/// time: a second is rejected; cancel = abort), pause / resume, the interlock inputs, and
/// publishes state, journal lines, the source marker and tf.
class AfterloaderRos {
public:
  AfterloaderRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);

private:
  using Server = actionlib::ActionServer<DeliverAction>;
  void onGoal(Server::GoalHandle goal);
  void onCancel(Server::GoalHandle goal);
  void onTimer(const ros::WallTimerEvent& event);
  bool onPause(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  bool onResume(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  bool onDoor(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res);
  bool onObstruction(SetChannelObstruction::Request& req, SetChannelObstruction::Response& res);
  DeliverResult result(const std::string& status, const std::string& message) const;
  void publish(bool feedback);

  std::unique_ptr<delivery::Afterloader> device_;
  std::string frame_id_;
  double time_scale_ = 1.0;
  double publish_period_s_ = 0.05;
  std::unique_ptr<Server> server_;
  std::optional<Server::GoalHandle> goal_;
  bool cancelling_ = false;
  double goal_start_time_s_ = 0.0;
  ros::WallTime last_step_;
  ros::WallTime last_publish_;
  ros::Publisher state_pub_, journal_pub_, marker_pub_;
  ros::ServiceServer pause_srv_, resume_srv_, door_srv_, obstruction_srv_;
  tf2_ros::TransformBroadcaster tf_;
  ros::WallTimer timer_;
};

}  // namespace needle_guidance
