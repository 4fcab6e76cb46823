#include "needle_guidance/ros/steerable_procedure_ros.h"
#include "needle_guidance/math.h"

#include <actionlib/client/simple_action_client.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <functional>
#include <iostream>
#include <memory>
#include <mutex>
#include <optional>
#include <vector>

#include "needle_guidance/BestStart.h"
#include "needle_guidance/FlipBevelAction.h"
#include "needle_guidance/LinearMoveAction.h"
#include "needle_guidance/NeedleTip.h"
#include "needle_guidance/SetEntryPose.h"
#include "needle_guidance/SteeringControl.h"
#include "needle_guidance/report/output_path.h"
#include "needle_guidance/ros/latest.h"
#include "needle_guidance/ros/node_supervisor.h"
#include "needle_guidance/ros/params.h"
#include "needle_guidance/ros/run_goal.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/adaptive_policy.h"
#include "needle_guidance/steering/model_selection.h"

namespace needle_guidance {
namespace {

constexpr double kMmPerM = 1e3;
constexpr double kDegPerRad = 180.0 / kPi;

using LinearMoveClient = actionlib::SimpleActionClient<LinearMoveAction>;
using FlipBevelClient = actionlib::SimpleActionClient<FlipBevelAction>;

steering::TipPose toPose(const NeedleTip& tip) {
  steering::TipPose pose;
  pose.p_SceneTip = steering::Point2(tip.pose.x, tip.pose.y);
  pose.theta_rad = tip.pose.theta;
  pose.bevel = steering::bevelFromString(tip.bevel).value_or(steering::Bevel::kLeft);
  return pose;
}

procedures::SteerableTip toTip(const NeedleTip& tip) {
  return {toPose(tip), tip.inserted_length_m, tip.source, tip.confident != 0};
}

/// The robot, the policy (and with images the imager and tracker) over ROS, as the trial loop's
/// devices: decode the messages, classify the robot's refusals, watch the nodes.
class RosSteerableDevices : public procedures::SteerableDevices {
public:
  RosSteerableDevices(ros::NodeHandle& nh, const SteerableProcedureRos::Settings& s)
      : nh_(nh),
        s_(s),
        insert_(nh, s.robot_ns + "/insert", true),
        retract_(nh, s.robot_ns + "/retract", true),
        flip_(nh, s.robot_ns + "/flip_bevel", true),
        set_entry_(nh.serviceClient<SetEntryPose>(s.robot_ns + "/set_entry_pose")),
        start_(ros::WallTime::now()) {
    tip_sub_ = nh.subscribe<NeedleTip>(s.robot_ns + "/measured_tip", 100,
                                       [this](const NeedleTipConstPtr& m) { tips_.set(*m); });
    control_sub_ = nh.subscribe<SteeringControl>(
        s.policy_ns + "/control", 100,
        [this](const SteeringControlConstPtr& m) { controls_.set(*m); });
  }

  /// Waits for the robot's actions and services (false after 60 s).
  bool waitForRobot() {
    const ros::Duration wait_up(60.0);
    return insert_.waitForServer(wait_up) && retract_.waitForServer(wait_up) &&
           flip_.waitForServer(wait_up) && set_entry_.waitForExistence(wait_up);
  }
  /// From here on every node the run depends on is watched; a death ends the run (no more trials
  /// waiting out their timeouts), and the report names the node.
  void supervise(const std::vector<std::string>& nodes) {
    supervisor_ = std::make_unique<NodeSupervisor>(nh_, nodes);
    const auto dead = [this] { return supervisor_->death().has_value(); };
    tips_.setAbort(dead);
    controls_.setAbort(dead);
  }

  bool placeAtEntry(const steering::TipPose& start, std::uint64_t seed, bool reseed,
                    std::string& why_not) override {
    NeedleTip tip;
    if (!tips_.waitFor(ros::Time(0), s_.timeout_s, tip)) {
      why_not = "no measured tip";
      return false;
    }
    if (tip.inserted_length_m > 0.0 && !move(retract_, 0.0, s_.retract_velocity_m_s, why_not)) {
      why_not = "retract: " + why_not;
      return false;
    }
    SetEntryPose entry;
    entry.request.height_m = start.p_SceneTip.y();
    entry.request.angle_rad = start.theta_rad;
    entry.request.bevel = steering::toString(start.bevel);
    entry.request.reseed = reseed;
    entry.request.seed = seed;
    if (!set_entry_.call(entry) || !entry.response.success) {
      why_not = "set_entry_pose: " + entry.response.message;
      return false;
    }
    tips_.startRecording();
    since_ = ros::Time::now();
    return true;
  }

