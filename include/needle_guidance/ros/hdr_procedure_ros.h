// The HDR delivery procedure (dissertation ch. 6 end to end): plan -> schedule -> deliver ->
// evaluate, and the delivery report (node hdr_procedure).
#pragma once

#include <ros/ros.h>

#include <string>

namespace needle_guidance {

/// Reads parameters once (throws std::runtime_error on a bad one). run() asks `dwell_scheduler`
/// for a plan of the case, sends its schedule to the afterloader's `deliver` action (optionally
/// pausing it once at a delivered fraction, as an operator would), asks the scheduler to
/// evaluate what was delivered, and writes report_dir/{summary.json, summary.md, delivery.csv,
/// indices.csv}. Returns true when the delivery completed with every dwell within tolerance.
class HdrProcedureRos {
public:
  HdrProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);
  bool run();

private:
  ros::NodeHandle nh_;
  std::string report_dir_, case_dir_, dicom_dir_, method_, scheduler_, afterloader_;
  int synthetic_seed_ = 1;
  double pause_at_fraction_ = -1.0;
  double pause_wall_s_ = 1.0;
  double timeout_s_ = 600.0;
  double tolerance_s_ = 0.1;
};

}  // namespace needle_guidance
