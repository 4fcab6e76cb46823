#include "needle_guidance/ros/insertion_procedure_ros.h"

#include <actionlib/client/simple_action_client.h>
#include <geometry_msgs/PoseArray.h>
#include <geometry_msgs/PoseStamped.h>
#include <std_srvs/Trigger.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <mutex>
#include <sstream>

#include "needle_guidance/ImplantSeed.h"
#include "needle_guidance/LinearMoveAction.h"
#include "needle_guidance/PlanRigid.h"
#include "needle_guidance/procedures/rigid_implant.h"
#include "needle_guidance/report/output_path.h"
#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/node_supervisor.h"
#include "needle_guidance/ros/params.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue_3d/scene_tissue_3d.h"

namespace needle_guidance {
namespace {

using LinearMoveClient = actionlib::SimpleActionClient<LinearMoveAction>;
using procedures::Fault;
using procedures::MoveResult;
using procedures::PlanResult;

constexpr double kConfirmPause_s = 0.2;  ///< between the pings that confirm a node's death
/// Placement tolerance of the 3-D scenes (the 3-D planner's, docs/tissue_3d.md) [m].
constexpr double kTolerance3d_m = 1e-4;

/// What the procedure needs of its scene, planar or `kind: tissue_3d`.
struct ProcedureScene {
  std::string name;
  std::vector<procedures::ImplantTarget> targets;
  double entry_x_m = 0.0;
  double insertion_velocity_m_s = 0.0;
  double placement_tolerance_m = 0.0;
  bool three_d = false;  ///< on the x-y stage: the lateral axis moves too
};

ProcedureScene loadProcedureScene(const std::string& spec) {
  ProcedureScene out;
  if (scene::sceneKind(spec) == "tissue_3d") {
    const tissue_3d::TissueScene3d scene = tissue_3d::loadTissueScene3d(spec);
    out.name = scene.name;
    for (const tissue_3d::Target3& t : scene.targets) {
      out.targets.push_back({t.name, t.position_m});
    }
    out.entry_x_m = scene.block_min_m.x();
    out.insertion_velocity_m_s = scene.needle.insertion_velocity_m_s;
    out.placement_tolerance_m = kTolerance3d_m;
    out.three_d = true;
    return out;
  }
  const scene::Scene scene = scene::loadSceneSpec(spec);
  out.name = scene.name;
  for (const auto& t : scene.targets) {
    out.targets.push_back({t.name, procedures::Point3(t.position.x(), t.position.y(), 0.0)});
  }
  out.entry_x_m = scene.workspace_min.x();
  out.insertion_velocity_m_s = scene.needle.insertion_velocity_m_s;
  out.placement_tolerance_m = scene.needle.placement_tolerance_m;
  return out;
}

/// The devices of the rigid implant procedure over ROS: the robot's actions, tissue_sim's and
/// rigid_planner's services, and a NodeSupervisor watching all three. A move polls the
/// supervisor every 50 ms and stops the robot when a node dies (seen within about 1 s).
class RosRigidDevices : public procedures::RigidImplantDevices {
public:
  void progress(const std::string& line) override {
    ROS_INFO_STREAM("insertion_procedure: " << line);  // scripts/demo prints these lines
  }
  RosRigidDevices(ros::NodeHandle& nh, const std::string& robot, const std::string& tissue,
                  const std::string& planner, bool lateral_stage)
      : nh_(nh),
        robot_(robot),
        tissue_(tissue),
        planner_(planner),
        lateral_stage_(lateral_stage),
        height_(nh, robot + "/move_to_height", true),
        lateral_(nh, robot + "/move_to_lateral", true),
        insert_(nh, robot + "/insert", true),
        retract_(nh, robot + "/retract", true),
        start_(ros::WallTime::now()) {}

