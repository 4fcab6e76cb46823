// Procedure runner for closed-loop steerable-needle trials (dissertation 5.5, figure 5.8):
// asks steering_policy for the best start, places the needle there, then repeatedly reads the
// imaged tip pose, takes the policy's control for it (insert or flip + insert) and moves the
// simulated robot ("the world", random deflections) until the tip reaches the target, touches
// an obstacle or leaves the workspace. Repeats N trials and reports the success rate against
// the predicted P_s.
#pragma once

#include <ros/ros.h>

#include <string>
#include <utility>
#include <vector>

#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance {

/// Reads its parameters once (throws std::runtime_error on a bad one); run() executes the
/// trials. Needs a spinner running.
class SteerableProcedureRos {
public:
  SteerableProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);
  /// Runs the trials and writes trials.csv, paths.csv, ps_map.csv, summary.json/.md and
  /// plot.json to report_dir. True if every trial ran to an outcome and the success rate's 95 %
  /// interval contains the predicted P_s or lies above it.
  bool run();

private:
  ros::NodeHandle nh_;
  std::string scene_spec_;
  std::string target_;
  std::string robot_ns_;
  std::string policy_ns_;
  std::string report_dir_;
  std::string table_dir_;  ///< where steering_policy saves its table ("" = solve here)
  int trials_ = 0;
  int max_steps_ = 0;
  double insertion_velocity_m_s_ = 0.0;
  double retract_velocity_m_s_ = 0.0;
  double flip_velocity_rad_s_ = 0.0;
  double timeout_s_ = 0.0;
  long seed_ = 1;            ///< per-trial deflection streams (-1: the robot's own stream)
  int max_unconfident_ = 0;  ///< extra controls to wait for a confident tip before acting
  std::string feedback_;     ///< label for the report: ground_truth | image
  std::vector<std::string> watch_nodes_;  ///< nodes whose death stops the run (~watch_nodes)
};

}  // namespace needle_guidance
