#include "needle_guidance/ros/insertion_robot_ros.h"

#include <visualization_msgs/Marker.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <iomanip>
#include <optional>
#include <sstream>

#include "needle_guidance/NeedleDrive.h"
#include "needle_guidance/NeedleShape.h"
#include "needle_guidance/NeedleTip.h"
#include "needle_guidance/OperatingState.h"
#include "needle_guidance/report/output_path.h"
#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/conversions_3d.h"
#include "needle_guidance/ros/params.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/tissue_3d/scene_tissue_3d.h"

namespace needle_guidance {
namespace {

using robot::LinearCommand;
using robot::StageJoint;

constexpr double kRadPerDeg = 3.14159265358979323846 / 180.0;
/// Spacing of the points of ~needle_path along the arcs [m].
constexpr double kPathSpacing_m = 5e-4;
/// Line width of ~needle_path [m].
constexpr double kPathWidth_m = 1e-3;

/// Entry and depth limits of a tissue_3d scene: the stage range (or the template grid's
/// extent), the deepest tip x and the block's entry face.
robot::SceneLimits tissue3dLimits(const std::string& scene_file) {
  const tissue_3d::TissueScene3d scene = tissue_3d::loadTissueScene3d(scene_file);
  const tissue_3d::Workspace3& w = scene.workspace;
  robot::SceneLimits limits;
  if (w.use_template) {
    limits.min_height_m = w.template_origin_m.x();
    limits.max_height_m = w.template_origin_m.x() + (w.template_rows - 1) * w.template_spacing_m;
    limits.min_lateral_m = w.template_origin_m.y();
    limits.max_lateral_m =
        w.template_origin_m.y() + (w.template_columns - 1) * w.template_spacing_m;
  } else {
    limits.min_height_m = w.y_min_m;
    limits.max_height_m = w.y_max_m;
    limits.min_lateral_m = w.z_min_m;
    limits.max_lateral_m = w.z_max_m;
  }
  limits.max_depth_m = w.max_tip_x_m;
  limits.entry_x_m = scene.block_min_m.x();
  return limits;
}

// Steerable-mode conversions, local to this node (its only user).

NeedleTip toNeedleTip(const steering::TipPose& tip, double inserted_length_m,
                      const ros::Time& stamp) {
  NeedleTip msg;
  msg.header.stamp = stamp;
  msg.header.frame_id = "scene";
  msg.pose.x = tip.p_SceneTip.x();
  msg.pose.y = tip.p_SceneTip.y();
  msg.pose.theta = tip.theta_rad;
  msg.bevel = steering::toString(tip.bevel);
  msg.inserted_length_m = inserted_length_m;
  msg.source = "ground_truth";
  msg.confident = true;  // covariance stays zero: the world's own tip is exact
  return msg;
}

/// Tip position with the tangent as yaw about +z of frame scene.
geometry_msgs::PoseStamped toPoseStamped(const steering::TipPose& tip, const ros::Time& stamp) {
  geometry_msgs::PoseStamped msg;
  msg.header.stamp = stamp;
  msg.header.frame_id = "scene";
  msg.pose.position = ros_conversions::toMessage(tip.p_SceneTip);
  msg.pose.orientation.z = std::sin(0.5 * tip.theta_rad);
  msg.pose.orientation.w = std::cos(0.5 * tip.theta_rad);
  return msg;
}

/// The inserted needle as a LINE_STRIP (DELETE while nothing is inserted).
visualization_msgs::Marker toPathMarker(const robot::SteerableNeedle& needle,
                                        const ros::Time& stamp) {
  visualization_msgs::Marker m;
  m.header.stamp = stamp;
  m.header.frame_id = "scene";
  m.ns = "needle_path";
  m.id = 0;
  m.type = visualization_msgs::Marker::LINE_STRIP;
  m.pose.orientation.w = 1.0;
  if (!(needle.insertedLength_m() > 0.0)) {
    m.action = visualization_msgs::Marker::DELETE;
    return m;
  }
  m.action = visualization_msgs::Marker::ADD;
  m.scale.x = kPathWidth_m;
  m.color.r = 0.85F;  // red: visible over the blue-to-yellow P_s map
  m.color.g = 0.1F;
  m.color.b = 0.1F;
  m.color.a = 1.0F;
  for (const geometry::Point2& p : needle.pathPoints(kPathSpacing_m)) {
    m.points.push_back(ros_conversions::toMessage(p));
    m.points.back().z = 0.001;  // in front of the scene's filled regions
  }
  return m;
}

}  // namespace

void InsertionRobotRos::setUpSteerableNeedle(const ros::NodeHandle& private_nh,
                                             const scene::Scene& scene, const robot::JointLimits& b,
                                             double initial_height_m, double initial_bevel_rad,
                                             const std::string& journal_path) {
  if (initial_bevel_rad != b.lower && initial_bevel_rad != b.upper) {
    throw std::runtime_error("parameter '" + private_nh.resolveName("initial_bevel_rad") +
                             "' must be " + std::to_string(b.lower) + " (left) or " +
                             std::to_string(b.upper) + " (right) in steerable mode");
  }
  const scene::Steering& st = *scene.steering;
  robot::SteerableNeedleConfig config;
  config.start_x_m = st.start_x_m;
  config.min_height_m = scene.needle.min_height_m;
  config.max_height_m = scene.needle.max_height_m;
  config.seed = static_cast<std::uint64_t>(
      ros_params::integer(private_nh, "seed", 1, 0, 9007199254740992L, ""));
  config.sigma_insert_rad =
      kRadPerDeg * ros_params::number(private_nh, "sigma_insert_deg",
                                      st.sigma_insert_rad / kRadPerDeg, 0.0, 90.0, "deg");
  config.sigma_flip_rad =
      kRadPerDeg * ros_params::number(private_nh, "sigma_flip_deg", st.sigma_flip_rad / kRadPerDeg,
                                      0.0, 90.0, "deg");
  robot::EntryPose entry;
  entry.height_m = initial_height_m;
  entry.angle_rad = 0.0;
  entry.bevel = initial_bevel_rad == b.lower ? steering::Bevel::kLeft : steering::Bevel::kRight;
  try {
    needle_ = std::make_unique<robot::SteerableNeedle>(
        steering::planarWorkspace(steering::problemFromScene(scene)), config, entry);
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(std::string("steerable needle: ") + e.what());
  }
  if (!journal_path.empty()) {
    const std::string needle_path = robot::companionJournalPath(journal_path, false);
    needle_journal_file_ = std::make_unique<robot::NeedleJournalFile>(needle_path);
    needle_->setJournalSink([this](const robot::NeedleJournalEntry& e) {
      needle_journal_file_->write(e, stage_->state().time_s);
    });
    ROS_INFO_STREAM("insertion_robot: needle journal appended to " << needle_path);
  }
  // The initial entry goes into the journal like every later one.
  needle_->setEntry(entry);
  steerable_ = std::make_unique<robot::SteerableStage>(*stage_, *needle_);
}

void InsertionRobotRos::setUpSteerable3d(const ros::NodeHandle& private_nh,
                                         const std::string& scene_file,
                                         const robot::StageLimits& limits,
                                         const std::string& journal_path) {
  scene3d_ = std::make_unique<needle_model::Scene3d>(needle_model::loadScene3d(scene_file));
  const double noise = ros_params::number(private_nh, "noise_scale", 1.0, 0.0, 10.0, "x sigma");
  const auto seed = ros_params::integer(private_nh, "seed", 1, 0, 9007199254740992L, "");
  steer3d_ = std::make_unique<robot::SteerableStage3d>(
      *stage_, *scene3d_, scene3d_->noise.scaled(noise), limits.spin_rate_max_rad_s,
      static_cast<std::uint64_t>(seed));
  if (!journal_path.empty()) {
    journal3_file_ =
        std::make_unique<robot::Journal3File>(robot::companionJournalPath(journal_path, true));
    steer3d_->setJournalSink([this](const robot::Journal3Entry& e) { journal3_file_->write(e); });
  }
}

void InsertionRobotRos::advertiseInterfaces(const ros::NodeHandle& private_nh) {
  ros::NodeHandle robot_nh(private_nh);
  measured_js_pub_ = robot_nh.advertise<sensor_msgs::JointState>("measured_js", 10);
  measured_cp_pub_ = robot_nh.advertise<geometry_msgs::PoseStamped>("measured_cp", 10);
  operating_state_pub_ = robot_nh.advertise<OperatingState>("operating_state", 1, true);
  estop_srv_ = robot_nh.advertiseService("estop", &InsertionRobotRos::onEstop, this);
  reset_estop_srv_ =
      robot_nh.advertiseService("reset_estop", &InsertionRobotRos::onResetEstop, this);
  // Served in both modes so that clients get an answer; rigid mode refuses it.
  set_entry_srv_ =
      robot_nh.advertiseService("set_entry_pose", &InsertionRobotRos::onSetEntryPose, this);
  if (steerable()) {
    measured_tip_pub_ = robot_nh.advertise<NeedleTip>("measured_tip", 10);
    needle_shape_pub_ = robot_nh.advertise<NeedleShape>("needle_shape", 10);
    drive_pub_ = robot_nh.advertise<NeedleDrive>("drive", 10);
    needle_path_pub_ = robot_nh.advertise<visualization_msgs::Marker>("needle_path", 1, true);
  } else if (steer3d_) {
    needle_path_pub_ = robot_nh.advertise<visualization_msgs::Marker>("needle_path", 1, true);
    needle_shape_pub_ = robot_nh.advertise<NeedleShape>("needle_shape", 1, true);
    set_entry3_srv_ =
        robot_nh.advertiseService("set_entry_pose_3d", &InsertionRobotRos::onSetEntryPose3, this);
    steer_server_ = std::make_unique<Steer3Server>(
        robot_nh, "steer", [this] { return runningMotion(); },
        [this](const Steer3Goal& goal) { onSteerGoal(goal); },
        [this] { onPreempt(Owner::kSteer); });
    steer_server_->start();
  }

  auto make_linear = [&](const std::string& name, Owner owner) {
    auto server = std::make_unique<LinearMoveServer>(
        robot_nh, name, [this] { return runningMotion(); },
        [this, owner](const LinearMoveGoal& goal) { onLinearGoal(owner, goal); },
        [this, owner] { onPreempt(owner); });
    server->start();
    return server;
  };
  height_server_ = make_linear("move_to_height", Owner::kHeight);
  insert_server_ = make_linear("insert", Owner::kInsert);
  retract_server_ = make_linear("retract", Owner::kRetract);
  if (stage_->limits().has_lateral) {
    lateral_server_ = make_linear("move_to_lateral", Owner::kLateral);
  }
  flip_server_ = std::make_unique<FlipBevelServer>(
      robot_nh, "flip_bevel", [this] { return runningMotion(); },
      [this](const FlipBevelGoal& goal) { onFlipGoal(goal); }, [this] { onPreempt(Owner::kFlip); });
  flip_server_->start();
}

InsertionRobotRos::InsertionRobotRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh) : nh_(nh) {
  ROS_INFO("insertion_robot parameters:");
  const std::string scene_spec = ros_params::text(private_nh, "scene", "prostate_sagittal");
  const std::string description_param =
      ros_params::text(private_nh, "robot_description_param", "robot_description");
  std::string urdf_xml;
  if (!nh.getParam(description_param, urdf_xml)) {
    throw std::runtime_error("parameter '" + nh.resolveName(description_param) +
                             "' (the stage URDF) is not set");
  }
  robot::StageLimits limits = robot::parseStageLimits(urdf_xml);
  // One ~scene, dispatched on its kind: a steering_3d file selects the 3-D steerable mode.
  const std::string kind = scene::sceneKind(scene_spec);
  const bool scene_is_3d = kind == "steering_3d";
  const bool tissue3d = kind == "tissue_3d";
  const std::string mode = ros_params::text(private_nh, "mode", "auto");
  const bool steerable3d = mode == "steerable_3d" || (mode == "auto" && scene_is_3d);
  if (mode != "auto" && mode != "rigid" && mode != "steerable" && mode != "steerable_3d") {
    throw std::runtime_error("parameter '" + private_nh.resolveName("mode") + "' = '" + mode +
                             "' is not rigid, steerable, steerable_3d or auto");
  }
  if (steerable3d != scene_is_3d) {
    throw std::runtime_error("parameter '" + private_nh.resolveName("scene") + "' = '" +
                             scene_spec + "': ~mode " + mode +
                             (scene_is_3d ? " cannot drive a steering_3d scene (use auto)"
                                          : " needs a steering_3d scene file"));
  }
  if (tissue3d && (mode == "steerable" || mode == "steerable_3d" || !limits.has_lateral)) {
    throw std::runtime_error(
        "parameter '" + private_nh.resolveName("scene") + "' = '" + scene_spec +
        "' (a tissue_3d scene) needs ~mode rigid or auto and a stage URDF with the 'lateral' "
        "joint (urdf/insertion_stage_3d.urdf)");
  }
  const scene::Scene scene =
      scene_is_3d || tissue3d ? scene::Scene{} : scene::loadSceneSpec(scene_spec);
  const bool steerable_mode = mode == "steerable" || (mode == "auto" && scene.steering);
  if (steerable_mode && !scene.steering) {
    throw std::runtime_error("~mode steerable needs a scene with models.steering; scene '" +
                             scene.name + "' has none");
  }
  if (steerable_mode) {
    // The planar steerable stage's height travel spans the scene's workspace, so every
    // workspace the scene loader accepts can be driven (the URDF's travel is the rigid stage's).
    robot::JointLimits& travel = limits.joints[static_cast<std::size_t>(StageJoint::kHeight)];
    travel.lower = scene.workspace_min.y();
    travel.upper = scene.workspace_max.y();
  }
  const auto& h = limits[StageJoint::kHeight];
  const auto& d = limits[StageJoint::kDepth];
  const auto& b = limits[StageJoint::kBevel];
  // Steerable: the insertion joint is the inserted arc length, 0 at the entry; the world stops
  // the needle at the workspace boundary, so the scene's max_depth (an x) does not cap the arc
  // length, the joint's travel does.
  const robot::SceneLimits scene_limits =
      tissue3d      ? tissue3dLimits(scene_spec)
      : steerable3d ? robot::SceneLimits{h.lower, h.upper, d.upper, 0.0}
      : steerable_mode
          ? robot::SceneLimits{scene.needle.min_height_m, scene.needle.max_height_m, d.upper, 0.0}
          : robot::SceneLimits{scene.needle.min_height_m, scene.needle.max_height_m,
                               scene.needle.max_depth_m, scene.workspace_min.x()};
  const double control_rate_hz =
      ros_params::number(private_nh, "control_rate_hz", 500.0, 10.0, 5000.0, "Hz");
  const double publish_rate_hz =
      ros_params::number(private_nh, "publish_rate_hz", 100.0, 1.0, control_rate_hz, "Hz");
  time_scale_ =
      ros_params::number(private_nh, "time_scale", 1.0, 1.0, 100.0, "simulated s per wall s");
  const double mid_height = 0.5 * (scene_limits.min_height_m + scene_limits.max_height_m);
  const double initial_height_m =
      ros_params::number(private_nh, "initial_height_m", mid_height, h.lower, h.upper, "m");
  // Steerable: the needle starts at its entry point (inserted length 0).
  const double initial_depth_m =
      steerable_mode || steerable3d
          ? 0.0
          : ros_params::number(private_nh, "initial_depth_m", scene_limits.entry_x_m - 0.01,
                               d.lower, scene_limits.entry_x_m, "m");
  const double initial_bevel_rad =
      ros_params::number(private_nh, "initial_bevel_rad", b.lower, b.lower, b.upper, "rad");
  const double mid_lateral = 0.5 * (scene_limits.min_lateral_m + scene_limits.max_lateral_m);
  const std::array<double, robot::kStageJointCount> initial{initial_height_m, initial_depth_m,
                                                            initial_bevel_rad, mid_lateral};
  const std::string journal_path = ros_params::rosHomePath(
      ros_params::text(private_nh, "journal_file", "insertion_robot_journal.csv"));
  publish_period_s_ = 1.0 / publish_rate_hz;

  stage_ = std::make_unique<robot::InsertionStage>(limits, scene_limits, initial);
  if (!journal_path.empty()) {
    // Appends only to a journal of ours, never into a system folder (unless allowed).
    const bool allow_system = ros_params::flag(private_nh, "allow_system_paths", false);
    report::checkAppendFile(journal_path, {robot::JournalFile::header()},
                            private_nh.resolveName("journal_file"), allow_system);
    if (steerable_mode || steerable3d) {
      report::checkAppendFile(
          robot::companionJournalPath(journal_path, steerable3d),
          {steerable3d ? robot::Journal3File::header() : robot::NeedleJournalFile::header()},
          private_nh.resolveName("journal_file") + " (needle journal)", allow_system);
    }
    journal_file_ = std::make_unique<robot::JournalFile>(journal_path);
    stage_->setJournalSink([this](const robot::JournalEntry& e) { journal_file_->write(e); });
    ROS_INFO_STREAM("insertion_robot: journal appended to " << journal_path);
  }

  if (steerable_mode)
    setUpSteerableNeedle(private_nh, scene, b, initial_height_m, initial_bevel_rad, journal_path);
  if (steerable3d) {
    setUpSteerable3d(private_nh, scene_spec, limits, journal_path);
  }
  advertiseInterfaces(private_nh);

  last_step_ = ros::Time::now();
  last_publish_ = last_step_;
  publishState(last_step_);
  control_timer_ = nh.createTimer(ros::Duration(1.0 / control_rate_hz),
                                  &InsertionRobotRos::onControlTimer, this);
  ROS_INFO_STREAM("insertion_robot: ready on scene '" << (scene3d_   ? scene3d_->name
                                                          : tissue3d ? scene_spec
                                                                     : scene.name)
                                                      << "', needle " << limits.needle_length_m
                                                      << " m, " << mode << " mode, time scale "
                                                      << time_scale_);
}

