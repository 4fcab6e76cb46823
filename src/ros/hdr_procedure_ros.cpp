#include "needle_guidance/ros/hdr_procedure_ros.h"

#include <actionlib/client/simple_action_client.h>
#include <std_srvs/Trigger.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <sstream>

#include <ros/topic.h>
#include "needle_guidance/DeliverAction.h"
#include "needle_guidance/DoseVolumeHistogram.h"
#include "needle_guidance/EvaluateDelivery.h"
#include "needle_guidance/PlanDwells.h"
#include "needle_guidance/procedures/hdr_report.h"
#include "needle_guidance/report/output_path.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/ros/delivery_conversions.h"
#include "needle_guidance/ros/node_supervisor.h"
#include "needle_guidance/ros/params.h"

namespace needle_guidance {

HdrProcedureRos::HdrProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh) : nh_(nh) {
  ROS_INFO("hdr_procedure parameters:");
  report_dir_ = ros_params::text(private_nh, "report_dir", "", true);
  // Refuses a system folder or someone else's non-empty folder before anything runs.
  report::prepareReportDir(report_dir_, private_nh.resolveName("report_dir"),
                           ros_params::flag(private_nh, "allow_system_paths", false));
  case_dir_ = ros_params::text(private_nh, "case_dir", "");
  dicom_dir_ = ros_params::text(private_nh, "dicom_dir", "");
  synthetic_seed_ =
      static_cast<int>(ros_params::integer(private_nh, "synthetic_seed", 1, 1, 1000000, ""));
  method_ = procedures::toString(procedures::parseDwellMethod(
      ros_params::text(private_nh, "method", "lp"), "parameter ~method"));
  scheduler_ = ros_params::text(private_nh, "scheduler", "dwell_scheduler", true);
  afterloader_ = ros_params::text(private_nh, "afterloader", "afterloader", true);
  pause_at_fraction_ = ros_params::number(private_nh, "pause_at_fraction", -1.0, -1.0, 0.99, "");
  pause_wall_s_ = ros_params::number(private_nh, "pause_s", 1.0, 0.0, 60.0, "s (wall)");
  timeout_s_ = ros_params::number(private_nh, "timeout_s", 600.0, 1.0, 86400.0, "s (wall)");
  tolerance_s_ = ros_params::number(private_nh, "dwell_tolerance_s", 0.1, 1e-6, 1.0, "s");
  journal_dir_ =
      ros_params::rosHomePath(ros_params::text(private_nh, "journal_dir", "afterloader", true));
  respawn_ = ros_params::flag(private_nh, "respawn", false);
  startup_wait_s_ =
      ros_params::number(private_nh, "startup_timeout_s", 60.0, 1.0, 600.0, "s (wall)");
}

procedures::HdrDeliveryReport HdrProcedureRos::planReport(const DwellPlan& p) const {
  procedures::HdrDeliveryReport r;
  r.case_name = p.case_name;
  r.plan_id = p.plan_id;
  r.method = p.method;
  r.objective = p.objective;
  r.channels = static_cast<int>(p.schedule.channels.size());
  r.source_U = p.schedule.current_air_kerma_strength_U;
  r.decay_days = p.schedule.decay_days;
  r.tolerance_s = tolerance_s_;
  ros::NodeHandle nh(nh_);
  // The scheduler's latched DVH of this plan (published before its ~plan response).
  const auto dvh =
      ros::topic::waitForMessage<DoseVolumeHistogram>(scheduler_ + "/dvh", nh, ros::Duration(2.0));
  if (dvh && dvh->plan_id == p.plan_id) {
    r.dvh_dose_Gy = dvh->dose_Gy;
    for (const auto& curve : dvh->curves)
      r.dvh.emplace_back(curve.structure, curve.volume_percent);
  }
  return r;
}

bool HdrProcedureRos::reportNodeDeath(const DwellPlan& p, procedures::HdrDeliveryReport r,
                                      const NodeSupervisor::Death& death, double detect_s,
                                      const ros::WallTime& t0) {
  // What was given, from the afterloader's own durable journal (the device node is gone or its
  // result is not trusted): the delivered time per dwell and the trips, replayed independently.
  r.deliveredFromJournal(ros_conversions::fromMessage(p.schedule),
                         journal_dir_ + "/" + p.plan_id + ".journal");
  r.status = "node_died";
  r.dead_node = death.node;
  r.cause = death.toString() + "; delivery stopped " + report::jsonNumber(detect_s, 3) +
            " s after the supervisor saw it";
  r.detect_s = detect_s;
  r.detected_unix_s = death.when.toSec();
  r.wall_s = (ros::WallTime::now() - t0).toSec();
  r.write(report_dir_);
  std::cout << r.consoleSummary(report_dir_) << std::flush;
  return false;
}