  /// Waits for every interface (30 s each), then starts watching the nodes. Throws
  /// std::runtime_error naming what did not come up.
  void connect() {
    for (LinearMoveClient* client : {&height_, &insert_, &retract_}) {
      if (!client->waitForServer(ros::Duration(30.0))) {
        throw std::runtime_error("robot action servers of " + robot_ + " did not come up in 30 s");
      }
    }
    if (lateral_stage_) {
      if (!lateral_.waitForServer(ros::Duration(30.0))) {
        throw std::runtime_error(robot_ +
                                 "/move_to_lateral (the x-y stage's lateral axis) did "
                                 "not come up in 30 s");
      }
    }
    tip_sub_ = nh_.subscribe<geometry_msgs::PoseStamped>(
        robot_ + "/measured_cp", 10, [this](const geometry_msgs::PoseStampedConstPtr& msg) {
          std::lock_guard<std::mutex> lock(mutex_);
          tip_ =
              procedures::Point3(msg->pose.position.x, msg->pose.position.y, msg->pose.position.z);
        });
    estop_ = nh_.serviceClient<std_srvs::Trigger>(robot_ + "/estop");
    std::vector<std::string> watched{robot_};
    if (!tissue_.empty()) {
      implant_ = nh_.serviceClient<ImplantSeed>(tissue_ + "/implant_seed");
      reset_ = nh_.serviceClient<std_srvs::Trigger>(tissue_ + "/reset");
      if (!implant_.waitForExistence(ros::Duration(30.0))) {
        throw std::runtime_error(tissue_ + "/implant_seed did not come up in 30 s");
      }
      seeds_sub_ = nh_.subscribe<geometry_msgs::PoseArray>(
          tissue_ + "/seeds", 10, [this](const geometry_msgs::PoseArrayConstPtr& msg) {
            std::lock_guard<std::mutex> lock(mutex_);
            seeds_ = *msg;
          });
      watched.push_back(tissue_);
    }
    if (!planner_.empty()) {
      plan_ = nh_.serviceClient<PlanRigid>(planner_ + "/plan");
      if (!plan_.waitForExistence(ros::Duration(30.0))) {
        throw std::runtime_error(planner_ + "/plan did not come up in 30 s");
      }
      watched.push_back(planner_);
    }
    supervisor_ = std::make_unique<NodeSupervisor>(nh_, watched);
  }

  bool hasPlanner() const override { return !planner_.empty(); }
  bool hasTissue() const override { return !tissue_.empty(); }

  PlanResult plan(const procedures::Point3& target) override {
    PlanRigid srv;
    srv.request.target.x = target.x();
    srv.request.target.y = target.y();
    srv.request.target.z = target.z();
    PlanResult r;
    const bool called = plan_.call(srv);
    if (!called) {
      checkNodesNow();  // a dead planner fails the call at once, before the supervisor's timer
    }
    r.ok = called && srv.response.success;
    r.refused = called && !r.ok && srv.response.code != "simulation failed";
    r.unreachable = r.refused && srv.response.code == "unreachable";
    r.message = called ? srv.response.message : "the planner service call failed";
    if (r.ok) {
      r.release = {srv.response.release.x, srv.response.release.y, srv.response.release.z};
      r.predicted_error_m = srv.response.predicted_error_m;
      r.unplanned_error_m = srv.response.unplanned_error_m;
      r.plan_s = srv.response.planning_time_s;
      r.verified_error_m = srv.response.verified ? srv.response.verified_error_m : NAN;
    }
    return r;
  }

  MoveResult moveHeight(double height_m, double velocity_m_s) override {
    return move(height_, height_m, velocity_m_s, 0.0);
  }
  MoveResult moveLateral(double lateral_m, double velocity_m_s) override {
    return move(lateral_, lateral_m, velocity_m_s, 0.0);
  }
  MoveResult moveDepth(double depth_m, double velocity_m_s, double from_m, bool retract) override {
    return move(retract ? retract_ : insert_, depth_m, velocity_m_s, from_m);
  }

  std::optional<procedures::Point3> tip() override {
    ros::Duration(0.05).sleep();  // one more measured_cp at rest
    std::lock_guard<std::mutex> lock(mutex_);
    return tip_;
  }

  std::optional<int> implantSeed(std::string& why_not) override {
    ImplantSeed srv;
    const bool called = implant_.call(srv);
    if (called && srv.response.success) {
      return srv.response.seed_id;
    }
    if (!called) {
      checkNodesNow();
    }
    why_not = srv.response.message.empty() ? "the implant_seed call failed" : srv.response.message;
    ROS_ERROR_STREAM("insertion_procedure: seed not implanted: " << why_not);
    return std::nullopt;
  }