InsertionRobotRos::LinearMoveServer& InsertionRobotRos::linearServer(Owner owner) {
  return owner == Owner::kHeight    ? *height_server_
         : owner == Owner::kInsert  ? *insert_server_
         : owner == Owner::kLateral ? *lateral_server_
                                    : *retract_server_;
}

robot::StageJoint InsertionRobotRos::linearJoint(Owner owner) {
  return owner == Owner::kHeight    ? StageJoint::kHeight
         : owner == Owner::kLateral ? StageJoint::kLateral
                                    : StageJoint::kDepth;
}

std::string InsertionRobotRos::runningMotion() const {
  static const char* const kRunning[] = {"",
                                         "a move_to_height motion is running",
                                         "an insert motion is running",
                                         "a retract motion is running",
                                         "a flip_bevel rotation is running",
                                         "a steer motion is running",
                                         "a move_to_lateral motion is running"};
  return kRunning[static_cast<int>(owner_)];  // indexed by Owner
}

void InsertionRobotRos::onLinearGoal(Owner owner, const LinearMoveGoal& goal_msg) {
  LinearMoveServer& server = linearServer(owner);
  const LinearMoveGoal* goal = &goal_msg;
  const StageJoint joint = linearJoint(owner);
  const double current = stage_->state().position[static_cast<std::size_t>(joint)];
  robot::CommandStatus status = robot::CommandStatus::accepted();
  const LinearCommand command = owner == Owner::kInsert    ? LinearCommand::kInsert
                                : owner == Owner::kRetract ? LinearCommand::kRetract
                                                           : LinearCommand::kHeight;
  std::string why = robot::directionRefusal(command, goal->target_m, current);
  if (why.empty()) {
    why = steer3d_      ? steer3d_->linearRefusal(command, goal->target_m)
          : steerable() ? steerable_->refusal(command, goal->target_m)
                        : "";
  }
  if (!why.empty()) {
    status = robot::CommandStatus::refused(why);
  } else {
    status = stage_->command(joint, goal->target_m, goal->velocity_m_s);
    if (status && steerable() && owner == Owner::kInsert && stage_->busy()) {
      // The insertion command starts here: its deflection is drawn once (5.3).
      status = needle_->beginInsertion();
      if (!status) {
        stage_->cancel();
      }
    }
  }
  if (!status) {
    LinearMoveResult result;
    result.success = false;
    result.message = status.toString();
    result.reached_m = current;
    last_message_ = status.toString();
    ROS_WARN_STREAM_NAMED("insertion_robot", status.toString());
    server.setAborted(result, result.message);
    publishState(ros::Time::now());
    return;
  }
  owner_ = owner;
  goal_start_ = ros::Time::now();
  goal_start_position_ = current;
  goal_target_ = goal->target_m;
  goal_velocity_ = goal->velocity_m_s;
  if (!stage_->busy()) {
    finishActiveGoal(true, "already at target");
  }
}

