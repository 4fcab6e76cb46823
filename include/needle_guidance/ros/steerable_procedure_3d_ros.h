// Procedure runner for 3-D closed-loop steerable-needle trials (node steerable_procedure_3d,
// issue 18). The world is simulated in this node: the core's noisy needle (needle_3d.h, seeded)
// stands in for a 3-D insertion robot and imager. Per trial it asks steering_planner_3d for a
// plan from the entry (~plan), places the tip at its start, then publishes the true tip pose,
// waits for the planner's control for it, inserts one step with noise, and repeats until the
// plan is completed (the tip refereed against the target ball) or the path touches an obstacle
// or leaves the tissue. The planner node is watched (NodeSupervisor): if it dies the run stops,
// the report names it (status node_died) and run() returns false. The trial loop and the report
// are ROS-free (procedures/steering_3d_trials.h).
#pragma once

#include <geometry_msgs/PoseWithCovarianceStamped.h>
#include <ros/ros.h>

#include <condition_variable>
#include <memory>
#include <mutex>
#include <optional>
#include <string>

#include "needle_guidance/SteeringControl3.h"
#include "needle_guidance/procedures/steering_3d_trials.h"

namespace needle_guidance {

class NodeSupervisor;

/// Reads its parameters once (throws std::runtime_error on a bad one, scene::SceneError on a bad
/// scene); run() executes the trials. Needs a spinner running (AsyncSpinner).
class SteerableProcedure3dRos {
public:
  SteerableProcedure3dRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);
  /// Runs the trials and writes the report (procedures::writeSteeringReport3) to ~report_dir.
  /// False on a fault: the planner never came up, a control did not come within
  /// ~control_timeout_s, a tip was refused, the planner node died, or the report could not be
  /// written. A fault ends the run (the report covers the trials run so far).
  bool run();

private:
  /// One trial; false on a fault (the trial is then marked as such).
  bool runTrial(procedures::SteeringTrial3& trial, std::uint64_t trial_seed,
                std::vector<double>& round_trip_ms);
  /// Publishes the tip and waits for the control answering it; nullopt after the timeout or
  /// once the supervisor has seen the planner die.
  std::optional<SteeringControl3> exchange(const steering_3d::TipPose3& tip);
  void onControl(const SteeringControl3ConstPtr& msg);
  void publishPath(const std::vector<steering_3d::Vector3>& path);

  ros::NodeHandle nh_;
  std::unique_ptr<steering_3d::Scene3d> scene_;
  std::unique_ptr<steering_3d::CollisionWorld3> world_;
  steering_3d::NoiseParams3 noise_;
  std::string planner_ns_;
  std::string report_dir_;
  int trials_ = 10;
  int max_steps_ = 200;
  long seed_ = 1;
  double control_timeout_s_ = 10.0;
  double startup_timeout_s_ = 30.0;
  double tip_sigma_m_ = 0.0;  ///< position std published with the tip (0: the truth) [m]
  ros::Publisher tip_pub_;
  ros::Publisher path_pub_;
  ros::Subscriber control_sub_;
  ros::ServiceClient plan_client_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::optional<SteeringControl3> last_control_;  ///< the answer to the tip stamped expected_stamp_
  NodeSupervisor* supervisor_ = nullptr;          ///< watches the planner while run() runs
  ros::Time expected_stamp_;
};

}  // namespace needle_guidance
