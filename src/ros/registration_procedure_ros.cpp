#include "needle_guidance/ros/registration_procedure_ros.h"

#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/Register.h"
#include "needle_guidance/report/statistics.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/report/output_path.h"
#include "needle_guidance/ros/params.h"

namespace needle_guidance {

RegistrationProcedureRos::RegistrationProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh)
    : nh_(nh) {
  ROS_INFO("registration_procedure parameters:");
  report_dir_ = ros_params::text(private_nh, "report_dir", "", true);
  // Refuses a system folder or someone else's non-empty folder before anything runs.
  report::prepareReportDir(report_dir_, private_nh.resolveName("report_dir"),
                           ros_params::flag(private_nh, "allow_system_paths", false));
  service_ = ros_params::text(private_nh, "service", "registration/register");
  cases_per_probe_ = ros_params::integer(private_nh, "cases_per_probe", 5, 1, 100, "cases");
}

bool RegistrationProcedureRos::run() {
  ros::ServiceClient client = nh_.serviceClient<Register>(service_);
  if (!client.waitForExistence(ros::Duration(60.0))) {
    ROS_FATAL_STREAM("registration_procedure: " << service_ << " did not come up in 60 s");
    return false;
  }
  report::Table table({"probe", "seed", "status", "dice", "initial_dice", "point_error_mm",
                       "rigid_point_error_mm", "unregistered_point_error_mm", "seconds",
                       "iterations", "cg_kPa", "pz_kPa", "surrounding_kPa", "message"},
                      6);
  report::Table errors({"case", "method", "point_error_mm"}, 6);
  std::vector<double> dice, err, rigid, seconds;
  bool all_ok = true;
  int index = 0;
  for (const std::string probe : {"balloon", "rigid"}) {
    for (long seed = 1; seed <= cases_per_probe_; ++seed) {
      Register srv;
      srv.request.synthetic_seed = static_cast<std::uint64_t>(seed);
      srv.request.probe_type = probe;
      srv.request.alpha = -1.0;
      if (!client.call(srv)) {
        ROS_ERROR_STREAM("registration_procedure: the call for " << probe << " " << seed << " failed");
        all_ok = false;
        continue;
      }
      const auto& r = srv.response;
      all_ok = all_ok && r.success;
      const auto kpa = [&](std::size_t i) { return i < r.modulus_kPa.size() ? r.modulus_kPa[i] : 0.0; };
      table.addRow({probe, double(seed), r.status, r.dice, r.initial_dice, r.point_error_mm,
                    r.rigid_point_error_mm, r.unregistered_point_error_mm, r.seconds,
                    double(r.iterations), kpa(1), kpa(2), kpa(0), r.message});
      ++index;
      errors.addRow({double(index), std::string("ours"), r.point_error_mm});
      errors.addRow({double(index), std::string("rigid_com"), r.rigid_point_error_mm});
      errors.addRow({double(index), std::string("none"), r.unregistered_point_error_mm});
      if (r.success) {
        dice.push_back(r.dice);
        err.push_back(r.point_error_mm);
        rigid.push_back(r.rigid_point_error_mm);
        seconds.push_back(r.seconds);
      }
      ROS_INFO_STREAM("registration_procedure: " << probe << " case " << seed << ": " << r.status
                      << ", Dice " << r.dice << ", point error " << r.point_error_mm
                      << " mm (rigid " << r.rigid_point_error_mm << " mm), " << r.seconds << " s");
    }
  }
  std::ostringstream json;
  json << "{\n  \"procedure\": \"registration\",\n  \"scene\": \"synthetic_probe_cases\""
       << ",\n  \"success\": " << (all_ok ? "true" : "false")
       << ",\n  \"cases\": " << table.rowCount()
       << ",\n  \"dice_mean\": " << report::jsonNumber(report::mean(dice))
       << ",\n  \"point_error_mm_mean\": " << report::jsonNumber(report::mean(err))
       << ",\n  \"rigid_point_error_mm_mean\": " << report::jsonNumber(report::mean(rigid))
       << ",\n  \"seconds_per_slice_mean\": " << report::jsonNumber(report::mean(seconds)) << "\n}\n";
  table.writeCsv(report_dir_ + "/cases.csv");
  errors.writeCsv(report_dir_ + "/point_errors.csv");
  report::writeTextFile(report_dir_ + "/summary.json", json.str());
  report::writeTextFile(report_dir_ + "/summary.md",
                    "# Deformable registration of " + std::to_string(table.rowCount()) +
                        " synthetic probe-in / probe-out slices\n\n" + table.toMarkdown());
  report::writeTextFile(report_dir_ + "/plot.json",
                    "[{\"csv\": \"point_errors.csv\", \"x\": \"case\", \"y\": \"point_error_mm\", "
                    "\"group\": \"method\", \"points\": true, \"title\": \"Test-point error per case "
                    "(1-5 balloon, 6-10 rigid probe)\", \"png\": \"point_errors.png\"}]\n");
  std::cout << "\n== Registration: " << dice.size() << " / " << table.rowCount()
            << " slices registered, Dice mean " << report::mean(dice) << ", point error mean "
            << report::mean(err) << " mm (rigid centre of mass " << report::mean(rigid) << " mm), "
            << report::mean(seconds) << " s per slice ==\nreport in " << report_dir_ << "\n"
            << std::flush;
  return all_ok;
}

}  // namespace needle_guidance