void InsertionRobotRos::onFlipGoal(const FlipBevelGoal& goal_msg) {
  const FlipBevelGoal* goal = &goal_msg;
  const robot::CommandStatus status =
      steer3d_ ? robot::CommandStatus::refused("flip_bevel refused: in 3-D mode use steer")
               : stage_->flipBevel(goal->velocity_rad_s);
  if (!status) {
    FlipBevelResult result;
    result.success = false;
    result.message = status.toString();
    result.bevel_rad = stage_->state().bevel_rad();
    last_message_ = status.toString();
    ROS_WARN_STREAM_NAMED("insertion_robot", status.toString());
    flip_server_->setAborted(result, result.message);
    return;
  }
  owner_ = Owner::kFlip;
  goal_start_ = ros::Time::now();
  goal_start_position_ = stage_->state().bevel_rad();
}

void InsertionRobotRos::onPreempt(Owner owner) {
  if (owner_ != owner) {
    return;
  }
  steer3d_ ? steer3d_->cancel("goal preempted; motion stopped") : stage_->cancel();
  owner_ = Owner::kNone;
  last_message_ = "goal preempted; motion stopped";
  if (owner == Owner::kSteer) {
    steer_server_->setPreempted(steerResult(false, last_message_), last_message_);
  } else if (owner == Owner::kFlip) {
    FlipBevelResult result;
    result.success = false;
    result.message = last_message_;
    result.bevel_rad = stage_->state().bevel_rad();
    flip_server_->setPreempted(result, result.message);
  } else {
    LinearMoveResult result;
    result.success = false;
    result.message = last_message_;
    const StageJoint joint = linearJoint(owner);
    result.reached_m = stage_->state().position[static_cast<std::size_t>(joint)];
    linearServer(owner).setPreempted(result, result.message);
  }
}