  std::optional<procedures::Point3> seedAtRest(int id) override {
    // The tissue comes to rest; seeds are republished at tissue_sim's marker rate. Only seeds
    // stamped well after the retraction ended count (tissue_sim may lag the robot).
    const ros::Time since = ros::Time::now() + ros::Duration(0.2);
    ros::Duration(0.4).sleep();
    const ros::WallTime deadline = ros::WallTime::now() + ros::WallDuration(10.0);
    while (ros::ok() && ros::WallTime::now() < deadline && !fault()) {
      {
        std::lock_guard<std::mutex> lock(mutex_);
        if (seeds_.header.stamp >= since) {
          break;
        }
      }
      ros::Duration(0.05).sleep();
    }
    std::lock_guard<std::mutex> lock(mutex_);
    if (id < 0 || static_cast<std::size_t>(id) >= seeds_.poses.size()) {
      return std::nullopt;
    }
    const auto& p = seeds_.poses[static_cast<std::size_t>(id)].position;
    return procedures::Point3(p.x, p.y, p.z);
  }

  void resetTissue() override {
    std_srvs::Trigger trigger;
    reset_.call(trigger);
    std::lock_guard<std::mutex> lock(mutex_);
    seeds_.poses.clear();
  }

  /// Checks the watched nodes at once, so a fault() right after a failed service call names a
  /// node that died instead of waiting for the supervisor's next period.
  void checkNodesNow() {
    if (supervisor_) {
      supervisor_->checkNow();
    }
  }

  std::optional<Fault> fault() override {
    return supervisor_ ? supervisor_->confirmedFault(start_, kConfirmPause_s) : std::nullopt;
  }

  std::string safeStop(double retract_depth_m, double velocity_m_s) override {
    const auto f = fault();
    if (f && f->node == nh_.resolveName(robot_, false)) {
      return "none possible: the robot node itself died";
    }
    const MoveResult r = move(retract_, retract_depth_m, velocity_m_s, 0.06, /*supervised=*/false);
    if (r.ok) {
      return "needle retracted to " + std::to_string(1e3 * retract_depth_m) + " mm";
    }
    std_srvs::Trigger trigger;
    const bool stopped = estop_.call(trigger) && trigger.response.success;
    return std::string("retraction ") + r.state + "; emergency stop " +
           (stopped ? "engaged" : "FAILED");
  }

  double now_s() const override { return (ros::WallTime::now() - start_).toSec(); }

private:
  /// Sends a goal and waits for it (twice the nominal duration plus 5 s); supervised, a node
  /// death cancels it.
  MoveResult move(LinearMoveClient& client, double target_m, double velocity_m_s, double from_m,
                  bool supervised = true) {
    LinearMoveGoal goal;
    goal.target_m = target_m;
    goal.velocity_m_s = velocity_m_s;
    const ros::WallTime deadline =
        ros::WallTime::now() +
        ros::WallDuration(2.0 * std::abs(target_m - from_m) / velocity_m_s + 5.0);
    client.sendGoal(goal);
    MoveResult outcome;
    while (!client.waitForResult(ros::Duration(0.05))) {
      const auto f = supervised ? fault() : std::nullopt;
      if (f || ros::WallTime::now() > deadline || !ros::ok()) {
        client.cancelGoal();
        client.waitForResult(ros::Duration(1.0));
        outcome.state = f ? "stopped: " + f->node + " died" : "timed out";
        break;
      }
    }
    if (outcome.state.empty()) {
      outcome.state = client.getState().toString();
      outcome.ok = client.getState() == actionlib::SimpleClientGoalState::SUCCEEDED;
    }
    if (const auto result = client.getResult()) {
      outcome.reached_m = result->reached_m;
      outcome.duration_s = result->duration_s;
      outcome.mean_velocity_m_s = result->mean_velocity_m_s;
    }
    if (!outcome.ok) {
      ROS_ERROR_STREAM("insertion_procedure: move to " << target_m << " m ended " << outcome.state);
    }
    return outcome;
  }

