// steerable_procedure_3d (steerable_procedure_3d_ros.h).
#include "needle_guidance/ros/steerable_procedure_3d_ros.h"

#include <chrono>
#include <limits>
#include <optional>
#include <stdexcept>

#include <cv_bridge/cv_bridge.h>

#include "needle_guidance/PlanSteering3.h"
#include "needle_guidance/SetEntryPose3.h"
#include "needle_guidance/report/output_path.h"
#include "needle_guidance/robot/insertion_stage.h"
#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/conversions_3d.h"
#include "needle_guidance/ros/node_supervisor.h"
#include "needle_guidance/ros/params.h"
#include "needle_guidance/ros/run_goal.h"

namespace needle_guidance {

namespace sd = steering_3d;

SteerableProcedure3dRos::SteerableProcedure3dRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh)
    : nh_(nh) {
  namespace rp = ros_params;
  ROS_INFO("steerable_procedure_3d parameters:");
  const std::string scene_path = rp::text(private_nh, "scene", "", true);
  trials_ = static_cast<int>(rp::integer(private_nh, "trials", 10, 1, 100000, "trials"));
  seed_ = rp::integer(private_nh, "seed", 1, 0, 1L << 30, "");
  max_steps_ = static_cast<int>(rp::integer(private_nh, "max_steps", 200, 1, 100000, "steps"));
  control_timeout_s_ = rp::number(private_nh, "control_timeout_s", 10.0, 0.1, 600.0, "s");
  startup_timeout_s_ = rp::number(private_nh, "startup_timeout_s", 30.0, 0.1, 600.0, "s");
  tip_sigma_m_ = rp::number(private_nh, "tip_sigma_m", 0.0, 0.0, 0.1, "m");
  planner_ns_ = rp::text(private_nh, "planner_ns", "steering_planner_3d");
  robot_ns_ = rp::text(private_nh, "robot_ns", "insertion_robot");
  report_dir_ = ros_params::rosHomePath(rp::text(private_nh, "report_dir", "", true));
  const procedures::TipSource3 source = procedures::tipSource3OrThrow(
      rp::text(private_nh, "tip_source", "truth"), private_nh.resolveName("tip_source"));
  scene_ = std::make_unique<needle_model::Scene3d>(needle_model::loadScene3d(scene_path));
  if (source == procedures::TipSource3::kBiplane) {  // the frames of the two imager nodes
    fusion_ = std::make_unique<imaging::BiplaneFusion3>(*scene_, imaging::BiplaneViewsConfig{});
    for (int k = 0; k < 2; ++k) {
      view_subs_[k] = nh.subscribe<sensor_msgs::Image>(
          k == 0 ? "imager_along_z/image" : "imager_along_y/image", 2,
          [this, k](const sensor_msgs::ImageConstPtr& m) { views_[k].set(*m); });
    }
  }
  world_ = std::make_unique<needle_model::CollisionWorld3>(scene_->collisionWorld());
  std::string urdf;  // the robot's own model: the insertion joint's travel
  travel_m_ = nh.getParam("robot_description", urdf)
                  ? robot::parseStageLimits(urdf)[robot::StageJoint::kDepth].upper
                  : std::numeric_limits<double>::infinity();
  tip_pub_ = private_nh.advertise<geometry_msgs::PoseWithCovarianceStamped>("tip", 10);
  steer_ = std::make_unique<actionlib::SimpleActionClient<Steer3Action>>(nh, robot_ns_ + "/steer");
  retract_ =
      std::make_unique<actionlib::SimpleActionClient<LinearMoveAction>>(nh, robot_ns_ + "/retract");
  set_entry_ = nh.serviceClient<SetEntryPose3>(robot_ns_ + "/set_entry_pose_3d");
  control_sub_ = nh.subscribe<SteeringControl3>(
      planner_ns_ + "/control", 10, [this](const SteeringControl3ConstPtr& m) {
        if (m->header.stamp.toNSec() == expected_ns_) {  // the answer to this node's last tip
          controls_.set(*m);
        }
      });
  plan_client_ = nh.serviceClient<PlanSteering3>(planner_ns_ + "/plan");
}