void InsertionRobotRos::finishActiveGoal(bool success, const std::string& message) {
  const Owner owner = owner_;
  owner_ = Owner::kNone;
  last_message_ = message;
  const ros::Time now = ros::Time::now();
  if (steerable()) {
    if (owner == Owner::kFlip && success) {
      steerable_->finishFlip();
    }
    publishNeedle(now);  // the pose at the goal's end, before its result
  } else if (steer3d_) {
    publishNeedle3(now, true);
  }
  if (owner == Owner::kSteer) {
    const Steer3Result result = steerResult(success, message);
    success ? steer_server_->setSucceeded(result, message)
            : steer_server_->setAborted(result, message);
    return;
  }
  if (owner == Owner::kFlip) {
    FlipBevelResult result;
    result.success = success;
    result.message = message;
    result.bevel_rad = stage_->state().bevel_rad();
    success ? flip_server_->setSucceeded(result, message)
            : flip_server_->setAborted(result, message);
    return;
  }
  if (owner == Owner::kNone) {
    return;
  }
  const StageJoint joint = linearJoint(owner);
  LinearMoveResult result;
  result.success = success;
  result.message = message;
  result.reached_m = stage_->state().position[static_cast<std::size_t>(joint)];
  result.duration_s = (now - goal_start_).toSec() * time_scale_;  // simulated time
  result.mean_velocity_m_s =
      result.duration_s > 0.0
          ? std::abs(result.reached_m - goal_start_position_) / result.duration_s
          : 0.0;
  LinearMoveServer& server = linearServer(owner);
  success ? server.setSucceeded(result, message) : server.setAborted(result, message);
}

