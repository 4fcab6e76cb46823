// ROS wrapper of the simulated insertion stage (node insertion_robot), rigid or steerable.
#pragma once

#include <ros/ros.h>
#include <std_srvs/Trigger.h>
#include "needle_guidance/ros/exclusive_action_server.h"

#include <cstdint>
#include <memory>
#include <string>

#include "needle_guidance/FlipBevelAction.h"
#include "needle_guidance/LinearMoveAction.h"
#include "needle_guidance/SetEntryPose.h"
#include "needle_guidance/SetEntryPose3.h"
#include "needle_guidance/Steer3Action.h"
#include "needle_guidance/robot/insertion_stage.h"
#include "needle_guidance/robot/steerable_needle.h"
#include "needle_guidance/robot/steerable_stage.h"
#include "needle_guidance/robot/steerable_stage_3d.h"
#include "needle_guidance/scene/scene.h"

namespace needle_guidance {

/// Owns the NodeHandles, reads and validates parameters once, runs the stage's control loop on
/// a timer and exposes CRTK-style topics, the motion actions and the e-stop services.
/// Throws std::runtime_error from the constructor on a missing or invalid parameter.
///
/// Modes (~mode: rigid | steerable | auto; auto, the default, is steerable when the scene has
/// models.steering, else rigid):
/// - rigid: a straight needle; "insertion" is the tip's x in frame scene (unchanged behaviour).
/// - steerable: the stage drives a bevel-tip needle through robot::SteerableNeedle, "the world"
///   of dissertation 5.3 (constant-curvature arcs, deflection beta ~ N(0, sigma_i) drawn at the
///   start of every insert goal, N(0, sigma_r) when a flip came before it, contact with expanded
///   obstacles and the workspace). The "insertion" joint is the inserted arc length (>= 0; 0 at
///   the entry point on the scene's line x = steering.start_x, up to the joint's upper limit),
///   "height" is the entry height (move_to_height moves the needle guide out of tissue, within
///   the scene's needle heights), "bevel" 0 = left, pi = right (flip_bevel turns the world's
///   bevel when the rotation completes; insertion is refused while the bevel is between the
///   two). insert / retract goals move the inserted length; an insert goal that makes contact
///   stops at the contact point and aborts with success = false and a message naming the
///   obstacle (or "left the workspace") and the point; insertion is then refused until a
///   retract goes back past the contact point. ~set_entry_pose (SetEntryPose) places the needle
///   guide at once, as a setup step rather than a motion: it is refused while the needle is in
///   tissue (inserted length > 0), while a motion runs or the e-stop is active, for an unknown
///   bevel, an angle outside [-pi/2, pi/2] or a height outside the scene's needle heights; on
///   success the stage's height and bevel joints jump to the entry height and bevel.
///   Publishes ~measured_tip (NeedleTip, frame scene, ground truth) at ~publish_rate_hz and
///   after every goal end, ~measured_cp (tip position, yaw = theta) and the latched
///   ~needle_path (Marker LINE_STRIP, frame scene). Deflections and contacts are journaled to
///   a second CSV next to ~journal_file ("X.csv" -> "X_needle.csv"), flushed per line.
///   The tf of the URDF (robot_state_publisher) still draws a straight needle.
/// - steerable_3d: robot::SteerableStage3d drives the 3-D bevel-tip needle of the
///   steering_3d scene ~scene_3d (noise scaled by ~noise_scale, seeded by ~seed). The action
///   ~steer (Steer3) rotates the needle about its axis ("axial_rotation" joint, at most its URDF
///   velocity limit and the scene's spin-rate limit) and then inserts a length with
///   duty-cycled spinning; unsafe goals are refused (steerable_stage_3d.h) and a contact stops
///   the insertion there (success = false, the obstacle named). ~set_entry_pose_3d
///   (SetEntryPose3) places the guide on the scene's entry disc (the height joint, anywhere in
///   its hardware range, only shows the stage); ~retract pulls the needle back
///   along its path; move_to_height, insert and flip_bevel are refused. Publishes ~measured_cp
///   (the true 3-D tip pose), ~needle_shape (latched: the needle's 3-D points, entry -> tip,
///   published and stamped when each motion ends, for the imagers' ~view along_z / along_y) and
///   ~needle_path (Marker); the 3-D journal goes to "X_needle3d.csv" next to ~journal_file.
/// - rigid on a tissue_3d scene (~scene a `kind: tissue_3d` file): the rigid needle of the 3-D
///   tissue procedures on the URDF's x-y stage (urdf/insertion_stage_3d.urdf): "height" is the
///   needle's y, "lateral" its z (action ~move_to_lateral, LinearMove), "insertion" the tip's x.
///   The scene's workspace bounds entry (stage range, or the template grid's extent) and the
///   depth (workspace.max_tip_x); height and lateral moves are refused with the tip in tissue.
/// measured_js also carries "axial_rotation" (0 outside steerable_3d), and "lateral" when the
/// URDF has that joint.
///
/// ~time_scale (in [1, 100], default 1): simulated seconds per wall second. The control loop
/// advances the stage by time_scale x the wall time between ticks, so goal velocities (and the
/// URDF's velocity limits) are in simulated time and a goal takes 1 / time_scale of its
/// simulated duration; result duration_s and mean_velocity_m_s are in simulated time. Topic
/// stamps stay ROS time.
class InsertionRobotRos {
public:
  InsertionRobotRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);

private:
  /// One goal at a time over all four actions: a goal sent while a motion runs is refused
  /// (preemption only through an explicit cancel of the running goal).
  using LinearMoveServer = ExclusiveActionServer<LinearMoveAction>;
  using FlipBevelServer = ExclusiveActionServer<FlipBevelAction>;
  /// Which action owns the running motion.
  enum class Owner { kNone, kHeight, kInsert, kRetract, kFlip, kSteer, kLateral };
  using Steer3Server = ExclusiveActionServer<Steer3Action>;

