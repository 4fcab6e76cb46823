// Procedure runner for deformable registration (dissertation 3.3): asks the registration node
// to register the seeded synthetic probe-out / probe-in cases (balloon and rigid probes) and
// writes the report: per case Dice, test-point error against the rigid centre-of-mass baseline
// and against no registration, estimated moduli and time.
#pragma once

#include <ros/ros.h>

#include <string>

namespace needle_guidance {

/// Reads its parameters once (throws std::runtime_error on a bad one); run() registers the
/// cases and writes cases.csv, point_errors.csv, summary.json/.md and plot.json to report_dir.
class RegistrationProcedureRos {
public:
  RegistrationProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);
  /// True if every case was registered (a mapping was computed).
  bool run();

private:
  ros::NodeHandle nh_;
  std::string report_dir_;
  std::string service_;
  std::string watch_node_;  ///< the registration node, watched (NodeSupervisor)
  long cases_per_probe_ = 0;
};

}  // namespace needle_guidance
