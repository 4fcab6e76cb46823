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
#include "needle_guidance/report/table.h"
#include "needle_guidance/ros/params.h"

namespace needle_guidance {

namespace {

std::string jsonNumber(double v) { return report::jsonNumber(v, 8); }

}  // namespace

HdrProcedureRos::HdrProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh) : nh_(nh) {
  ROS_INFO("hdr_procedure parameters:");
  report_dir_ = ros_params::text(private_nh, "report_dir", "", true);
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
  DeliverGoal goal;
  goal.schedule = p.schedule;
  double fraction = 0.0;
  deliver.sendGoal(goal, {}, {}, [&](const DeliverFeedbackConstPtr& f) { fraction = f->delivered_fraction; });
  bool paused_once = pause_at_fraction_ < 0.0;
  const ros::WallTime deadline = t0 + ros::WallDuration(timeout_s_);
  while (!deliver.getState().isDone() && ros::ok() && ros::WallTime::now() < deadline) {
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
