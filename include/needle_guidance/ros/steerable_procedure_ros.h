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

#include "needle_guidance/procedures/steerable_trials.h"

namespace needle_guidance {

/// Reads its parameters once (throws std::runtime_error on a bad one); run() executes the
/// trials (procedures::SteerableTrials on the ROS devices). Needs a spinner running.
class SteerableProcedureRos {
public:
  struct Settings {
    std::string scene_spec, target, robot_ns, policy_ns, report_dir;
    std::string table_dir;  ///< where steering_policy saves its table ("" = solve here)
    procedures::SteerableSettings trials;
    double insertion_velocity_m_s = 0.0;
    double retract_velocity_m_s = 0.0;
    double flip_velocity_rad_s = 0.0;
    double timeout_s = 0.0;
    /// How long the policy may take to come up: it chooses and solves its model first [s].
    double policy_wait_s = 0.0;
    int max_unconfident = 0;  ///< extra controls to wait for a confident tip before acting
    std::vector<std::string> watch_nodes;  ///< nodes whose death stops the run (~watch_nodes)
  };

  SteerableProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);
  /// Runs the trials and writes the report (procedures::SteerableReport::write) to report_dir.
  /// True if every trial ran to an outcome and, with ground-truth feedback, the success rate's
  /// 95 % interval contains the predicted P_s or lies above it.
  bool run();

private:
  ros::NodeHandle nh_;
  Settings s_;
};

}  // namespace needle_guidance
