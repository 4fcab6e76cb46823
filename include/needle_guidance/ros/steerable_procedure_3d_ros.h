// Procedure runner for 3-D closed-loop steerable-needle trials (node
// steerable_procedure_3d). The world is the insertion robot in its 3-D steerable mode
// (insertion_robot ~mode steerable_3d, ~robot_ns): per trial this node asks steering_planner_3d for
// a plan from the entry (~plan), retracts the needle and places the robot's guide at the plan's
// start (set_entry_pose_3d, the robot's noise reseeded with the trial's seed), then publishes the
// tip pose, waits for the planner's control for it, has the robot rotate and insert one step (the
// steer action), and repeats until the plan is completed (the tip refereed against the target
// ball) or the robot's needle touches an obstacle or leaves the tissue. The planner and the
// robot are watched (NodeSupervisor): if one dies the run stops, the report names it (status
// node_died) and run() returns false. ~tip_source: truth (the robot's true tip) or biplane: after
// every step it waits (up to ~control_timeout_s, then a fault naming the topic) for one frame of
// each of two imager nodes (~view along_z / along_y, subscribed as imager_along_z/image and
// imager_along_y/image) stamped at or after the step's goal was sent (the robot stamps the
// shape it publishes when the motion ends), detects the tip in each and triangulates them
// (imaging::BiplaneFusion3); the fused covariance goes out with ~tip. The trial loop and the
// report are ROS-free (procedures/steering_3d_trials.h).
#pragma once

#include <actionlib/client/simple_action_client.h>
#include <geometry_msgs/PoseWithCovarianceStamped.h>
#include <ros/ros.h>
#include <sensor_msgs/Image.h>

#include <atomic>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <optional>
#include <string>

#include "needle_guidance/LinearMoveAction.h"
#include "needle_guidance/Steer3Action.h"
#include "needle_guidance/SteeringControl3.h"
#include "needle_guidance/procedures/steering_3d_trials.h"
#include "needle_guidance/ros/latest.h"

namespace needle_guidance {

class NodeSupervisor;

/// Reads its parameters once (throws std::runtime_error on a bad one, scene::SceneError on a bad
/// scene); run() executes the trials. Needs a spinner running (AsyncSpinner).
class SteerableProcedure3dRos : private procedures::SteeringDevices3 {
public:
  SteerableProcedure3dRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);
  /// Runs the trials and writes the report (procedures::writeSteeringReport3) to ~report_dir.
  /// False on a fault: the planner never came up, a control did not come within
  /// ~control_timeout_s, a tip was refused, the planner node died, or the report could not be
  /// written. A fault ends the run (the report covers the trials run so far).
  bool run();

private:
  // procedures::SteeringDevices3: one trial (false on a fault), the supervisor's cause, the
  // retraction after the run (if the robot answers), the log.
  bool runTrial(procedures::SteeringTrial3& trial, std::uint64_t trial_seed) override;
  std::optional<std::string> fault() override;
  std::string leaveSafe() override;
  void progress(const std::string& line) override;
  /// Publishes the tip and waits for the control answering it; nullopt after the timeout or
  /// once the supervisor has seen the planner die.
  std::optional<SteeringControl3> exchange(const procedures::SteeringTrial3& trial);
  /// Retracts the robot's needle and places its guide at `entry`; "" or the fault.
  std::string placeRobot(const needle_model::TipPose3& entry, std::uint64_t seed);
  /// SteeringTrial3::WorldStep3 through the robot's steer action.
  bool robotStep(const needle_model::Control3& control, needle_model::TipPose3& tip,
                 steering_3d::TrialResult3& result);
  /// Retracts the needle out of the tissue (`death` as runGoal's); "" or why not.
  std::string retract(const std::function<std::optional<std::string>()>& death);

  ros::NodeHandle nh_;
  std::unique_ptr<needle_model::Scene3d> scene_;
  std::unique_ptr<needle_model::CollisionWorld3> world_;
  std::string planner_ns_;
  std::string robot_ns_;
  std::string report_dir_;
  int trials_ = 10;
  int max_steps_ = 200;
  long seed_ = 1;
  double control_timeout_s_ = 10.0;
  double startup_timeout_s_ = 30.0;
  double travel_m_ = 0.0;              ///< the insertion joint's travel (~robot_description) [m]
  std::vector<double> round_trip_ms_;  ///< tip-to-control latencies of the run
  double tip_sigma_m_ = 0.0;           ///< position std published with the tip (0: the truth) [m]
  ros::Publisher tip_pub_;
  std::unique_ptr<actionlib::SimpleActionClient<Steer3Action>> steer_;
  std::unique_ptr<actionlib::SimpleActionClient<LinearMoveAction>> retract_;
  ros::ServiceClient set_entry_;
  std::unique_ptr<imaging::BiplaneFusion3> fusion_;  ///< ~tip_source biplane; null: the truth
  ros::Subscriber view_subs_[2];                     ///< the imagers' images, along z and y
  Latest<sensor_msgs::Image> views_[2];              ///< their latest frames
  ros::Time step_sent_;  ///< when the last steer goal was sent: later frames show its end
  ros::Subscriber control_sub_;
  ros::ServiceClient plan_client_;
  Latest<SteeringControl3> controls_;          ///< the planner's latest answer to this node's tip
  std::atomic<std::uint64_t> expected_ns_{0};  ///< the stamp of this node's last tip [ns]
  NodeSupervisor* supervisor_ = nullptr;  ///< watches the planner and the robot while run() runs
};

}  // namespace needle_guidance
