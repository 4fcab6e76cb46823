// Procedure runner for deformable registration (dissertation 3.3): asks the registration node
// to register the seeded synthetic probe-out / probe-in cases (balloon and rigid probes) and
// writes the report: per case Dice, test-point error against the rigid centre-of-mass baseline
// and against no registration, estimated moduli and time.
#include <ros/ros.h>

#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/Register.h"
#include "needle_guidance/report/statistics.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/ros/params.h"

int main(int argc, char** argv) {
  namespace ng = needle_guidance;
  ros::init(argc, argv, "registration_procedure");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    ROS_INFO("registration_procedure parameters:");
    const std::string report_dir = ng::ros_params::text(private_nh, "report_dir", "", true);
    const std::string service = ng::ros_params::text(private_nh, "service", "registration/register");
    const long cases = ng::ros_params::integer(private_nh, "cases_per_probe", 5, 1, 100, "cases");
    ros::ServiceClient client = nh.serviceClient<ng::Register>(service);
    if (!client.waitForExistence(ros::Duration(60.0))) {
      ROS_FATAL_STREAM("registration_procedure: " << service << " did not come up in 60 s");
      return 1;
    }
    ng::report::Table table({"probe", "seed", "status", "dice", "initial_dice", "point_error_mm",
                             "rigid_point_error_mm", "unregistered_point_error_mm", "seconds",
                             "iterations", "cg_kPa", "pz_kPa", "surrounding_kPa", "message"},
                            6);
    ng::report::Table errors({"case", "method", "point_error_mm"}, 6);
    std::vector<double> dice, err, rigid, seconds;
    bool all_ok = true;
    int index = 0;
    for (const std::string probe : {"balloon", "rigid"}) {
      for (long seed = 1; seed <= cases; ++seed) {
        ng::Register srv;
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
    namespace rp = ng::report;
    std::ostringstream json;
    json << "{\n  \"procedure\": \"registration\",\n  \"scene\": \"synthetic_probe_cases\""
         << ",\n  \"success\": " << (all_ok ? "true" : "false")
         << ",\n  \"cases\": " << table.rowCount()
         << ",\n  \"dice_mean\": " << rp::jsonNumber(rp::mean(dice))
         << ",\n  \"point_error_mm_mean\": " << rp::jsonNumber(rp::mean(err))
         << ",\n  \"rigid_point_error_mm_mean\": " << rp::jsonNumber(rp::mean(rigid))
         << ",\n  \"seconds_per_slice_mean\": " << rp::jsonNumber(rp::mean(seconds)) << "\n}\n";
    table.writeCsv(report_dir + "/cases.csv");
    errors.writeCsv(report_dir + "/point_errors.csv");
    rp::writeTextFile(report_dir + "/summary.json", json.str());
    rp::writeTextFile(report_dir + "/summary.md",
                      "# Deformable registration of " + std::to_string(table.rowCount()) +
                          " synthetic probe-in / probe-out slices\n\n" + table.toMarkdown());
    rp::writeTextFile(report_dir + "/plot.json",
                      "[{\"csv\": \"point_errors.csv\", \"x\": \"case\", \"y\": \"point_error_mm\", "
                      "\"group\": \"method\", \"points\": true, \"title\": \"Test-point error per case "
                      "(1-5 balloon, 6-10 rigid probe)\", \"png\": \"point_errors.png\"}]\n");
    std::cout << "\n== Registration: " << dice.size() << " / " << table.rowCount()
              << " slices registered, Dice mean " << rp::mean(dice) << ", point error mean "
              << rp::mean(err) << " mm (rigid centre of mass " << rp::mean(rigid) << " mm), "
              << rp::mean(seconds) << " s per slice ==\nreport in " << report_dir << "\n"
              << std::flush;
    return all_ok ? 0 : 1;
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("registration_procedure: " << e.what());
    return 1;
  }
}
