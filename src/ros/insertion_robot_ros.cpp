#include "needle_guidance/ros/insertion_robot_ros.h"

#include <cstdlib>

#include "needle_guidance/OperatingState.h"
#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/params.h"
#include "needle_guidance/scene/scene.h"

namespace needle_guidance {
namespace {

using robot::StageJoint;

}  // namespace

InsertionRobotRos::InsertionRobotRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh) : nh_(nh) {
  ROS_INFO("insertion_robot parameters:");
  const std::string scene_spec = ros_params::text(private_nh, "scene", "prostate_sagittal");
  const std::string description_param = ros_params::text(private_nh, "robot_description_param",
                                                         "robot_description");
  std::string urdf_xml;
  if (!nh.getParam(description_param, urdf_xml)) {
    throw std::runtime_error("parameter '" + nh.resolveName(description_param) +
                             "' (the stage URDF) is not set");
  }
  const robot::StageLimits limits = robot::parseStageLimits(urdf_xml);
  const scene::Scene scene = scene::loadSceneSpec(scene_spec);
  const robot::SceneLimits scene_limits{scene.needle.min_height_m, scene.needle.max_height_m,
                                        scene.needle.max_depth_m, scene.workspace_min.x()};
  const double control_rate_hz = ros_params::number(private_nh, "control_rate_hz", 500.0, 10.0,
                                                    5000.0, "Hz");
  const double publish_rate_hz = ros_params::number(private_nh, "publish_rate_hz", 100.0, 1.0,
                                                    control_rate_hz, "Hz");
  const auto& h = limits[StageJoint::kHeight];
  const auto& d = limits[StageJoint::kDepth];
  const auto& b = limits[StageJoint::kBevel];
  const double mid_height = 0.5 * (scene_limits.min_height_m + scene_limits.max_height_m);
  const std::array<double, robot::kStageJointCount> initial{
      ros_params::number(private_nh, "initial_height_m", mid_height, h.lower, h.upper, "m"),
      ros_params::number(private_nh, "initial_depth_m", scene_limits.entry_x_m - 0.01, d.lower,
                         scene_limits.entry_x_m, "m"),
      ros_params::number(private_nh, "initial_bevel_rad", b.lower, b.lower, b.upper, "rad")};
  const std::string journal_path = ros_params::rosHomePath(
      ros_params::text(private_nh, "journal_file", "insertion_robot_journal.csv"));
  publish_period_s_ = 1.0 / publish_rate_hz;

  stage_ = std::make_unique<robot::InsertionStage>(limits, scene_limits, initial);
  if (!journal_path.empty()) {
    journal_file_ = std::make_unique<robot::JournalFile>(journal_path);
    stage_->setJournalSink([this](const robot::JournalEntry& e) { journal_file_->write(e); });
    ROS_INFO_STREAM("insertion_robot: journal appended to " << journal_path);
  }

  ros::NodeHandle robot_nh(private_nh);
  measured_js_pub_ = robot_nh.advertise<sensor_msgs::JointState>("measured_js", 10);
  measured_cp_pub_ = robot_nh.advertise<geometry_msgs::PoseStamped>("measured_cp", 10);
  operating_state_pub_ = robot_nh.advertise<OperatingState>("operating_state", 1, true);
  estop_srv_ = robot_nh.advertiseService("estop", &InsertionRobotRos::onEstop, this);
  reset_estop_srv_ = robot_nh.advertiseService("reset_estop", &InsertionRobotRos::onResetEstop, this);

  auto make_linear = [&](const std::string& name, Owner owner) {
    auto server = std::make_unique<LinearMoveServer>(robot_nh, name, false);
    server->registerGoalCallback([this, owner] { onLinearGoal(owner); });
    server->registerPreemptCallback([this, owner] { onPreempt(owner); });
    server->start();
    return server;
  };
  height_server_ = make_linear("move_to_height", Owner::kHeight);
  insert_server_ = make_linear("insert", Owner::kInsert);
  retract_server_ = make_linear("retract", Owner::kRetract);
  flip_server_ = std::make_unique<FlipBevelServer>(robot_nh, "flip_bevel", false);
  flip_server_->registerGoalCallback([this] { onFlipGoal(); });
  flip_server_->registerPreemptCallback([this] { onPreempt(Owner::kFlip); });
  flip_server_->start();

  last_step_ = ros::Time::now();
  last_publish_ = last_step_;
  publishState(last_step_);
  control_timer_ = nh.createTimer(ros::Duration(1.0 / control_rate_hz),
                                  &InsertionRobotRos::onControlTimer, this);
  ROS_INFO_STREAM("insertion_robot: ready on scene '" << scene.name << "', needle "
                                                      << limits.needle_length_m << " m");
}