bool HdrProcedureRos::reportNotStarted(const std::string& node, const std::string& cause,
                                       const ros::WallTime& t0) {
  procedures::HdrDeliveryReport r;
  r.case_name = case_dir_.empty() && dicom_dir_.empty()
                    ? "synthetic_" + std::to_string(synthetic_seed_)
                    : (dicom_dir_.empty() ? case_dir_ : dicom_dir_);
  r.method = method_;
  r.status = "not_started";
  r.delivered_from = "nothing (no delivery started)";
  r.dead_node = node;
  r.cause = cause;
  r.detected_unix_s = ros::WallTime::now().toSec();
  r.wall_s = (ros::WallTime::now() - t0).toSec();
  r.write(report_dir_);
  std::cout << r.consoleSummary(report_dir_) << std::flush;
  return false;
}

bool HdrProcedureRos::run() {
  const ros::WallTime t0 = ros::WallTime::now();
  // Watches the scheduler and the afterloader from the start: a node that refused its
  // parameters never comes up, one that dies later is seen within about 0.5 s.
  NodeSupervisor supervisor(nh_, {scheduler_, afterloader_});
  if (const auto missing = supervisor.waitForAll(startup_wait_s_); !missing.empty()) {
    return reportNotStarted(missing.front(),
                            "node " + missing.front() + " did not come up within " +
                                std::to_string(int(startup_wait_s_)) +
                                " s (did it refuse its parameters? see its log)",
                            t0);
  }
  supervisor.clear();  // "not registered yet" seen while the nodes were starting
  const std::string plan_srv = scheduler_ + "/plan";
  PlanDwells plan;
  plan.request.case_dir = case_dir_;
  plan.request.dicom_dir = dicom_dir_;
  plan.request.synthetic_seed = synthetic_seed_;
  plan.request.method = method_;
  if (!ros::service::waitForService(plan_srv, ros::Duration(startup_wait_s_)) ||
      !ros::service::call(plan_srv, plan) || !plan.response.success) {
    supervisor.checkNow();
    if (const auto death = supervisor.death())
      return reportNotStarted(death->node, death->toString() + " while planning", t0);
    return reportNotStarted("", "planning failed: " + plan.response.message, t0);
  }
  const DwellPlan& p = plan.response.plan;
  ROS_INFO_STREAM("hdr_procedure: plan " << p.plan_id << ": objective " << p.objective << ", "
                                         << p.total_dwell_s << " s of dwell in "
                                         << p.schedule.channels.size() << " channels");
  const procedures::HdrDeliveryReport base = planReport(p);

  actionlib::SimpleActionClient<DeliverAction> deliver(afterloader_ + "/deliver", true);
  if (!deliver.waitForServer(ros::Duration(startup_wait_s_))) {
    supervisor.checkNow();
    const auto death = supervisor.death();
    return reportNotStarted(death ? death->node : afterloader_,
                            death ? death->toString() : afterloader_ + "/deliver did not come up",
                            t0);
  }
  DeliverGoal goal;
  goal.schedule = p.schedule;
  double fraction = 0.0;
  std::size_t dwell_count = 0;
  for (const auto& c : p.schedule.channels)
    dwell_count += c.time_s.size();
  std::size_t dwells_started = 0;
  std::pair<int, int> current{-1, -1};
  const auto send = [&] {
    deliver.sendGoal(goal, {}, {}, [&](const DeliverFeedbackConstPtr& f) {
      fraction = f->delivered_fraction;
      if (f->state == "DELIVERING" && f->dwell_index >= 0 &&
          std::make_pair(f->channel, f->dwell_index) != current) {
        current = {f->channel, f->dwell_index};
        ++dwells_started;  // progress for the operator (scripts/demo prints these lines)
        ROS_INFO_STREAM("hdr_procedure: dwell "
                        << dwells_started << "/" << dwell_count << " (channel " << f->channel
                        << ", position " << f->dwell_index << "), " << std::lround(100.0 * fraction)
                        << " % delivered");
      }
    });
  };
  send();
  bool paused_once = pause_at_fraction_ < 0.0;
  int restarts = 0;
  ros::WallTime last_restart_seen;
  const ros::WallTime deadline = t0 + ros::WallDuration(timeout_s_);
  while (!deliver.getState().isDone() && ros::ok() && ros::WallTime::now() < deadline) {
    if (supervisor.death()) {
      const NodeSupervisor::Death death = *supervisor.death();
      const double detect_s = (ros::WallTime::now() - death.when).toSec();
      const bool afterloader_died = death.node == nh_.resolveName(afterloader_, false);
      if (afterloader_died && respawn_ && supervisor.waitForAll(10.0).empty() &&
          deliver.waitForServer(ros::Duration(10.0))) {
        // The respawned afterloader recovered from its journal: the same schedule resumes it.
        ++restarts;
        last_restart_seen = death.when;
        ROS_WARN_STREAM("hdr_procedure: " << death.toString()
                                          << "; it restarted, resuming the delivery");
        supervisor.clear();
        send();
        continue;
      }
      ROS_ERROR_STREAM("hdr_procedure: " << death.toString() << "; stopping the delivery");
      if (!afterloader_died) {
        deliver.cancelGoal();  // the source retracts to its safe
        deliver.waitForResult(ros::Duration(10.0));
      }
      return reportNodeDeath(p, base, death, detect_s, t0);
    }
    if (!paused_once && fraction >= pause_at_fraction_) {
      paused_once = true;
      std_srvs::Trigger t;
      ros::service::call(afterloader_ + "/pause", t);
      ROS_INFO_STREAM("hdr_procedure: operator pause at " << 100.0 * fraction
                                                          << " %: " << t.response.message);
      ros::WallDuration(pause_wall_s_).sleep();
      ros::service::call(afterloader_ + "/resume", t);
      ROS_INFO_STREAM("hdr_procedure: resume: " << t.response.message);
    }
    ros::WallDuration(0.02).sleep();
  }
  if (!deliver.getState().isDone()) {
    deliver.cancelGoal();
    deliver.waitForResult(ros::Duration(30.0));
  }
  if (restarts > 0)
    ROS_INFO_STREAM("hdr_procedure: the afterloader restarted " << restarts << " time(s)");
  const DeliverResult result = deliver.getResult() ? *deliver.getResult() : DeliverResult{};
  procedures::HdrDeliveryReport r = base;
  r.afterloader_restarts = restarts;
  r.detected_unix_s = restarts > 0 ? last_restart_seen.toSec() : 0.0;
  r.status = result.status;
  r.message = result.message;
  r.journal = result.journal;
  r.interruptions = result.interruptions;
  r.transit_in_patient_s = result.transit_in_patient_s;
  const std::size_t n = result.delivered_s.size();
  if (result.channel.size() != n || result.dwell_index.size() != n ||
      result.planned_s.size() != n) {
    r.status = "bad_result";  // a result whose lists disagree is not trusted as a record
    r.message = "the afterloader's result lists differ in length";
    ROS_ERROR_STREAM("hdr_procedure: " << r.message);
  }
  for (std::size_t k = 0; r.status != "bad_result" && k < n; ++k) {
    r.dwells.push_back({result.channel[k], result.dwell_index[k], result.planned_s[k],
                        result.delivered_s[k], 0.0});
  }
  if (r.status != "bad_result")
    evaluate(p, result, r);
  r.wall_s = (ros::WallTime::now() - t0).toSec();
  r.write(report_dir_);
  std::cout << r.consoleSummary(report_dir_) << std::flush;
  return r.success();
}

