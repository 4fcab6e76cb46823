#include "needle_guidance/ros/hdr_procedure_ros.h"

#include <actionlib/client/simple_action_client.h>
#include <std_srvs/Trigger.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <sstream>

#include "needle_guidance/DeliverAction.h"
#include "needle_guidance/EvaluateDelivery.h"
#include "needle_guidance/PlanDwells.h"
#include "needle_guidance/delivery/journal.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/ros/delivery_conversions.h"
#include "needle_guidance/ros/node_supervisor.h"
#include "needle_guidance/report/output_path.h"
#include "needle_guidance/ros/params.h"

namespace needle_guidance {

namespace {

std::string jsonNumber(double v) { return report::jsonNumber(v, 8); }

}  // namespace

HdrProcedureRos::HdrProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh) : nh_(nh) {
  ROS_INFO("hdr_procedure parameters:");
  report_dir_ = ros_params::text(private_nh, "report_dir", "", true);
  // Refuses a system folder or someone else's non-empty folder before anything runs.
  report::prepareReportDir(report_dir_, private_nh.resolveName("report_dir"),
                           ros_params::flag(private_nh, "allow_system_paths", false));
  case_dir_ = ros_params::text(private_nh, "case_dir", "");
  dicom_dir_ = ros_params::text(private_nh, "dicom_dir", "");
  synthetic_seed_ = static_cast<int>(ros_params::integer(private_nh, "synthetic_seed", 1, 1, 1000000, ""));
  method_ = ros_params::text(private_nh, "method", "lp");
  if (method_ != "lp" && method_ != "sa") throw std::runtime_error("parameter ~method must be lp or sa, not '" + method_ + "'");
  scheduler_ = ros_params::text(private_nh, "scheduler", "dwell_scheduler", true);
  afterloader_ = ros_params::text(private_nh, "afterloader", "afterloader", true);
  pause_at_fraction_ = ros_params::number(private_nh, "pause_at_fraction", -1.0, -1.0, 0.99, "");
  pause_wall_s_ = ros_params::number(private_nh, "pause_s", 1.0, 0.0, 60.0, "s (wall)");
  timeout_s_ = ros_params::number(private_nh, "timeout_s", 600.0, 1.0, 86400.0, "s (wall)");
  tolerance_s_ = ros_params::number(private_nh, "dwell_tolerance_s", 0.1, 1e-6, 1.0, "s");
  journal_dir_ = ros_params::rosHomePath(ros_params::text(private_nh, "journal_dir", "afterloader", true));
  respawn_ = ros_params::flag(private_nh, "respawn", false);
}

bool HdrProcedureRos::reportNodeDeath(const DwellPlan& p, const NodeSupervisor::Death& death, double detect_s,
                                      const ros::WallTime& t0) {
  // What was given, from the afterloader's own durable journal (the device node is gone or its
  // result is not trusted): the delivered time per dwell and the trips, replayed independently.
  const delivery::Schedule schedule = ros_conversions::fromMessage(p.schedule);
  const std::string path = journal_dir_ + "/" + p.plan_id + ".journal";
  report::Table dwells({"channel", "dwell_index", "planned_s", "delivered_s", "uncertainty_s"});
  double planned = 0.0, delivered = 0.0;
  std::string journal_note;
  try {
    const delivery::Journal journal(path);
    const delivery::Ledger ledger = delivery::replay(journal.records(), &schedule, 0.5);
    for (const auto& c : schedule.channels) {
      for (std::size_t k = 0; k < c.time_s.size(); ++k) {
        const auto key = std::make_pair(c.channel, c.dwell_index[k]);
        const auto d = ledger.delivered_s.find(key);
        const auto u = ledger.uncertainty_s.find(key);
        const double given = d == ledger.delivered_s.end() ? 0.0 : d->second;
        dwells.addRow({double(c.channel), double(c.dwell_index[k]), c.time_s[k], given,
                       u == ledger.uncertainty_s.end() ? 0.0 : u->second});
        planned += c.time_s[k];
        delivered += given;
      }
    }
    journal_note = std::to_string(journal.records().size()) + " journal records in " + path;
  } catch (const std::exception& e) {
    journal_note = std::string("journal not readable: ") + e.what();
    planned = schedule.totalDwellTime();
  }
  const std::string cause = death.toString() + "; delivery stopped " + report::jsonNumber(detect_s, 3) +
                            " s after the supervisor saw it";
  std::ostringstream json;
  json << "{\n  \"procedure\": \"hdr_delivery\",\n  \"scene\": \"" << p.case_name
       << "\",\n  \"success\": false,\n  \"status\": \"node_died\",\n  \"dead_node\": \"" << death.node
       << "\",\n  \"cause\": \"" << cause << "\",\n  \"plan_id\": \"" << p.plan_id
       << "\",\n  \"planned_dwell_s\": " << jsonNumber(planned) << ",\n  \"delivered_dwell_s\": "
       << jsonNumber(delivered) << ",\n  \"delivered_from\": \"journal\",\n  \"detect_s\": "
       << jsonNumber(detect_s) << ",\n  \"wall_s\": " << jsonNumber((ros::WallTime::now() - t0).toSec())
       << "\n}\n";
  std::ostringstream md;
  md << "# HDR delivery — case `" << p.case_name << "`, plan `" << p.plan_id << "`: STOPPED\n\n"
     << cause << ". The delivery was stopped; what was delivered comes from the afterloader's journal ("
     << journal_note << "): " << delivered << " s of " << planned << " s planned.\n\n"
     << "On a restart the afterloader recovers from this journal with the source in its safe and resumes the "
        "delivery when the same schedule is sent again (respawn:=true does this automatically).\n\n"
     << dwells.toMarkdown();
  dwells.writeCsv(report_dir_ + "/delivery.csv");
  report::writeTextFile(report_dir_ + "/summary.md", md.str());
  report::writeTextFile(report_dir_ + "/summary.json", json.str());
  std::cout << "\n== HDR delivery of case '" << p.case_name << "' ==\nFAIL: " << cause << "; delivered " << delivered
            << " s of " << planned << " s planned (from the journal); report in " << report_dir_ << "\n"
            << std::flush;
  return false;
}

