// Procedure runner: drives the insertion robot through every target of a scene (move to the
// target's height, insert to its depth, retract) with its actions and writes a report.
#pragma once

#include <ros/ros.h>

#include <string>

#include "needle_guidance/report/table.h"

namespace needle_guidance {

/// Reads its parameters once (throws std::runtime_error on a bad one); run() executes the
/// procedure. Needs a spinner running (it waits on actions and reads measured_cp).
class InsertionProcedureRos {
public:
  InsertionProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);
  /// Runs every target; returns true if every move succeeded within tolerance. Writes
  /// moves.csv, summary.json and summary.md to report_dir.
  bool run();

private:
  ros::NodeHandle nh_;
  std::string scene_spec_;
  std::string robot_ns_;
  std::string tissue_ns_;  ///< tissue_sim namespace; "" = no tissue (no seeds)
  std::string planner_ns_; ///< rigid_planner namespace; "" = aim at the target (no planning)
  /// Reset the tissue after each needle (each insertion independent, as dissertation 4.4
  /// assumes); false keeps earlier needle tracks in the tissue.
  bool reset_between_needles_ = true;
  std::string report_dir_;
  double insertion_velocity_m_s_ = 0.0;
  double retract_velocity_m_s_ = 0.0;
  double height_velocity_m_s_ = 0.0;
  double retract_depth_m_ = 0.0;
  double depth_tolerance_m_ = 0.0;
  double velocity_tolerance_ = 0.0;
  int max_targets_ = 0;
  double placement_tolerance_m_ = 1e-4;  ///< a seed within this of its target is placed [m]
};

}  // namespace needle_guidance