void HdrProcedureRos::evaluate(const DwellPlan& p, const DeliverResult& result,
                               procedures::HdrDeliveryReport& r) const {
  if (result.delivered_s.empty())
    return;
  EvaluateDelivery ev;
  ev.request.plan_id = p.plan_id;
  ev.request.channel = result.channel;
  ev.request.dwell_index = result.dwell_index;
  ev.request.delivered_s = result.delivered_s;
  ev.request.trips_channel = result.trips_channel;
  ev.request.trips = result.trips;
  if (!ros::service::call(scheduler_ + "/evaluate", ev) || !ev.response.success) {
    ROS_ERROR_STREAM("hdr_procedure: evaluation refused: " << ev.response.message);
    return;
  }
  const auto& e = ev.response;
  if (e.planned_values.size() != e.index_names.size() ||
      e.delivered_values.size() != e.index_names.size() ||
      e.with_transit_values.size() != e.index_names.size()) {
    ROS_ERROR("hdr_procedure: the evaluation's index lists differ in length; not used");
    return;
  }
  for (std::size_t k = 0; k < e.index_names.size(); ++k) {
    r.indices.push_back(
        {e.index_names[k], e.planned_values[k], e.delivered_values[k], e.with_transit_values[k]});
  }
  r.transit_dose_max_Gy = e.transit_dose_max_Gy;
}

}  // namespace needle_guidance