InsertionRobotRos::LinearMoveServer& InsertionRobotRos::linearServer(Owner owner) {
  switch (owner) {
    case Owner::kHeight:
      return *height_server_;
    case Owner::kInsert:
      return *insert_server_;
    default:
      return *retract_server_;
  }
}

void InsertionRobotRos::onLinearGoal(Owner owner) {
  LinearMoveServer& server = linearServer(owner);
  if (owner_ == owner) {
    stage_->cancel();  // the new goal replaces this server's running one
    owner_ = Owner::kNone;
  }
  const auto goal = server.acceptNewGoal();
  const StageJoint joint = owner == Owner::kHeight ? StageJoint::kHeight : StageJoint::kDepth;
  const double current = stage_->state().position[static_cast<std::size_t>(joint)];
  robot::CommandStatus status = robot::CommandStatus::accepted();
  if (owner == Owner::kInsert && goal->target_m < current) {
    status = robot::CommandStatus::refused("insert command refused: target depth " +
                                           std::to_string(goal->target_m) +
                                           " m is shallower than the current depth " +
                                           std::to_string(current) + " m; use retract");
  } else if (owner == Owner::kRetract && goal->target_m > current) {
    status = robot::CommandStatus::refused("retract command refused: target depth " +
                                           std::to_string(goal->target_m) +
                                           " m is deeper than the current depth " +
                                           std::to_string(current) + " m; use insert");
  } else {
    status = stage_->command(joint, goal->target_m, goal->velocity_m_s);
  }
  if (!status) {
    LinearMoveResult result;
    result.success = false;
    result.message = status.toString();
    result.reached_m = current;
    last_message_ = status.toString();
    ROS_WARN_STREAM_NAMED("insertion_robot", status.toString());
    server.setAborted(result, result.message);
    publishState(ros::Time::now());
    return;
  }
  owner_ = owner;
  goal_start_ = ros::Time::now();
  goal_start_position_ = current;
  if (!stage_->busy()) {
    finishActiveGoal(true, "already at target");
  }
}

void InsertionRobotRos::onFlipGoal() {
  if (owner_ == Owner::kFlip) {
    stage_->cancel();
    owner_ = Owner::kNone;
  }
  const auto goal = flip_server_->acceptNewGoal();
  const robot::CommandStatus status = stage_->flipBevel(goal->velocity_rad_s);
  if (!status) {
    FlipBevelResult result;
    result.success = false;
    result.message = status.toString();
    result.bevel_rad = stage_->state().bevel_rad();
    last_message_ = status.toString();
    ROS_WARN_STREAM_NAMED("insertion_robot", status.toString());
    flip_server_->setAborted(result, result.message);
    return;
  }
  owner_ = Owner::kFlip;
  goal_start_ = ros::Time::now();
  goal_start_position_ = stage_->state().bevel_rad();
}

void InsertionRobotRos::onPreempt(Owner owner) {
  if (owner_ != owner) {
    return;
  }
  stage_->cancel();
  owner_ = Owner::kNone;
  last_message_ = "goal preempted; motion stopped";
  if (owner == Owner::kFlip) {
    FlipBevelResult result;
    result.success = false;
    result.message = last_message_;
    result.bevel_rad = stage_->state().bevel_rad();
    flip_server_->setPreempted(result, result.message);
  } else {
    LinearMoveResult result;
    result.success = false;
    result.message = last_message_;
    const StageJoint joint = owner == Owner::kHeight ? StageJoint::kHeight : StageJoint::kDepth;
    result.reached_m = stage_->state().position[static_cast<std::size_t>(joint)];
    linearServer(owner).setPreempted(result, result.message);
  }
}