void InsertionRobotRos::onControlTimer(const ros::TimerEvent& /*event*/) {
  const ros::Time now = ros::Time::now();
  const double dt_s = std::max(0.0, (now - last_step_).toSec()) * time_scale_;
  last_step_ = now;
  if (steer3d_) {
    const auto r = steer3d_->step(dt_s);
    if (r.ended && owner_ == Owner::kSteer) {
      finishActiveGoal(r.success, r.message);
    }
  } else if (steerable()) {
    const auto r = steerable_->step(
        dt_s, owner_ == Owner::kInsert ? std::optional(std::pair(goal_target_, goal_velocity_))
                                       : std::nullopt);
    if (r.stopped) {
      if (r.contact) {
        ROS_WARN_STREAM_NAMED("insertion_robot", r.message);
      } else {
        ROS_ERROR_STREAM_NAMED("insertion_robot", "needle refused a step: " << r.message);
      }
      finishActiveGoal(false, r.message);
    }
  } else {
    stage_->step(dt_s);
  }
  if (owner_ != Owner::kNone && owner_ != Owner::kSteer && !stage_->busy()) {
    finishActiveGoal(true, "target reached");
  }
  if ((now - last_publish_).toSec() >= publish_period_s_ - 1e-6) {
    last_publish_ = now;
    publishState(now);
  }
}

