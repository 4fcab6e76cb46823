#include "needle_guidance/ros/registration_procedure_ros.h"

#include <iostream>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/Register.h"
#include "needle_guidance/report/output_path.h"
#include "needle_guidance/report/plot.h"
#include "needle_guidance/report/statistics.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/ros/node_supervisor.h"
#include "needle_guidance/ros/params.h"

namespace needle_guidance {
namespace {

/// Test-point error per case for ours, the rigid baseline and no registration (a plain roslaunch
/// writes the figure too).
void writePointErrorPlot(const report::Table& errors, const std::string& path) {
  report::LinePlot plot("Test-point error per case (1-5 balloon, 6-10 rigid probe)", "case",
                        "point error [mm]");
  const char* methods[] = {"ours", "rigid_com", "none"};
  for (std::size_t m = 0; m < 3; ++m) {
    std::vector<double> x, y;
    for (std::size_t r = 0; r < errors.rowCount(); r += 3) {
      x.push_back(errors.number(r + m, "case"));
      y.push_back(errors.number(r + m, "point_error_mm"));
    }
    plot.addPoints(methods[m], x, y, report::seriesColour(m), 5);
  }
  plot.save(path);
}

}  // namespace

RegistrationProcedureRos::RegistrationProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh)
    : nh_(nh) {
  ROS_INFO("registration_procedure parameters:");
  report_dir_ = ros_params::text(private_nh, "report_dir", "", true);
  // Refuses a system folder or someone else's non-empty folder before anything runs.
  report::prepareReportDir(report_dir_, private_nh.resolveName("report_dir"),
                           ros_params::flag(private_nh, "allow_system_paths", false));
  service_ = ros_params::text(private_nh, "service", "registration/register");
  cases_per_probe_ = ros_params::integer(private_nh, "cases_per_probe", 5, 1, 100, "cases");
  watch_node_ = ros_params::text(private_nh, "watch_node", "registration");
}

bool RegistrationProcedureRos::run() {
  // Watches the registration node from the start: one that never comes up (it refused its
  // parameters) or dies during a case ends the run at once with a report that names it.
  NodeSupervisor supervisor(nh_, {watch_node_});
  std::optional<NodeSupervisor::Death> death;
  const auto missing = supervisor.waitForAll(60.0);
  supervisor.clear();
  ros::ServiceClient client = nh_.serviceClient<Register>(service_);
  if (!missing.empty() || !client.waitForExistence(ros::Duration(60.0))) {
    death = NodeSupervisor::Death{missing.empty() ? service_ : missing.front(),
                                  ros::WallTime::now(), "did not come up within 60 s"};
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
    for (long seed = 1; seed <= cases_per_probe_ && !death; ++seed) {
      Register srv;
      srv.request.synthetic_seed = static_cast<std::uint64_t>(seed);
      srv.request.probe_type = probe;
      srv.request.alpha = -1.0;
      if (!client.call(srv)) {
        supervisor.checkNow();
        death = supervisor.death();
        if (!death)
          death = NodeSupervisor::Death{service_, ros::WallTime::now(), "the call failed"};
        ROS_ERROR_STREAM("registration_procedure: the call for "
                         << probe << " " << seed << " failed: " << death->toString());
        break;
      }
      const auto& r = srv.response;
      all_ok = all_ok && r.success;
      const auto kpa = [&](std::size_t i) {
        return i < r.modulus_kPa.size() ? r.modulus_kPa[i] : 0.0;
      };
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
      ROS_INFO_STREAM("registration_procedure: "
                      << probe << " case " << seed << ": " << r.status << ", Dice " << r.dice
                      << ", point error " << r.point_error_mm << " mm (rigid "
                      << r.rigid_point_error_mm << " mm), " << r.seconds << " s");
    }
  }
  all_ok = all_ok && !death;
  std::ostringstream json;
  json << "{\n  \"procedure\": \"registration\",\n  \"scene\": \"synthetic_probe_cases\""
       << ",\n  \"success\": " << (all_ok ? "true" : "false");
  if (death) {
    json << ",\n  \"status\": \"node_died\",\n  \"dead_node\": \"" << death->node
         << "\",\n  \"cause\": \"" << death->toString() << "; stopped after " << table.rowCount()
         << " of " << 2 * cases_per_probe_
         << " cases\",\n  \"detected_unix_s\": " << report::jsonNumber(death->when.toSec(), 15);
  }
  json << ",\n  \"cases\": " << table.rowCount()
       << ",\n  \"dice_mean\": " << report::jsonNumber(report::mean(dice))
       << ",\n  \"point_error_mm_mean\": " << report::jsonNumber(report::mean(err))
       << ",\n  \"rigid_point_error_mm_mean\": " << report::jsonNumber(report::mean(rigid))
       << ",\n  \"seconds_per_slice_mean\": " << report::jsonNumber(report::mean(seconds))
       << "\n}\n";
  table.writeCsv(report_dir_ + "/cases.csv");
  errors.writeCsv(report_dir_ + "/point_errors.csv");
  report::writeTextFile(report_dir_ + "/summary.json", json.str());
  report::writeTextFile(report_dir_ + "/summary.md",
                        "# Deformable registration of " + std::to_string(table.rowCount()) +
                            " synthetic probe-in / probe-out slices\n\n" + table.toMarkdown());
  writePointErrorPlot(errors, report_dir_ + "/point_errors.png");
  report::writeTextFile(
      report_dir_ + "/plot.json",
      "[{\"csv\": \"point_errors.csv\", \"x\": \"case\", \"y\": \"point_error_mm\", "
      "\"group\": \"method\", \"points\": true, \"title\": \"Test-point error per case "
      "(1-5 balloon, 6-10 rigid probe)\", \"png\": \"point_errors.png\"}]\n");
  if (death)
    std::cout << "\nFAIL: " << death->toString() << "; stopped after " << table.rowCount()
              << " cases\n";
  std::cout << "\n== Registration: " << dice.size() << " / " << table.rowCount()
            << " slices registered, Dice mean " << report::mean(dice) << ", point error mean "
            << report::mean(err) << " mm (rigid centre of mass " << report::mean(rigid) << " mm), "
            << report::mean(seconds) << " s per slice ==\nreport in " << report_dir_ << "\n"
            << std::flush;
  return all_ok;
}

}  // namespace needle_guidance
