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
#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/report/output_path.h"
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

/// A table cell: the value, or empty for a figure that does not exist (never inserted).
report::Cell cell(double value) {
  return std::isfinite(value) ? report::Cell(value) : report::Cell(std::string());
}

}  // namespace

InsertionProcedureRos::InsertionProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh)
    : nh_(nh) {
  ROS_INFO("insertion_procedure parameters:");
  scene_spec_ = ros_params::text(private_nh, "scene", "prostate_sagittal");
  const scene::Scene scene = scene::loadSceneSpec(scene_spec_);
  robot_ns_ = ros_params::text(private_nh, "robot", "insertion_robot");
  tissue_ns_ = ros_params::text(private_nh, "tissue", "");
  planner_ns_ = ros_params::text(private_nh, "planner", "");
  reset_between_needles_ =
      ros_params::number(private_nh, "reset_between_needles", 1.0, 0.0, 1.0, "(0 or 1)") > 0.5;
  report_dir_ = ros_params::text(private_nh, "report_dir", "", true);
  // Refuses a system folder or someone else's non-empty folder before anything runs.
  report::prepareReportDir(report_dir_, private_nh.resolveName("report_dir"),
                           ros_params::flag(private_nh, "allow_system_paths", false));
  insertion_velocity_m_s_ = ros_params::number(
      private_nh, "insertion_velocity_m_s", scene.needle.insertion_velocity_m_s, 1e-4, 1.0, "m/s");
  retract_velocity_m_s_ = ros_params::number(private_nh, "retract_velocity_m_s",
                                             2.0 * insertion_velocity_m_s_, 1e-4, 1.0, "m/s");
  height_velocity_m_s_ =
      ros_params::number(private_nh, "height_velocity_m_s", 0.01, 1e-4, 1.0, "m/s");
  retract_depth_m_ = ros_params::number(private_nh, "retract_depth_m", -0.005, -1.0, 0.0, "m");
  depth_tolerance_m_ = ros_params::number(private_nh, "depth_tolerance_m", 1e-6, 0.0, 0.01, "m");
  velocity_tolerance_ = ros_params::number(private_nh, "velocity_tolerance", 0.05, 0.0, 1.0, "1");
  placement_tolerance_m_ = ros_params::number(private_nh, "placement_tolerance_m",
                                              scene.needle.placement_tolerance_m, 1e-7, 0.05, "m");
  max_targets_ =
      static_cast<int>(ros_params::number(private_nh, "max_targets", 0, 0, 1000, "targets"));
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
  std::mutex mutex;
  geometry_msgs::PoseStamped last_tip;
  geometry_msgs::PoseArray last_seeds;
  ros::Subscriber tip_sub = nh_.subscribe<geometry_msgs::PoseStamped>(
      robot_ns_ + "/measured_cp", 10, [&](const geometry_msgs::PoseStampedConstPtr& msg) {
        std::lock_guard<std::mutex> lock(mutex);
        last_tip = *msg;
      });
  ros::ServiceClient implant;
  ros::ServiceClient reset_tissue;
  ros::Subscriber seeds_sub;
  if (!tissue_ns_.empty()) {
    implant = nh_.serviceClient<ImplantSeed>(tissue_ns_ + "/implant_seed");
    reset_tissue = nh_.serviceClient<std_srvs::Trigger>(tissue_ns_ + "/reset");
    if (!implant.waitForExistence(ros::Duration(30.0))) {
      ROS_FATAL_STREAM("insertion_procedure: " << tissue_ns_
                                               << "/implant_seed did not come up in 30 s");
      return false;
    }
    seeds_sub = nh_.subscribe<geometry_msgs::PoseArray>(
        tissue_ns_ + "/seeds", 10, [&](const geometry_msgs::PoseArrayConstPtr& msg) {
          std::lock_guard<std::mutex> lock(mutex);
          last_seeds = *msg;
        });
  }

  ros::ServiceClient planner;
  if (!planner_ns_.empty()) {
    planner = nh_.serviceClient<PlanRigid>(planner_ns_ + "/plan");
    if (!planner.waitForExistence(ros::Duration(30.0))) {
      ROS_FATAL_STREAM("insertion_procedure: " << planner_ns_ << "/plan did not come up in 30 s");
      return false;
    }
  }
  struct Record {
    const scene::Target* target;
    geometry::Point2 aim = geometry::Point2::Zero();  ///< release point commanded [m]
    double predicted_error_m = NAN;
    double unplanned_predicted_m = NAN;
    double plan_s = NAN;
    double verified_error_m = NAN;
    std::string outcome;              ///< placed | missed | refused | error
    std::string reason;               ///< why refused, or what went wrong
    geometry::Point2 seed{NAN, NAN};  ///< seed position once the needle is out and at rest [m]
    MoveOutcome insert, retract;
    double tip_error_mm = NAN;
    int seed_id = -1;
    std::string status;
  };
  std::vector<Record> records;
  const ros::WallTime start = ros::WallTime::now();
  const std::size_t count = max_targets_ > 0
                                ? std::min<std::size_t>(scene.targets.size(), max_targets_)
                                : scene.targets.size();
  double depth_now = retract_depth_m_;
  for (std::size_t i = 0; i < count && ros::ok(); ++i) {
    Record r;
    r.target = &scene.targets[i];
    r.aim = r.target->position;
    if (!planner_ns_.empty()) {
      PlanRigid srv;
      srv.request.target = ros_conversions::toMessage(r.target->position);
      const bool called = planner.call(srv);
      if (!called || !srv.response.success) {
        r.status = "plan failed: " + srv.response.message;
        r.outcome = called && srv.response.code != "simulation failed" ? "refused" : "error";
        r.reason = called ? srv.response.message : "the planner service call failed";
        ROS_ERROR_STREAM("insertion_procedure: " << r.target->name << " " << r.status);
        records.push_back(r);
        continue;
      }
      r.aim = {srv.response.release.x, srv.response.release.y};
      r.predicted_error_m = srv.response.predicted_error_m;
      r.unplanned_predicted_m = srv.response.unplanned_error_m;
      r.plan_s = srv.response.planning_time_s;
      r.verified_error_m = srv.response.verified ? srv.response.verified_error_m : NAN;
    }
    const double height = r.aim.y();
    const double depth = r.aim.x();
    const MoveOutcome h = move(height_client, height, height_velocity_m_s_, 0.0);
    if (h.ok) {
      r.insert = move(insert_client, depth, insertion_velocity_m_s_, depth_now);
    }
    ros::Duration(0.05).sleep();  // one more measured_cp at rest
    {
      std::lock_guard<std::mutex> lock(mutex);
      r.tip_error_mm =
          1e3 *
          (geometry::Point2(last_tip.pose.position.x, last_tip.pose.position.y) - r.aim).norm();
    }
    if (!tissue_ns_.empty() && r.insert.ok) {
      ImplantSeed srv;
      if (implant.call(srv) && srv.response.success) {
        r.seed_id = srv.response.seed_id;
      } else {
        ROS_ERROR_STREAM("insertion_procedure: seed at "
                         << r.target->name << " not implanted: " << srv.response.message);
      }
    }
    r.retract = move(retract_client, retract_depth_m_, retract_velocity_m_s_, depth);
    if (r.seed_id >= 0) {
      ros::Duration(0.4).sleep();  // the tissue comes to rest; seeds are republished at 20 Hz
      std::lock_guard<std::mutex> lock(mutex);
      if (static_cast<std::size_t>(r.seed_id) < last_seeds.poses.size()) {
        const auto& p = last_seeds.poses[static_cast<std::size_t>(r.seed_id)].position;
        r.seed = {p.x, p.y};
      }
    }
    if (reset_tissue && reset_between_needles_) {
      std_srvs::Trigger trigger;
      reset_tissue.call(trigger);  // the next needle meets undisturbed tissue (4.4)
      std::lock_guard<std::mutex> lock(mutex);
      last_seeds.poses.clear();
    }
    depth_now = r.retract.ok ? retract_depth_m_ : depth;
    r.status = !h.ok                                    ? "height " + h.state
               : !r.insert.ok                           ? "insert " + r.insert.state
               : !r.retract.ok                          ? "retract " + r.retract.state
               : (!tissue_ns_.empty() && r.seed_id < 0) ? "no seed"
                                                        : "ok";
    ROS_INFO_STREAM("insertion_procedure: " << r.target->name << " " << r.status << " ("
                                            << r.insert.result.duration_s << " s)");
    records.push_back(r);
  }

  report::Table moves({"target",
                       "target_x_mm",
                       "target_y_mm",
                       "release_x_mm",
                       "release_y_mm",
                       "depth_reached_mm",
                       "depth_error_mm",
                       "tip_error_mm",
                       "insert_s",
                       "insert_velocity_mm_s",
                       "velocity_error_pct",
                       "retract_s",
                       "seed_x_mm",
                       "seed_y_mm",
                       "seed_error_mm",
                       "predicted_error_mm",
                       "unplanned_predicted_mm",
                       "plan_s",
                       "status",
                       "outcome",
                       "verified_error_mm",
                       "reason"},
                      6);
  double sum_plan_s = 0.0;
  bool all_ok = records.size() == count;
  double max_depth_error_mm = 0.0, max_velocity_error_pct = 0.0, max_tip_error_mm = 0.0;
  double max_seed_error_mm = 0.0, sum_seed_error_mm = 0.0;
  int seeds_measured = 0;
  const bool with_tissue = !tissue_ns_.empty();
  const bool planned = !planner_ns_.empty();
  int placed = 0, missed = 0, refused = 0, errors = 0;
  for (Record& r : records) {
    const double depth_error_mm = 1e3 * std::abs(r.insert.result.reached_m - r.aim.x());
    sum_plan_s += std::isfinite(r.plan_s) ? r.plan_s : 0.0;
    const double velocity_error_pct =
        100.0 * std::abs(r.insert.result.mean_velocity_m_s - insertion_velocity_m_s_) /
        insertion_velocity_m_s_;
    if (r.status == "ok" && (depth_error_mm > 1e3 * depth_tolerance_m_ ||
                             velocity_error_pct > 100.0 * velocity_tolerance_)) {
      r.status = "out of tolerance";
    }
    const geometry::Point2 seed = r.seed;
    double seed_error_mm = NAN;
    if (seed.allFinite()) {
      seed_error_mm = 1e3 * (seed - r.target->position).norm();
      max_seed_error_mm = std::max(max_seed_error_mm, seed_error_mm);
      sum_seed_error_mm += seed_error_mm;
      ++seeds_measured;
    } else if (!tissue_ns_.empty() && r.status == "ok") {
      r.status = "seed not measured";
    }
    // Success means the seed landed: placed within the tolerance, else missed; refused and
    // error come from planning and the moves.
    if (r.outcome.empty()) {
      if (r.status != "ok") {
        r.outcome = "error";
        r.reason = r.status;
      } else if (with_tissue && std::isfinite(seed_error_mm)) {
        r.outcome = seed_error_mm <= 1e3 * placement_tolerance_m_ ? "placed" : "missed";
      } else {
        r.outcome = with_tissue ? "error" : "placed";  // robot only: the move is the placement
      }
    }
    placed += r.outcome == "placed" ? 1 : 0;
    missed += r.outcome == "missed" ? 1 : 0;
    refused += r.outcome == "refused" ? 1 : 0;
    errors += r.outcome == "error" ? 1 : 0;
    all_ok = all_ok && (planned ? r.outcome == "placed" : r.status == "ok");
    const bool inserted = r.insert.ok || r.insert.result.duration_s > 0.0;
    if (inserted) {  // a target never inserted has no move figures (not a 1e9 stand-in)
      max_depth_error_mm = std::max(max_depth_error_mm, depth_error_mm);
      max_velocity_error_pct = std::max(max_velocity_error_pct, velocity_error_pct);
      max_tip_error_mm = std::isfinite(r.tip_error_mm) ? std::max(max_tip_error_mm, r.tip_error_mm)
                                                       : max_tip_error_mm;
    }
    const double none = NAN;
    moves.addRow({r.target->name,
                  1e3 * r.target->position.x(),
                  1e3 * r.target->position.y(),
                  1e3 * r.aim.x(),
                  1e3 * r.aim.y(),
                  cell(inserted ? 1e3 * r.insert.result.reached_m : none),
                  cell(inserted ? depth_error_mm : none),
                  cell(inserted ? r.tip_error_mm : none),
                  cell(inserted ? r.insert.result.duration_s : none),
                  cell(inserted ? 1e3 * r.insert.result.mean_velocity_m_s : none),
                  cell(inserted ? velocity_error_pct : none),
                  cell(inserted ? r.retract.result.duration_s : none),
                  cell(1e3 * seed.x()),
                  cell(1e3 * seed.y()),
                  cell(seed_error_mm),
                  cell(1e3 * r.predicted_error_m),
                  cell(1e3 * r.unplanned_predicted_m),
                  cell(r.plan_s),
                  r.status,
                  r.outcome,
                  cell(1e3 * r.verified_error_m),
                  r.reason});
  }
  const double total_s = (ros::WallTime::now() - start).toSec();

  std::ostringstream json;
  json.precision(9);
  json << "{\n  \"procedure\": \""
       << (planned       ? "rigid_seed_implant"
           : with_tissue ? "unplanned_seed_implant"
                         : "robot_insertion")
       << "\",\n  \"scene\": \"" << scene.name
       << "\",\n  \"success\": " << (all_ok ? "true" : "false") << ",\n  \"targets\": " << count
       << ",\n  \"max_depth_error_mm\": " << max_depth_error_mm
       << ",\n  \"max_tip_error_mm\": " << max_tip_error_mm
       << ",\n  \"max_velocity_error_pct\": " << max_velocity_error_pct
       << ",\n  \"placed\": " << placed << ",\n  \"missed\": " << missed
       << ",\n  \"refused\": " << refused << ",\n  \"error\": " << errors
       << ",\n  \"placement_tolerance_mm\": " << 1e3 * placement_tolerance_m_
       << ",\n  \"success_means\": \""
       << (planned ? "every target placed (seed within the placement tolerance)"
                   : "every move succeeded")
       << "\"";
  if (with_tissue) {
    json << ",\n  \"seeds\": " << seeds_measured
         << ",\n  \"max_seed_error_mm\": " << max_seed_error_mm << ",\n  \"mean_seed_error_mm\": "
         << (seeds_measured > 0 ? sum_seed_error_mm / seeds_measured : -1.0);
  }
  if (planned) {
    json << ",\n  \"planning_s_mean\": " << (count > 0 ? sum_plan_s / count : 0.0);
  }
  json << ",\n  \"wall_time_s\": " << total_s << "\n}\n";
  std::ostringstream md;
  md << "# "
     << (planned       ? "Rigid seed implant with offset planning (ch. 4)"
         : with_tissue ? "Seed implant without deformation compensation"
                       : "Robot insertion")
     << " — scene `" << scene.name << "`\n\n"
     << "Each target: move to its height, insert to its depth at " << 1e3 * insertion_velocity_m_s_
     << " mm/s" << (with_tissue ? ", implant a seed" : "") << ", retract to "
     << 1e3 * retract_depth_m_ << " mm. Tip error is the robot's positioning error."
     << (with_tissue ? " Seed error is where the seed ends up in the FEM tissue once the needle is "
                       "out, against its target: the error that offset planning (dissertation "
                       "ch. 4) cancels."
                     : " No tissue model.")
     << "\n\n"
     << moves.toMarkdown() << "\nTargets: " << placed << " placed (within "
     << 1e3 * placement_tolerance_m_ << " mm), " << missed << " missed, " << refused << " refused, "
     << errors << " error.\nResult: "
     << (all_ok ? (planned ? "every seed placed" : "all moves succeeded") : "FAILED")
     << ", wall time " << total_s << " s.\n";
  moves.writeCsv(report_dir_ + "/moves.csv");
  report::writeTextFile(report_dir_ + "/summary.json", json.str());
  report::writeTextFile(report_dir_ + "/summary.md", md.str());
  std::cout << "\n== "
            << (planned       ? "Rigid seed implant (planned)"
                : with_tissue ? "Seed implant (no compensation)"
                              : "Robot insertion")
            << " on scene '" << scene.name << "' ==\n"
            << moves.toText() << (all_ok ? "PASS" : "FAIL") << ": " << count
            << " targets, max depth error " << max_depth_error_mm << " mm, max velocity error "
            << max_velocity_error_pct << " %";
  if (with_tissue) {
    std::cout << ", seed error max " << max_seed_error_mm << " mm";
  }
  std::cout << ", " << total_s << " s; report in " << report_dir_ << "\n" << std::flush;
  return all_ok;
}

}  // namespace needle_guidance