void InsertionRobotRos::publishState(const ros::Time& stamp) {
  const robot::StageState& state = stage_->state();
  sensor_msgs::JointState js;
  ros_conversions::toMessage(state, js);
  js.name.emplace_back("axial_rotation");  // the URDF's continuous joint (3-D mode's spin)
  js.position.push_back(steer3d_ ? steer3d_->spin_rad() : 0.0);
  js.velocity.push_back(0.0);
  if (stage_->limits().has_lateral) {
    js.name.emplace_back(robot::jointName(StageJoint::kLateral));
    js.position.push_back(state.lateral_m());
    js.velocity.push_back(state.velocity[static_cast<std::size_t>(StageJoint::kLateral)]);
  }
  js.header.stamp = stamp;
  measured_js_pub_.publish(js);

  if (steerable()) {
    publishNeedle(stamp);  // measured_cp is the needle's tip pose
  } else if (steer3d_) {
    publishNeedle3(stamp);
  } else {
    geometry_msgs::PoseStamped cp;
    ros_conversions::tipPoseToMessage(state, cp);
    cp.header.stamp = stamp;
    measured_cp_pub_.publish(cp);
  }

  OperatingState op;
  op.header.stamp = stamp;
  op.state = robot::toString(stage_->operatingState());
  op.is_homed = true;
  op.is_busy = stage_->busy();
  const auto joint = stage_->activeJoint();
  op.active_joint = joint ? robot::jointName(*joint) : "";
  op.last_message = last_message_;
  operating_state_pub_.publish(op);

  if (owner_ == Owner::kFlip) {
    FlipBevelFeedback fb;
    fb.bevel_rad = state.bevel_rad();
    flip_server_->publishFeedback(fb);
  } else if (owner_ == Owner::kSteer) {
    Steer3Feedback fb;
    fb.inserted_length_m = steer3d_->insertedLength_m();
    fb.spin_rad = steer3d_->spin_rad();
    steer_server_->publishFeedback(fb);
  } else if (owner_ != Owner::kNone) {
    const StageJoint j = linearJoint(owner_);
    LinearMoveFeedback fb;
    fb.position_m = state.position[static_cast<std::size_t>(j)];
    fb.velocity_m_s = state.velocity[static_cast<std::size_t>(j)];
    fb.tip = steer3d_ ? ros_conversions::toMessage(steer3d_->tip()).position
                      : ros_conversions::toMessage(steerable() ? needle_->tip().p_SceneTip
                                                               : stage_->tipPosition());
    linearServer(owner_).publishFeedback(fb);
  }
}