  /// Steerable mode: the needle world (seeded deflections), its journal, the initial entry.
  void setUpSteerableNeedle(const ros::NodeHandle& private_nh, const scene::Scene& scene,
                            const robot::JointLimits& bevel_limits, double initial_height_m,
                            double initial_bevel_rad, const std::string& journal_path);
  /// Topics, services and the four exclusive action servers.
  void advertiseInterfaces(const ros::NodeHandle& private_nh);
  void onLinearGoal(Owner owner, const LinearMoveGoal& goal);
  static robot::StageJoint linearJoint(Owner owner);
  void onFlipGoal(const FlipBevelGoal& goal);
  /// "" when no motion runs, else which one does (the exclusive servers' busy check).
  std::string runningMotion() const;
  void onPreempt(Owner owner);
  void onControlTimer(const ros::TimerEvent& event);
  bool onEstop(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  bool onResetEstop(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  void finishActiveGoal(bool success, const std::string& message);
  void publishState(const ros::Time& stamp);
  LinearMoveServer& linearServer(Owner owner);

  // Steerable mode.
  bool steerable() const { return static_cast<bool>(needle_); }
  bool onSetEntryPose(SetEntryPose::Request& req, SetEntryPose::Response& res);
  void publishNeedle(const ros::Time& stamp);

  // 3-D steerable mode.
  void setUpSteerable3d(const ros::NodeHandle& private_nh, const std::string& scene_file,
                        const robot::StageLimits& limits, const std::string& journal_path);
  void onSteerGoal(const Steer3Goal& goal);
  Steer3Result steerResult(bool success, const std::string& message) const;
  bool onSetEntryPose3(SetEntryPose3::Request& req, SetEntryPose3::Response& res);
  /// `moved`: a motion just ended; the needle's 3-D shape goes out on ~needle_shape too.
  void publishNeedle3(const ros::Time& stamp, bool moved = false);

  ros::NodeHandle nh_;
  std::unique_ptr<robot::InsertionStage> stage_;
  std::unique_ptr<robot::JournalFile> journal_file_;
  Owner owner_ = Owner::kNone;
  ros::Time goal_start_;
  double goal_start_position_ = 0.0;
  std::string last_message_;

  ros::Publisher measured_js_pub_;
  ros::Publisher measured_cp_pub_;
  ros::Publisher operating_state_pub_;
  ros::ServiceServer estop_srv_;
  ros::ServiceServer reset_estop_srv_;
  std::unique_ptr<LinearMoveServer> height_server_;
  std::unique_ptr<LinearMoveServer> insert_server_;
  std::unique_ptr<LinearMoveServer> retract_server_;
  std::unique_ptr<LinearMoveServer> lateral_server_;  ///< only with a lateral axis (3-D tissue)
  std::unique_ptr<FlipBevelServer> flip_server_;
  ros::Timer control_timer_;
  ros::Time last_step_;
  ros::Time last_publish_;
  double publish_period_s_ = 0.01;
  double time_scale_ = 1.0;  ///< simulated seconds per wall second

  // Steerable mode only (needle_ is null in rigid mode).
  std::unique_ptr<robot::SteerableNeedle> needle_;
  std::unique_ptr<robot::NeedleJournalFile> needle_journal_file_;
  double goal_target_ = 0.0;    ///< target of the running linear goal [m]
  double goal_velocity_ = 0.0;  ///< its velocity [m/s, simulated time]
  std::size_t published_path_version_ = static_cast<std::size_t>(-1);
  ros::Publisher measured_tip_pub_;
  ros::Publisher needle_path_pub_;
  ros::Publisher needle_shape_pub_;  ///< true needle shape (for the simulated imager)
  ros::Publisher drive_pub_;         ///< guide and joints (for the tip tracker's prediction)
  std::unique_ptr<robot::SteerableStage> steerable_;  ///< the stage driving the needle
  ros::ServiceServer set_entry_srv_;

  // 3-D steerable mode only (steer3d_ is null otherwise).
  std::unique_ptr<needle_model::Scene3d> scene3d_;
  std::unique_ptr<robot::SteerableStage3d> steer3d_;
  std::unique_ptr<robot::Journal3File> journal3_file_;
  std::unique_ptr<Steer3Server> steer_server_;
  ros::ServiceServer set_entry3_srv_;
};

}  // namespace needle_guidance