  std::optional<procedures::SteerableTip> tip(std::string& why_not) override {
    NeedleTip tip;
    if (!tips_.waitFor(since_, s_.timeout_s, tip)) {
      why_not = "no measured tip within " + std::to_string(s_.timeout_s) + " s";
      return std::nullopt;
    }
    return toTip(tip);
  }

  /// The policy's answer to a tip measured after the motion ended; with image feedback, waits up
  /// to max_unconfident_controls more frames for one the tracker is confident of.
  std::optional<procedures::PolicyAnswer> control(std::string& why_not) override {
    SteeringControl control;
    bool have = false;
    ros::Time after = since_;
    for (int unconfident = 0; controls_.waitFor(after, s_.timeout_s, control); ++unconfident) {
      have = true;
      if (control.tip_confident || unconfident >= s_.max_unconfident) {
        break;
      }
      after = control.header.stamp + ros::Duration(0, 1);
    }
    if (!have) {
      why_not =
          "no control from " + s_.policy_ns + " within " + std::to_string(s_.timeout_s) + " s";
      return std::nullopt;
    }
    procedures::PolicyAnswer answer;
    // The statuses with a control to act on; any other (invalid_tip: the pose was not finite,
    // or one this procedure does not know) ends the trial.
    answer.usable = control.status == "ok" || control.status == "in_target" ||
                    control.status == "in_obstacle" || control.status == "outside_grid";
    answer.status = control.status;
    answer.control =
        control.control == "flip" ? steering::Control::kFlip : steering::Control::kInsert;
    answer.probability_of_success = control.probability_of_success;
    answer.looked_up.p_SceneTip = steering::Point2(control.tip.x, control.tip.y);
    answer.looked_up.theta_rad = control.tip.theta;
    answer.source = control.tip_source;
    answer.confident = control.tip_confident != 0;
    answer.sigma_insert_rad = control.sigma_insert_rad;
    answer.sigma_flip_rad = control.sigma_flip_rad;
    return answer;
  }

  bool flip(std::string& why_not) override {
    FlipBevelGoal goal;
    goal.velocity_rad_s = s_.flip_velocity_rad_s;
    return runGoal(flip_, goal, why_not);
  }

  procedures::StepEnd insertTo(double length_m, std::string& message) override {
    const bool moved = move(insert_, length_m, s_.insertion_velocity_m_s, message);
    since_ = ros::Time::now();
    if (moved) {
      return procedures::StepEnd::kMoved;
    }
    // The robot's refusal, by its message: the world stopped the needle, or the joint's limit.
    if (message.find("workspace") != std::string::npos) {
      return procedures::StepEnd::kLeftWorkspace;
    }
    if (message.find("obstacle") != std::string::npos) {
      return procedures::StepEnd::kObstacle;
    }
    if (message.find("outside the joint limits") != std::string::npos) {
      return procedures::StepEnd::kJointLimit;
    }
    return procedures::StepEnd::kFailed;
  }

  std::vector<procedures::SteerableTip> takeSamples() override {
    std::vector<procedures::SteerableTip> out;
    for (const NeedleTip& m : tips_.stopRecording()) {
      out.push_back(toTip(m));
    }
    return out;
  }

  /// Checks at once as well as on the supervisor's timer: a trial that fails on a dead device
  /// ends in milliseconds, and the next ones must not run before the timer's next check.
  std::optional<procedures::Fault> fault() override {
    if (!supervisor_) {
      return std::nullopt;
    }
    if (!supervisor_->death()) {
      supervisor_->checkNow();
    }
    return supervisor_->confirmedFault(start_);
  }

  /// Leaves the needle out of the tissue: retracts if the robot lives, else nothing can move it.
  std::string leaveSafe() override {
    tips_.setAbort(nullptr);
    const std::string robot = nh_.resolveName(s_.robot_ns, false);
    if (!NodeSupervisor::ping(robot, 0.5).empty()) {
      return "none possible: the robot node " + robot + " does not answer";
    }
    NeedleTip tip;
    if (!tips_.waitFor(ros::Time(0), 1.0, tip) || tip.inserted_length_m <= 0.0) {
      return "";
    }
    std::string message;
    supervised_ = false;
    return move(retract_, 0.0, s_.retract_velocity_m_s, message) ? "needle retracted"
                                                                 : "retraction failed: " + message;
  }