bool InsertionRobotRos::onEstop(std_srvs::Trigger::Request& /*req*/,
                                std_srvs::Trigger::Response& res) {
  stage_->estop("e-stop service called");
  ROS_ERROR_NAMED("insertion_robot", "EMERGENCY STOP: all motion stopped");
  if (owner_ != Owner::kNone) {
    finishActiveGoal(false, "emergency stop: motion stopped");
  }
  last_message_ = "emergency stop active";
  publishState(ros::Time::now());
  res.success = true;
  res.message = "emergency stop active; call reset_estop to enable";
  return true;
}

bool InsertionRobotRos::onResetEstop(std_srvs::Trigger::Request& /*req*/,
                                     std_srvs::Trigger::Response& res) {
  const robot::CommandStatus status = stage_->resetEstop();
  res.success = static_cast<bool>(status);
  res.message = status.toString();
  last_message_ = status ? "enabled" : status.toString();
  publishState(ros::Time::now());
  return true;
}

bool InsertionRobotRos::onSetEntryPose(SetEntryPose::Request& req, SetEntryPose::Response& res) {
  res.success = false;
  if (!steerable()) {
    res.message = "set_entry_pose refused: the robot is in rigid mode (~mode)";
  } else if (const auto bevel = steering::bevelFromString(req.bevel); !bevel) {
    res.message = "set_entry_pose refused: bevel '" + req.bevel + "' is not left or right";
  } else if (owner_ != Owner::kNone || stage_->busy()) {
    res.message = "set_entry_pose refused: a motion is running; wait for it to end";
  } else {
    robot::EntryPose entry;
    entry.height_m = req.height_m;
    entry.angle_rad = req.angle_rad;
    entry.bevel = *bevel;
    const robot::CommandStatus status =
        steerable_->setEntry(entry, req.reseed ? std::optional(req.seed) : std::nullopt);
    res.success = static_cast<bool>(status);
    res.message = status ? "entry set: " + needle_->journal().back().message
                         : "set_entry_pose refused: " + status.toString();
  }
  last_message_ = res.message;
  if (!res.success) {
    ROS_WARN_STREAM_NAMED("insertion_robot", res.message);
  }
  publishState(ros::Time::now());
  return true;
}