std::optional<SteeringControl3> SteerableProcedure3dRos::exchange(
    const procedures::SteeringTrial3& trial) {
  geometry_msgs::PoseWithCovarianceStamped msg;
  msg.header.frame_id = "scene";
  msg.header.stamp = ros::Time::now();
  msg.pose.pose = ros_conversions::toMessage(trial.observedTip());
  const needle_model::Matrix3 covariance = trial.observedCovariance_m2(tip_sigma_m_);
  for (int k = 0; k < 9; ++k) {
    msg.pose.covariance[static_cast<std::size_t>(6 * (k / 3) + k % 3)] = covariance(k / 3, k % 3);
  }
  expected_ns_ = msg.header.stamp.toNSec();
  tip_pub_.publish(msg);
  SteeringControl3 answer;  // the answer to this tip (stamped with it)
  return controls_.waitFor(msg.header.stamp, control_timeout_s_, answer) ? std::optional(answer)
                                                                         : std::nullopt;
}

bool SteerableProcedure3dRos::runTrial(procedures::SteeringTrial3& trial,
                                       std::uint64_t trial_seed) {
  PlanSteering3 srv;
  srv.request.seed = trial_seed;
  if (!plan_client_.call(srv)) {
    supervisor_->checkNow();
    trial.abort("the call of " + plan_client_.getService() +
                " failed: " + fault().value_or("no answer"));
    return false;
  }
  if (!srv.response.success) {
    trial.refuseStart(procedures::planCodeFromName(srv.response.status), srv.response.message);
    return true;
  }
  needle_model::TipPose3 entry;
  if (const std::string bad = ros_conversions::fromMessage(srv.response.start, entry);
      !bad.empty()) {
    trial.abort("the planner's entry pose: " + bad);
    return false;
  }
  trial.start(entry, srv.response.p_success, srv.response.seconds);
  if (const std::string failed = placeRobot(entry, trial_seed); !failed.empty()) {
    trial.abort(failed);
    return false;
  }
  trial.setWorld([this](const needle_model::Control3& c, needle_model::TipPose3& tip,
                        sd::TrialResult3& r) { return robotStep(c, tip, r); });
  // As runTrial3: the entry plan's first step, then a replan from every tip.
  trial.setPlan(ros_conversions::controlsFromArrays(
      srv.response.rotate_rad, srv.response.curvature_per_m, srv.response.insertion_m));
  if (fusion_) {  // one frame of each imager after the step, fused
    trial.setObserver([this](const auto&, const needle_model::TipPose3& predicted, auto) {
      imaging::Frame frames[2];
      for (int k = 0; k < 2; ++k) {
        sensor_msgs::Image m;
        if (!views_[k].waitFor(step_sent_, control_timeout_s_, m)) {
          throw std::runtime_error(view_subs_[k].getTopic() + ": no frame after the step within " +
                                   std::to_string(control_timeout_s_) + " s");
        }
        frames[k].image = cv_bridge::toCvCopy(m, "mono8")->image;
      }
      return fusion_->observeFrames(frames[0], frames[1], predicted);
    });
  }
  while (trial.step() && ros::ok()) {
    const auto t0 = std::chrono::steady_clock::now();
    const std::optional<SteeringControl3> answer = exchange(trial);
    if (!answer) {
      trial.abort(fault().value_or("no control from " + planner_ns_ + " within " +
                                   std::to_string(control_timeout_s_) + " s"));
      return false;
    }
    round_trip_ms_.push_back(
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
    std::vector<needle_model::Control3> plan = ros_conversions::controlsFromArrays(
        answer->next_rotate_rad, answer->next_curvature_per_m, answer->next_insertion_m);
    plan.insert(plan.begin(), needle_model::Control3{answer->rotate_rad, answer->curvature_per_m,
                                                     answer->insertion_m});
    if (!trial.followAnswer(answer->status, answer->message, answer->plan_seconds, plan)) {
      return false;
    }
  }
  return ros::ok();
}

std::optional<std::string> SteerableProcedure3dRos::fault() {
  const auto death = supervisor_ != nullptr ? supervisor_->death() : std::nullopt;
  return death       ? std::optional(death->toString())
         : ros::ok() ? std::nullopt
                     : std::optional<std::string>("ROS shut down");
}

std::string SteerableProcedure3dRos::leaveSafe() {
  controls_.setAbort(nullptr);
  if (const std::string robot = nh_.resolveName(robot_ns_, false);
      !NodeSupervisor::ping(robot, 0.5).empty()) {
    return "none possible: the robot node " + robot + " does not answer";
  }
  const std::string failed = retract(nullptr);
  return failed.empty() ? "needle retracted" : "retraction failed: " + failed;
}

std::string SteerableProcedure3dRos::retract(
    const std::function<std::optional<std::string>()>& death) {
  LinearMoveGoal out;  // out of the tissue (at once when the needle is already out)
  out.velocity_m_s = 0.02;
  std::string message;
  return runGoal(*retract_, out, control_timeout_s_, death, message) ? "" : message;
}

void SteerableProcedure3dRos::progress(const std::string& line) {
  ROS_INFO_STREAM("steerable_procedure_3d: " << line);
}

std::string SteerableProcedure3dRos::placeRobot(const needle_model::TipPose3& entry,
                                                std::uint64_t seed) {
  if (const std::string failed = retract([this] { return fault(); }); !failed.empty()) {
    return "the robot did not retract: " + failed;
  }
  SetEntryPose3 srv;
  srv.request.entry = ros_conversions::toMessage(entry);
  srv.request.reseed = true;
  srv.request.seed = seed;  // the trial's noise stream, as runTrial3's world
  if (!set_entry_.call(srv) || !srv.response.success) {
    return "the robot refused the entry: " + srv.response.message + fault().value_or("");
  }
  return "";
}

bool SteerableProcedure3dRos::robotStep(const needle_model::Control3& c,
                                        needle_model::TipPose3& tip, sd::TrialResult3& r) {
  Steer3Goal goal;
  goal.rotate_rad = c.rotate_rad;
  goal.spin_rate_rad_s = scene_->needle.spin_rate_max_rad_s;
  goal.curvature_per_m = c.curvature_per_m;
  goal.length_m = c.length_m;
  goal.velocity_m_s = scene_->needle.insertion_speed_m_s;
  std::string message;
  step_sent_ = ros::Time::now();  // the robot publishes the shape (stamped) when the step ends
  const bool ok = runGoal(
      *steer_, goal, control_timeout_s_, [this] { return fault(); }, message);
  const Steer3ResultConstPtr result = steer_->getResult();
  std::vector<needle_model::Vector3> path;
  for (const geometry_msgs::Point& p : result->path) {
    path.emplace_back(p.x, p.y, p.z);
  }
  const std::optional<bool> free =
      procedures::recordRobotStep3(ok, result->contact, result->obstacle, result->message, path, r);
  if (!free || !ros_conversions::fromMessage(result->tip, tip).empty()) {
    supervisor_->checkNow();
    throw std::runtime_error("the robot's steer goal: " + message);  // a fault, not an outcome
  }
  return *free;
}

bool SteerableProcedure3dRos::run() {
  report::prepareReportDir(report_dir_, "~report_dir", false);
  const ros::Duration up(startup_timeout_s_);
  if (!plan_client_.waitForExistence(up) || !set_entry_.waitForExistence(up) ||
      !steer_->waitForServer(up) || !retract_->waitForServer(up)) {
    ROS_ERROR_STREAM("steerable_procedure_3d: no planner or robot (steerable_3d mode) within "
                     << startup_timeout_s_ << " s");
    return false;
  }
  const ros::WallTime deadline = ros::WallTime::now() + ros::WallDuration(startup_timeout_s_);
  while (ros::ok() && (tip_pub_.getNumSubscribers() == 0 || control_sub_.getNumPublishers() == 0)) {
    if (ros::WallTime::now() > deadline) {
      ROS_ERROR("steerable_procedure_3d: the planner never connected to ~tip / control");
      return false;
    }
    ros::WallDuration(0.05).sleep();
  }
  NodeSupervisor supervisor(nh_, {planner_ns_, robot_ns_});
  supervisor_ = &supervisor;
  controls_.setAbort([this] { return fault().has_value(); });
  const procedures::SteeringRun3 r = procedures::runSteeringTrials3(
      *scene_, *world_, *this, trials_, static_cast<std::uint64_t>(seed_), max_steps_, travel_m_);
  procedures::NodeDeath3 death;
  if (const auto d = supervisor.death()) {
    death = {d->node, d->toString(), d->when.toSec()};
    ROS_ERROR_STREAM("steerable_procedure_3d: stopped: " << death.cause);
  }
  supervisor_ = nullptr;
  procedures::writeSteeringReport3(report_dir_, *scene_, r, round_trip_ms_,
                                   static_cast<std::uint64_t>(seed_), death);
  ROS_INFO_STREAM("steerable_procedure_3d: "
                  << procedures::describe(procedures::summarize(r.results, r.faulted))
                  << "; robot: " << r.safe_stop << "; report in " << report_dir_);
  return death.dead_node.empty() && r.completed(trials_);
}

}  // namespace needle_guidance
