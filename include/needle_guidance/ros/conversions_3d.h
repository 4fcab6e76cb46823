// Conversions between the 3-D steering core (steering_3d/) and ROS messages.
#pragma once

#include <geometry_msgs/Pose.h>
#include <geometry_msgs/PoseWithCovarianceStamped.h>
#include <visualization_msgs/MarkerArray.h>

#include <string>
#include <vector>

#include "needle_guidance/needle_model/scene_3d.h"

namespace needle_guidance::ros_conversions {

/// Tip pose as a Pose of frame scene: the orientation's rotation matrix has the columns
/// (bevel d, binormal n, tangent t) of TipPose3.
geometry_msgs::Pose toMessage(const needle_model::TipPose3& tip);

/// Decodes a tip pose (frame scene). Returns "" and sets `tip` on success; otherwise the reason
/// (a non-finite position or orientation, a quaternion whose norm is not 1 within 1e-3), and
/// `tip` is left unchanged.
std::string fromMessage(const geometry_msgs::Pose& pose, needle_model::TipPose3& tip);
/// Decodes a tip pose with covariance of frame `frame_id`. Returns "" and sets `tip` on
/// success; otherwise the reason (wrong frame, a non-finite position, orientation or
/// covariance entry, a quaternion whose norm is not 1 within 1e-3, a negative variance), and
/// `tip` is left unchanged.
std::string fromMessage(const geometry_msgs::PoseWithCovarianceStamped& msg,
                        const std::string& frame_id, needle_model::TipPose3& tip);

/// Controls from three parallel arrays (a plan in SteeringControl3 or PlanSteering3). Throws
/// std::invalid_argument for arrays of different lengths, a non-finite value or a negative
/// curvature or length.
std::vector<needle_model::Control3> controlsFromArrays(const std::vector<double>& rotate_rad,
                                                       const std::vector<double>& curvature_per_m,
                                                       const std::vector<double>& insertion_m);
/// Appends `controls` to three parallel arrays.
void controlsToArrays(const std::vector<needle_model::Control3>& controls,
                      std::vector<double>& rotate_rad, std::vector<double>& curvature_per_m,
                      std::vector<double>& insertion_m);

/// Markers of a 3-D scene in frame `frame_id`: the tissue mesh (translucent), the obstacle
/// meshes (red, TRIANGLE_LIST), the target ball (green) and the entry disc (blue).
visualization_msgs::MarkerArray sceneToMarkers(const needle_model::Scene3d& scene,
                                               const std::string& frame_id);

/// A LINE_STRIP through `points` [m] with width width_m.
visualization_msgs::Marker lineStrip(const std::vector<needle_model::Vector3>& points,
                                     const std::string& frame_id, const std::string& ns,
                                     const std_msgs::ColorRGBA& colour, double width_m);

}  // namespace needle_guidance::ros_conversions