void InsertionRobotRos::publishNeedle(const ros::Time& stamp) {
  const steering::TipPose tip = needle_->tip();
  const NeedleTip tip_msg = toNeedleTip(tip, needle_->insertedLength_m(), stamp);
  measured_tip_pub_.publish(tip_msg);
  // The whole needle, for the imager: built only while someone listens (it is a hot path).
  if (needle_shape_pub_.getNumSubscribers() > 0) {
    NeedleShape shape;
    shape.header = tip_msg.header;
    shape.tip = tip_msg;
    for (const geometry::Point2& p : needle_->pathPoints(kPathSpacing_m)) {
      shape.points.push_back(ros_conversions::toMessage(p));
    }
    needle_shape_pub_.publish(shape);
  }
  NeedleDrive drive;
  drive.header = tip_msg.header;
  drive.entry_id = steerable_->entryId();
  drive.entry.x = needle_->entryPoint().x();
  drive.entry.y = needle_->entryPoint().y();
  drive.entry.theta = needle_->entry().angle_rad;
  drive.bevel = steering::toString(needle_->bevel());
  drive.inserted_length_m = needle_->insertedLength_m();
  drive.flips = steerable_->flipsSinceEntry();
  drive_pub_.publish(drive);
  measured_cp_pub_.publish(toPoseStamped(tip, stamp));
  // The journal grows with every change of the needle's state: republish the path then only.
  const std::size_t version = needle_->journal().size();
  if (version != published_path_version_) {
    published_path_version_ = version;
    needle_path_pub_.publish(toPathMarker(*needle_, stamp));
  }
}

void InsertionRobotRos::onSteerGoal(const Steer3Goal& goal) {
  const robot::CommandStatus status =
      steer3d_->steer({{goal.rotate_rad, goal.curvature_per_m, goal.length_m},
                       goal.spin_rate_rad_s,
                       goal.velocity_m_s});
  if (!status) {
    last_message_ = status.toString();
    ROS_WARN_STREAM_NAMED("insertion_robot", last_message_);
    steer_server_->setAborted(steerResult(false, last_message_), last_message_);
    return;
  }
  owner_ = Owner::kSteer;
}

Steer3Result InsertionRobotRos::steerResult(bool success, const std::string& message) const {
  Steer3Result r;
  r.success = success;
  r.message = message;
  r.contact = needle_model::toString(steer3d_->contact());
  r.obstacle = steer3d_->contactObstacle();
  r.tip = ros_conversions::toMessage(steer3d_->tip());
  for (const needle_model::Vector3& p : steer3d_->lastPath()) {
    r.path.push_back(ros_conversions::toMessage(geometry::Point2(p.x(), p.y()), p.z()));
  }
  r.inserted_length_m = steer3d_->insertedLength_m();
  r.kappa_per_m = steer3d_->lastCycle().kappa_per_m;
  r.saturated = steer3d_->lastCycle().saturated;
  return r;
}

bool InsertionRobotRos::onSetEntryPose3(SetEntryPose3::Request& req, SetEntryPose3::Response& res) {
  needle_model::TipPose3 entry;
  const std::string bad = ros_conversions::fromMessage(req.entry, entry);
  const robot::CommandStatus status =
      bad.empty() ? steer3d_->setEntry(entry, req.reseed ? std::optional(req.seed) : std::nullopt)
                  : robot::CommandStatus::refused("set entry refused: " + bad);
  res.success = static_cast<bool>(status);
  res.message = status ? steer3d_->journal().back().message : status.toString();
  last_message_ = res.message;
  publishState(ros::Time::now());
  return true;
}

void InsertionRobotRos::publishNeedle3(const ros::Time& stamp, bool moved) {
  geometry_msgs::PoseStamped cp;
  cp.header.stamp = stamp;
  cp.header.frame_id = "scene";
  cp.pose = ros_conversions::toMessage(steer3d_->tip());
  measured_cp_pub_.publish(cp);
  const std::size_t version = steer3d_->journal().size() * 1000003 + steer3d_->path().size();
  if (version != published_path_version_ || moved) {
    published_path_version_ = version;
    visualization_msgs::Marker m = ros_conversions::lineStrip(
        steer3d_->path(), "scene", "needle_path", ros_conversions::colour(0.95, 0.6, 0.1), 1.5e-3);
    m.header.stamp = stamp;
    needle_path_pub_.publish(m);
    if (moved) {  // the 3-D needle where the motion ended, for the biplane imagers
      NeedleShape shape;
      shape.header = m.header;
      shape.points = m.points;
      needle_shape_pub_.publish(shape);
    }
  }
}

}  // namespace needle_guidance