  ros::NodeHandle nh_;
  std::string robot_, tissue_, planner_;
  bool lateral_stage_ = false;
  LinearMoveClient height_, lateral_, insert_, retract_;
  ros::WallTime start_;
  std::mutex mutex_;
  std::optional<procedures::Point3> tip_;
  geometry_msgs::PoseArray seeds_;
  ros::Subscriber tip_sub_, seeds_sub_;
  ros::ServiceClient implant_, reset_, plan_, estop_;
  std::unique_ptr<NodeSupervisor> supervisor_;
};

}  // namespace

InsertionProcedureRos::InsertionProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh)
    : nh_(nh) {
  ROS_INFO("insertion_procedure parameters:");
  scene_spec_ = ros_params::text(private_nh, "scene", "prostate_sagittal");
  const ProcedureScene scene = loadProcedureScene(scene_spec_);
  settings_.lateral_stage = scene.three_d;
  robot_ns_ = ros_params::text(private_nh, "robot", "insertion_robot");
  tissue_ns_ = ros_params::text(private_nh, "tissue", "");
  planner_ns_ = ros_params::text(private_nh, "planner", "");
  settings_.reset_between_needles =
      ros_params::number(private_nh, "reset_between_needles", 1.0, 0.0, 1.0, "(0 or 1)") > 0.5;
  report_dir_ = ros_params::text(private_nh, "report_dir", "", true);
  // Refuses a system folder or someone else's non-empty folder before anything runs.
  report::prepareReportDir(report_dir_, private_nh.resolveName("report_dir"),
                           ros_params::flag(private_nh, "allow_system_paths", false));
  settings_.insertion_velocity_m_s = ros_params::number(
      private_nh, "insertion_velocity_m_s", scene.insertion_velocity_m_s, 1e-4, 1.0, "m/s");
  settings_.retract_velocity_m_s = ros_params::number(
      private_nh, "retract_velocity_m_s", 2.0 * settings_.insertion_velocity_m_s, 1e-4, 1.0, "m/s");
  settings_.height_velocity_m_s =
      ros_params::number(private_nh, "height_velocity_m_s", 0.01, 1e-4, 1.0, "m/s");
  settings_.retract_depth_m =
      ros_params::number(private_nh, "retract_depth_m", -0.005, -1.0, 0.0, "m");
  settings_.depth_tolerance_m =
      ros_params::number(private_nh, "depth_tolerance_m", 1e-6, 0.0, 0.01, "m");
  settings_.velocity_tolerance =
      ros_params::number(private_nh, "velocity_tolerance", 0.05, 0.0, 1.0, "1");
  settings_.placement_tolerance_m = ros_params::number(
      private_nh, "placement_tolerance_m", scene.placement_tolerance_m, 1e-7, 0.05, "m");
  settings_.max_targets =
      static_cast<int>(ros_params::number(private_nh, "max_targets", 0, 0, 1000, "targets"));
  // Refuses settings out of range now.
  procedures::RigidImplantProcedure(scene.name, scene.targets, scene.entry_x_m, settings_);
}

bool InsertionProcedureRos::run() {
  const ProcedureScene scene = loadProcedureScene(scene_spec_);
  RosRigidDevices devices(nh_, robot_ns_, tissue_ns_, planner_ns_, scene.three_d);
  const procedures::RigidImplantProcedure procedure(scene.name, scene.targets, scene.entry_x_m,
                                                    settings_);
  procedures::RigidImplantReport report;
  try {
    devices.connect();
    report = procedure.run(devices);
  } catch (const std::exception& e) {  // a node that never came up: a report that says so
    ROS_FATAL_STREAM("insertion_procedure: " << e.what());
    report.scene = scene.name;
    report.planned = !planner_ns_.empty();
    report.with_tissue = !tissue_ns_.empty();
    report.settings = settings_;
    report.fault =
        procedures::Fault{"(start-up)", devices.now_s(), e.what(), ros::WallTime::now().toSec()};
    report.safe_stop = "nothing moved";
    report.targets_in_scene = static_cast<int>(scene.targets.size());
  }
  report.write(report_dir_);
  if (report.fault) {
    ROS_ERROR_STREAM("insertion_procedure: stopped: "
                     << report.fault->node << " " << report.fault->reason << " at "
                     << report.fault->at_s << " s; robot: " << report.safe_stop);
  }
  std::cout << "\n== "
            << (report.planned       ? "Rigid seed implant (planned)"
                : report.with_tissue ? "Seed implant (no compensation)"
                                     : "Robot insertion")
            << " on scene '" << scene.name << "' ==\n"
            << report.text() << (report.success() ? "PASS" : "FAIL") << ": "
            << report.records.size() << " of " << report.targets_in_scene << " targets tried, "
            << report.count(procedures::TargetOutcome::kPlaced) << " placed, "
            << report.count(procedures::TargetOutcome::kMissed) << " missed, "
            << report.count(procedures::TargetOutcome::kRefused) << " refused ("
            << report.unreachableCount() << " unreachable), "
            << report.count(procedures::TargetOutcome::kError) << " error, " << report.wall_time_s
            << " s; report in " << report_dir_ << "\n"
            << std::flush;
  return report.success();
}

}  // namespace needle_guidance