void InsertionRobotRos::finishActiveGoal(bool success, const std::string& message) {
  const Owner owner = owner_;
  owner_ = Owner::kNone;
  last_message_ = message;
  const ros::Time now = ros::Time::now();
  if (owner == Owner::kFlip) {
    FlipBevelResult result;
    result.success = success;
    result.message = message;
    result.bevel_rad = stage_->state().bevel_rad();
    success ? flip_server_->setSucceeded(result, message) : flip_server_->setAborted(result, message);
    return;
  }
  if (owner == Owner::kNone) {
    return;
  }
  const StageJoint joint = owner == Owner::kHeight ? StageJoint::kHeight : StageJoint::kDepth;
  LinearMoveResult result;
  result.success = success;
  result.message = message;
  result.reached_m = stage_->state().position[static_cast<std::size_t>(joint)];
  result.duration_s = (now - goal_start_).toSec();
  result.mean_velocity_m_s =
      result.duration_s > 0.0 ? std::abs(result.reached_m - goal_start_position_) / result.duration_s
                              : 0.0;
  LinearMoveServer& server = linearServer(owner);
  success ? server.setSucceeded(result, message) : server.setAborted(result, message);
}

void InsertionRobotRos::onControlTimer(const ros::TimerEvent& /*event*/) {
  const ros::Time now = ros::Time::now();
  const double dt_s = std::max(0.0, (now - last_step_).toSec());
  last_step_ = now;
  stage_->step(dt_s);
  if (owner_ != Owner::kNone && !stage_->busy()) {
    finishActiveGoal(true, "target reached");
  }
  if ((now - last_publish_).toSec() >= publish_period_s_ - 1e-6) {
    last_publish_ = now;
    publishState(now);
  }
}

void InsertionRobotRos::publishState(const ros::Time& stamp) {
  const robot::StageState& state = stage_->state();
  sensor_msgs::JointState js;
  ros_conversions::toMessage(state, js);
  js.header.stamp = stamp;
  measured_js_pub_.publish(js);

  geometry_msgs::PoseStamped cp;
  ros_conversions::tipPoseToMessage(state, cp);
  cp.header.stamp = stamp;
  measured_cp_pub_.publish(cp);

  OperatingState op;
  op.header.stamp = stamp;
  op.state = robot::toString(stage_->operatingState());
  op.is_homed = true;
  op.is_busy = stage_->busy();
  const auto joint = stage_->activeJoint();
  op.active_joint = joint ? robot::jointName(*joint) : "";
  op.last_message = last_message_;
  operating_state_pub_.publish(op);

  if (owner_ == Owner::kFlip) {
    FlipBevelFeedback fb;
    fb.bevel_rad = state.bevel_rad();
    flip_server_->publishFeedback(fb);
  } else if (owner_ != Owner::kNone) {
    const StageJoint j = owner_ == Owner::kHeight ? StageJoint::kHeight : StageJoint::kDepth;
    LinearMoveFeedback fb;
    fb.position_m = state.position[static_cast<std::size_t>(j)];
    fb.velocity_m_s = state.velocity[static_cast<std::size_t>(j)];
    fb.tip = ros_conversions::toMessage(stage_->tipPosition());
    linearServer(owner_).publishFeedback(fb);
  }
}

bool InsertionRobotRos::onEstop(std_srvs::Trigger::Request& /*req*/,
                                std_srvs::Trigger::Response& res) {
  stage_->estop("e-stop service called");
  ROS_ERROR_NAMED("insertion_robot", "EMERGENCY STOP: all motion stopped");
  if (owner_ != Owner::kNone) {
    finishActiveGoal(false, "emergency stop: motion stopped");
  }
  last_message_ = "emergency stop active";
  publishState(ros::Time::now());
  res.success = true;
  res.message = "emergency stop active; call reset_estop to enable";
  return true;
}

bool InsertionRobotRos::onResetEstop(std_srvs::Trigger::Request& /*req*/,
                                     std_srvs::Trigger::Response& res) {
  const robot::CommandStatus status = stage_->resetEstop();
  res.success = static_cast<bool>(status);
  res.message = status.toString();
  last_message_ = status ? "enabled" : status.toString();
  publishState(ros::Time::now());
  return true;
}

}  // namespace needle_guidance