bool HdrProcedureRos::run() {
  const ros::WallTime t0 = ros::WallTime::now();
  const std::string plan_srv = scheduler_ + "/plan", evaluate_srv = scheduler_ + "/evaluate";
  if (!ros::service::waitForService(plan_srv, ros::Duration(60.0)) ||
      !ros::service::waitForService(evaluate_srv, ros::Duration(10.0))) {
    throw std::runtime_error("services " + plan_srv + " and " + evaluate_srv + " did not come up in 60 s");
  }
  PlanDwells plan;
  plan.request.case_dir = case_dir_;
  plan.request.dicom_dir = dicom_dir_;
  plan.request.synthetic_seed = synthetic_seed_;
  plan.request.method = method_;
  if (!ros::service::call(plan_srv, plan) || !plan.response.success) {
    throw std::runtime_error("planning failed: " + plan.response.message);
  }
  const DwellPlan& p = plan.response.plan;
  ROS_INFO_STREAM("hdr_procedure: plan " << p.plan_id << ": objective " << p.objective << ", "
                                         << p.total_dwell_s << " s of dwell in " << p.schedule.channels.size()
                                         << " channels");

  actionlib::SimpleActionClient<DeliverAction> deliver(afterloader_ + "/deliver", true);
  if (!deliver.waitForServer(ros::Duration(60.0))) throw std::runtime_error(afterloader_ + "/deliver did not come up");
  // Watches the scheduler and the afterloader from here on (a death is seen within about 1 s).
  NodeSupervisor supervisor(nh_, {scheduler_, afterloader_});
  DeliverGoal goal;
  goal.schedule = p.schedule;
  double fraction = 0.0;
  std::size_t dwell_count = 0;
  for (const auto& c : p.schedule.channels) dwell_count += c.time_s.size();
  std::size_t dwells_started = 0;
  std::pair<int, int> current{-1, -1};
  const auto send = [&] {
    deliver.sendGoal(goal, {}, {}, [&](const DeliverFeedbackConstPtr& f) {
      fraction = f->delivered_fraction;
      if (f->state == "DELIVERING" && f->dwell_index >= 0 && std::make_pair(f->channel, f->dwell_index) != current) {
        current = {f->channel, f->dwell_index};
        ++dwells_started;  // progress for the operator (scripts/demo prints these lines)
        ROS_INFO_STREAM("hdr_procedure: dwell " << dwells_started << "/" << dwell_count << " (channel "
                                                << f->channel << ", position " << f->dwell_index << "), "
                                                << std::lround(100.0 * fraction) << " % delivered");
      }
    });
  };
  send();
  bool paused_once = pause_at_fraction_ < 0.0;
  int restarts = 0;
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
        ROS_WARN_STREAM("hdr_procedure: " << death.toString() << "; it restarted, resuming the delivery");
        supervisor.clear();
        send();
        continue;
      }
      ROS_ERROR_STREAM("hdr_procedure: " << death.toString() << "; stopping the delivery");
      if (!afterloader_died) {
        deliver.cancelGoal();  // the source retracts to its safe
        deliver.waitForResult(ros::Duration(10.0));
      }
      return reportNodeDeath(p, death, detect_s, t0);
    }
    if (!paused_once && fraction >= pause_at_fraction_) {
      paused_once = true;
      std_srvs::Trigger t;
      ros::service::call(afterloader_ + "/pause", t);
      ROS_INFO_STREAM("hdr_procedure: operator pause at " << 100.0 * fraction << " %: " << t.response.message);
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
  if (restarts > 0) ROS_INFO_STREAM("hdr_procedure: the afterloader restarted " << restarts << " time(s)");
  const DeliverResult r = deliver.getResult() ? *deliver.getResult() : DeliverResult{};
  const double wall_s = (ros::WallTime::now() - t0).toSec();

  report::Table dwells({"channel", "dwell_index", "planned_s", "delivered_s", "error_s"});
  double planned = 0.0, delivered = 0.0, max_error = 0.0;
  for (std::size_t k = 0; k < r.delivered_s.size(); ++k) {
    const double e = r.delivered_s[k] - r.planned_s[k];
    dwells.addRow({double(r.channel[k]), double(r.dwell_index[k]), r.planned_s[k], r.delivered_s[k], e});
    planned += r.planned_s[k];
    delivered += r.delivered_s[k];
    max_error = std::max(max_error, std::abs(e));
  }

  EvaluateDelivery ev;
  ev.request.plan_id = p.plan_id;
  ev.request.channel = r.channel;
  ev.request.dwell_index = r.dwell_index;
  ev.request.delivered_s = r.delivered_s;
  ev.request.trips_channel = r.trips_channel;
  ev.request.trips = r.trips;
  const bool evaluated = !r.delivered_s.empty() && ros::service::call(evaluate_srv, ev) && ev.response.success;
  report::Table indices({"index", "planned", "delivered", "delivered_with_transit"});
  if (evaluated) {
    for (std::size_t k = 0; k < ev.response.index_names.size(); ++k) {
      indices.addRow({ev.response.index_names[k], ev.response.planned_values[k], ev.response.delivered_values[k],
                      ev.response.with_transit_values[k]});
    }
  }
  auto index = [&](const std::string& name, const std::vector<double>& values) {
    for (std::size_t k = 0; k < ev.response.index_names.size(); ++k)
      if (ev.response.index_names[k] == name) return values[k];
    return std::nan("");
  };
  const bool success = r.status == "completed" && !r.delivered_s.empty() && max_error <= tolerance_s_ && evaluated;

  std::ostringstream json;
  json << "{\n  \"procedure\": \"hdr_delivery\",\n  \"scene\": \"" << p.case_name << "\",\n  \"success\": "
       << (success ? "true" : "false") << ",\n  \"status\": \"" << r.status << "\",\n  \"plan_id\": \"" << p.plan_id
       << "\",\n  \"method\": \"" << p.method << "\",\n  \"objective\": " << jsonNumber(p.objective)
       << ",\n  \"planned_dwell_s\": " << jsonNumber(planned) << ",\n  \"delivered_dwell_s\": "
       << jsonNumber(delivered) << ",\n  \"max_dwell_error_s\": " << jsonNumber(max_error)
       << ",\n  \"interruptions\": " << r.interruptions << ",\n  \"transit_in_patient_s\": "
       << jsonNumber(r.transit_in_patient_s) << ",\n  \"prostate_V100_delivered_pct\": "
       << jsonNumber(index("prostate_V100", ev.response.delivered_values)) << ",\n  \"prostate_D90_with_transit_Gy\": "
       << jsonNumber(index("prostate_D90", ev.response.with_transit_values)) << ",\n  \"transit_dose_max_Gy\": "
       << jsonNumber(ev.response.transit_dose_max_Gy) << ",\n  \"wall_s\": " << jsonNumber(wall_s) << "\n}\n";
  std::ostringstream md;
  md << "# HDR delivery — case `" << p.case_name << "`, plan `" << p.plan_id << "`\n\n"
     << "Plan (" << p.method << ", dissertation ch. 6): objective " << p.objective << ", " << planned
     << " s of dwell time in " << p.schedule.channels.size() << " channels, source S_K "
     << p.schedule.current_air_kerma_strength_U << " U (" << p.schedule.decay_days
     << " days after calibration). Delivery: " << r.status << " — " << r.message << "; " << r.interruptions
     << " interruption(s); source transit inside the patient " << r.transit_in_patient_s
     << " s (its dose is in the last column of the indices). Journal: `" << r.journal << "`.\n\n"
     << "## Dose indices (V in % of volume, D in Gy)\n\n" << indices.toMarkdown()
     << "\nLargest transit dose at a dose point: " << ev.response.transit_dose_max_Gy << " Gy.\n\n"
     << "## Planned vs delivered per dwell\n\n" << dwells.toMarkdown() << "\nResult: "
     << (success ? "PASS" : "FAIL") << ", largest dwell-time error " << max_error << " s (tolerance "
     << tolerance_s_ << " s), wall time " << wall_s << " s.\n";
  dwells.writeCsv(report_dir_ + "/delivery.csv");
  indices.writeCsv(report_dir_ + "/indices.csv");
  report::writeTextFile(report_dir_ + "/summary.md", md.str());
  report::writeTextFile(report_dir_ + "/summary.json", json.str());
  std::cout << "\n== HDR delivery of case '" << p.case_name << "' ==\n"
            << indices.toText() << (success ? "PASS" : "FAIL") << ": " << r.status << ", " << r.delivered_s.size()
            << " dwells, delivered " << delivered << " s of " << planned << " s planned, max dwell error "
            << max_error << " s, " << r.interruptions << " interruption(s), transit " << r.transit_in_patient_s
            << " s, " << wall_s << " s; report in " << report_dir_ << "\n"
            << std::flush;
  return success;
}

}  // namespace needle_guidance
