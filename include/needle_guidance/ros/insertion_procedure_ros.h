// Procedure runner: drives the insertion robot through every target of a scene (move to the
// target's height, insert to its depth, retract) with its actions and writes a report.
#pragma once

#include <ros/ros.h>

#include <string>

#include "needle_guidance/procedures/rigid_implant.h"

namespace needle_guidance {

/// Reads its parameters once (throws std::runtime_error on a bad one); run() executes the
/// procedure. Needs a spinner running (it waits on actions and reads measured_cp).
class InsertionProcedureRos {
public:
  InsertionProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);
  /// Runs procedures::RigidImplantProcedure over ROS devices, watching the robot, tissue_sim and
  /// rigid_planner nodes; true if every target was placed (unplanned: every move succeeded).
  /// Writes moves.csv, summary.json, summary.md and seed_errors.png to report_dir; a node death
  /// stops the robot safely and the report names the node, the time and the targets tried.
  bool run();

private:
  ros::NodeHandle nh_;
  std::string scene_spec_;
  std::string robot_ns_;
  std::string tissue_ns_;   ///< tissue_sim namespace; "" = no tissue (no seeds)
  std::string planner_ns_;  ///< rigid_planner namespace; "" = aim at the target (no planning)
  std::string report_dir_;
  procedures::RigidImplantSettings settings_;
};

}  // namespace needle_guidance
