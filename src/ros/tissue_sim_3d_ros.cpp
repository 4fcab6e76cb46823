#include "needle_guidance/ros/tissue_sim_3d_ros.h"

#include <geometry_msgs/PoseArray.h>
#include <visualization_msgs/MarkerArray.h>

#include <algorithm>
#include <chrono>

#include "needle_guidance/TissueStatus.h"
#include "needle_guidance/cpu_time.h"
#include "needle_guidance/ros/implant_seed_answer.h"
#include "needle_guidance/ros/params.h"
#include "needle_guidance/tissue_3d/tet_mesh_3d.h"

namespace needle_guidance {
namespace {

/// Shortest period of the organ-surface markers (each needs one full solve of the mesh) [s].
constexpr double kMarkerPeriod_s = 0.2;

}  // namespace

TissueSim3Ros::TissueSim3Ros(ros::NodeHandle& nh, ros::NodeHandle& private_nh,
                             const std::string& scene_file)
    : scene_(tissue_3d::loadTissueScene3d(scene_file)) {
  const double rate_hz = ros_params::number(private_nh, "rate_hz", 200.0, 1.0, 5000.0, "Hz");
  const double marker_rate_hz =
      ros_params::number(private_nh, "marker_rate_hz", 20.0, 0.1, rate_hz, "Hz");
  const std::string robot = ros_params::text(private_nh, "robot", "insertion_robot");
  marker_period_s_ = 1.0 / marker_rate_hz;

  const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
  tissue_3d::TetMeshReport mesh_report;
  tissue_3d::TetMesh3 mesh = tissue_3d::meshTissue3d(scene_, {}, 1.0, &mesh_report);
  const std::size_t tets = mesh.elements.size();
  model_ = std::make_unique<tissue_3d::TissueModel3>(std::move(mesh), scene_.materialTable(),
                                                     scene_.corotational);
  needle_ = std::make_unique<tissue_3d::NeedleInsertion3>(
      *model_, scene_.needle, scene_.block_min_m.x(), scene_.workspace.max_tip_x_m);
  surfaces_ = ros_conversions::embedSurfaces(scene_, *model_);
  ROS_INFO_STREAM("tissue_sim: 3-D scene '"
                  << scene_.name << "', " << tets << " tetrahedra, " << model_->mesh().nodeCount()
                  << " nodes" << (mesh_report.note.empty() ? "" : " (" + mesh_report.note + ")")
                  << ", built in " << clock.seconds() << " s CPU");

  markers_pub_ = private_nh.advertise<visualization_msgs::MarkerArray>("markers", 1, true);
  status_pub_ = private_nh.advertise<TissueStatus>("status", 10);
  seeds_pub_ = private_nh.advertise<geometry_msgs::PoseArray>("seeds", 1, true);
  reset_srv_ = private_nh.advertiseService("reset", &TissueSim3Ros::onReset, this);
  implant_srv_ = private_nh.advertiseService("implant_seed", &TissueSim3Ros::onImplantSeed, this);
  joint_sub_ = nh.subscribe(robot + "/measured_js", 10, &TissueSim3Ros::onJointState, this);
  step_timer_ = nh.createTimer(ros::Duration(1.0 / rate_hz), &TissueSim3Ros::onStepTimer, this);
  publishMarkers(ros::Time::now());
  publishSeeds(ros::Time::now());
}

void TissueSim3Ros::onJointState(const sensor_msgs::JointStateConstPtr& msg) {
  for (std::size_t i = 0; i < msg->name.size() && i < msg->position.size(); ++i) {
    if (msg->name[i] == "height") {
      height_m_ = msg->position[i];
    } else if (msg->name[i] == "lateral") {
      lateral_m_ = msg->position[i];
    } else if (msg->name[i] == "insertion") {
      depth_m_ = msg->position[i];
    }
  }
}

std::string TissueSim3Ros::follow() {
  if (!height_m_ || !lateral_m_ || !depth_m_) {
    return "";
  }
  const Eigen::Vector3d state(*height_m_, *lateral_m_, *depth_m_);
  if (followed_ && *followed_ == state) {
    return "";
  }
  std::string why_not;
  const auto start = std::chrono::steady_clock::now();
  if (!needle_->moveTo(state.head<2>(), state.z(), &why_not)) {
    return why_not;
  }
  last_step_ms_ =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  followed_ = state;
  markers_stale_ = true;
  return "";
}

void TissueSim3Ros::onStepTimer(const ros::TimerEvent& /*event*/) {
  const bool moved_before = markers_stale_;
  const std::string why_not = follow();
  if (!why_not.empty()) {
    ROS_ERROR_STREAM_THROTTLE_NAMED(2.0, "tissue_sim", "tissue_sim: move refused: " << why_not);
  }
  const ros::Time now = ros::Time::now();
  if (markers_stale_ != moved_before || markers_stale_) {
    const tissue_3d::InsertionInfo3& info = needle_->lastMove();
    TissueStatus msg;
    msg.header.stamp = now;
    msg.header.frame_id = "scene";
    msg.needle_in_tissue = needle_->inTissue();
    msg.tip_force_N = info.tip_force_N;
    msg.friction_force_N = info.friction_force_N;
    msg.shaft_nodes = info.shaft_points;
    msg.slipping_nodes = info.slipping;
    msg.cuts = info.events;
    msg.seeds = needle_->seedCount();
    msg.step_time_ms = last_step_ms_;
    msg.integrator = "quasi_static_3d";
    status_pub_.publish(msg);
  }
  if ((now - last_seeds_).toSec() >= marker_period_s_) {
    publishSeeds(now);  // always: a client waits for seeds stamped after the needle came out
  }
  if (markers_stale_ &&
      (now - last_markers_).toSec() >= std::max(marker_period_s_, kMarkerPeriod_s)) {
    publishMarkers(now);
  }
}

void TissueSim3Ros::publishMarkers(const ros::Time& stamp) {
  last_markers_ = stamp;
  markers_stale_ = false;
  const Eigen::VectorXd u = needle_->inTissue() || needle_->seedCount() > 0
                                ? needle_->displacementField()
                                : Eigen::VectorXd();
  visualization_msgs::MarkerArray markers =
      ros_conversions::tissue3dToMarkers(scene_, *model_, surfaces_, u, *needle_, "scene");
  for (auto& m : markers.markers) {
    m.header.stamp = stamp;
  }
  markers_pub_.publish(markers);
}

void TissueSim3Ros::publishSeeds(const ros::Time& stamp) {
  last_seeds_ = stamp;
  geometry_msgs::PoseArray seeds;
  seeds.header.stamp = stamp;
  seeds.header.frame_id = "scene";
  for (int i = 0; i < needle_->seedCount(); ++i) {
    const tissue_3d::Vector3 p = needle_->seedWorld(i);
    geometry_msgs::Pose pose;
    pose.position.x = p.x();
    pose.position.y = p.y();
    pose.position.z = p.z();
    pose.orientation.w = 1.0;
    seeds.poses.push_back(pose);
  }
  seeds_pub_.publish(seeds);
}

bool TissueSim3Ros::onReset(std_srvs::Trigger::Request& /*req*/, std_srvs::Trigger::Response& res) {
  if (needle_->inTissue()) {
    res.success = false;
    res.message = "not reset: the needle is in tissue (retract it first)";
    return true;
  }
  // A fresh needle on the same model: the factorisation and the compliance columns are kept.
  // The implant's seeds stay in the tissue, at their tissue points, with their ids.
  const Eigen::Vector2d lateral = needle_->lateral();
  const double tip_x = needle_->tipX();
  auto fresh = std::make_unique<tissue_3d::NeedleInsertion3>(
      *model_, scene_.needle, scene_.block_min_m.x(), scene_.workspace.max_tip_x_m);
  for (int i = 0; i < needle_->seedCount(); ++i) {
    fresh->addSeed(needle_->seedReference(i));
  }
  needle_ = std::move(fresh);
  needle_->moveTo(lateral, tip_x);
  res.success = true;
  res.message = "tissue reset to its reference state; " + std::to_string(needle_->seedCount()) +
                " seeds kept";
  publishMarkers(ros::Time::now());
  publishSeeds(ros::Time::now());
  return true;
}

bool TissueSim3Ros::onImplantSeed(ImplantSeed::Request& /*req*/, ImplantSeed::Response& res) {
  const std::optional<int> id = ros_conversions::answerImplantSeed(
      follow(),  // catch up with the robot's last state first
      [this](std::string* why_not) { return needle_->implantSeed(why_not); }, res);
  if (!id) {
    return true;
  }
  const tissue_3d::Vector3 p = needle_->seedWorld(*id);
  res.position.x = p.x();
  res.position.y = p.y();
  res.position.z = p.z();
  publishMarkers(ros::Time::now());
  publishSeeds(ros::Time::now());
  return true;
}

}  // namespace needle_guidance