  void progress(const std::string& line) override {
    ROS_INFO_STREAM("steerable_procedure: " << line);
  }

private:
  bool move(LinearMoveClient& client, double target_m, double velocity, std::string& message) {
    LinearMoveGoal goal;
    goal.target_m = target_m;
    goal.velocity_m_s = velocity;
    return runGoal(client, goal, message);
  }

  template <class Client, class Goal>
  bool runGoal(Client& client, const Goal& goal, std::string& message) {
    return needle_guidance::runGoal(
        client, goal, s_.timeout_s,
        [this]() -> std::optional<std::string> {
          if (supervised_ && supervisor_ && supervisor_->death())
            return supervisor_->death()->toString();
          return std::nullopt;
        },
        message);
  }

  ros::NodeHandle nh_;
  SteerableProcedureRos::Settings s_;
  LinearMoveClient insert_, retract_;
  FlipBevelClient flip_;
  ros::ServiceClient set_entry_;
  ros::Subscriber tip_sub_, control_sub_;
  Latest<NeedleTip> tips_;
  Latest<SteeringControl> controls_;
  std::unique_ptr<NodeSupervisor> supervisor_;
  bool supervised_ = true;
  ros::Time since_;
  ros::WallTime start_;
};

}  // namespace

SteerableProcedureRos::SteerableProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh)
    : nh_(nh) {
  ROS_INFO("steerable_procedure parameters:");
  s_.scene_spec = ros_params::text(private_nh, "scene", "steering_workspace");
  s_.target = ros_params::text(private_nh, "target", "");
  s_.robot_ns = ros_params::text(private_nh, "robot", "insertion_robot");
  s_.policy_ns = ros_params::text(private_nh, "policy", "steering_policy");
  s_.report_dir = ros_params::text(private_nh, "report_dir", "", true);
  // Refuses a system folder or someone else's non-empty folder before anything runs.
  report::prepareReportDir(s_.report_dir, private_nh.resolveName("report_dir"),
                           ros_params::flag(private_nh, "allow_system_paths", false));
  s_.table_dir =
      ros_params::rosHomePath(ros_params::text(private_nh, "table_dir", "steering_tables"));
  s_.trials.trials =
      static_cast<int>(ros_params::integer(private_nh, "trials", 20, 1, 100000, "trials"));
  s_.trials.max_steps =
      static_cast<int>(ros_params::integer(private_nh, "max_steps", 40, 1, 1000, "steps"));
  s_.insertion_velocity_m_s =
      ros_params::number(private_nh, "insertion_velocity_m_s", 0.05, 1e-4, 1.0, "m/s");
  s_.retract_velocity_m_s =
      ros_params::number(private_nh, "retract_velocity_m_s", 0.05, 1e-4, 1.0, "m/s");
  s_.flip_velocity_rad_s =
      ros_params::number(private_nh, "flip_velocity_rad_s", 2.0 * kPi, 1e-3, 100.0, "rad/s");
  s_.timeout_s = ros_params::number(private_nh, "timeout_s", 10.0, 0.1, 600.0, "s");
  s_.policy_wait_s = ros_params::number(private_nh, "policy_wait_s", 600.0, 1.0, 7200.0, "s");
  s_.trials.seed =
      ros_params::integer(private_nh, "seed", 1, -1, 1L << 40, "(-1 = the robot's stream)");
  s_.max_unconfident = static_cast<int>(
      ros_params::integer(private_nh, "max_unconfident_controls", 10, 0, 1000, "controls"));
  s_.trials.feedback = ros_params::text(private_nh, "feedback", "ground_truth");
  // The nodes the run depends on (the launch file adds imager and tip_tracker with images).
  const std::string watch =
      ros_params::text(private_nh, "watch_nodes", s_.robot_ns + "," + s_.policy_ns);
  for (std::size_t a = 0; a < watch.size();) {
    const std::size_t b = std::min(watch.find(',', a), watch.size());
    if (b > a)
      s_.watch_nodes.push_back(watch.substr(a, b - a));
    a = b + 1;
  }
  // Fail now, not after the robot has moved, if the scene cannot be steered.
  steering::problemFromScene(scene::loadSceneSpec(s_.scene_spec), s_.target);
}

bool SteerableProcedureRos::run() {
  const auto wall_start = std::chrono::steady_clock::now();
  const scene::Scene scene = scene::loadSceneSpec(s_.scene_spec);
  const steering::SteeringProblem problem = steering::problemFromScene(scene, s_.target);
  RosSteerableDevices devices(nh_, s_);
  ros::ServiceClient best_start = nh_.serviceClient<BestStart>(s_.policy_ns + "/best_start");
  if (!devices.waitForRobot()) {
    ROS_FATAL_STREAM("steerable_procedure: the robot (" << s_.robot_ns
                                                        << ") did not come up in 60 s");
    return false;
  }
  if (!best_start.waitForExistence(ros::Duration(s_.policy_wait_s))) {
    ROS_FATAL_STREAM("steerable_procedure: the policy ("
                     << s_.policy_ns << ") did not come up in " << s_.policy_wait_s
                     << " s (~policy_wait_s; it chooses and solves its model first)");
    return false;
  }
  devices.supervise(s_.watch_nodes);
  BestStart best;
  if (!best_start.call(best) || !best.response.found) {
    ROS_FATAL_STREAM("steerable_procedure: no start state: " << best.response.message);
    return false;
  }
  // The policy's own table (saved by steering_policy; solved here only without one) for the
  // report's Monte Carlo and P_s map.
  steering::SelectionOptions selection;
  selection.start = steering::startOptionsFromScene(scene);
  Result<steering::PolicySource> policy =
      steering::solveOrLoad(problem, scene.name, s_.table_dir, selection);
  if (!policy) {
    ROS_FATAL_STREAM("steerable_procedure: no policy table: " << policy.status().toString());
    return false;
  }
  ROS_INFO_STREAM("steerable_procedure: model " << policy.value().description() << " (ps_tolerance "
                                                << problem.ps_tolerance << ")");
  procedures::SteerableStart start;
  start.pose.p_SceneTip = steering::Point2(best.response.pose.x, best.response.pose.y);
  start.pose.theta_rad = best.response.pose.theta;
  start.pose.bevel =
      steering::bevelFromString(best.response.bevel).value_or(steering::Bevel::kLeft);
  start.predicted_ps = best.response.probability_of_success;
  start.verified_ps = best.response.verified_ps;
  start.verified_ci = {best.response.verified_ci_low, best.response.verified_ci_high};
  start.verification_trials = best.response.verification_trials;
  start.confirmed = best.response.confirmed;
  start.table_best_ps = best.response.table_best_ps;
  ROS_INFO_STREAM("steerable_procedure: start " << best.response.message);

  const procedures::SteerableTrials trials(scene.name, problem, *policy.value().table,
                                           selection.start, s_.trials);
  procedures::SteerableReport rep = trials.run(devices, start);
  rep.model = policy.value().description();
  rep.policy_table = policy.value().source;
  rep.estimated_ps_error = policy.value().estimated_error;
  // The tables that answered (the policy may have re-solved for the noise it learned), each with
  // its own prediction for its trials.
  std::vector<int> record_index;
  const auto noises = rep.trialNoises(record_index);
  if (!noises.empty()) {
    const auto used = steering::tablesUsed(policy.value().model->problem(), noises, scene.name,
                                           s_.table_dir, selection);
    if (used) {
      rep.addTablesUsed(used.value(), record_index);
    } else {
      ROS_ERROR_STREAM("steerable_procedure: tables used: " << used.status().toString());
    }
  }
  rep.wall_time_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - wall_start).count();
  if (rep.fault) {
    ROS_ERROR_STREAM("steerable_procedure: " << rep.fault->toString() << " after "
                                             << rep.records.size() << " of " << s_.trials.trials
                                             << " trials; the run was stopped; robot: "
                                             << rep.safe_stop);
  }
  if (!s_.report_dir.empty()) {
    rep.write(s_.report_dir);
  }
  std::cout << rep.text() << "report in " << s_.report_dir << "\n" << std::flush;
  return rep.success();
}

}  // namespace needle_guidance
