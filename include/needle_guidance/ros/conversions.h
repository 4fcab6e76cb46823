// Conversions between core types and ROS messages: the one place for them.
#pragma once

#include <geometry_msgs/Point.h>
#include <geometry_msgs/PoseStamped.h>
#include <sensor_msgs/JointState.h>
#include <std_msgs/ColorRGBA.h>
#include <visualization_msgs/MarkerArray.h>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/robot/insertion_stage.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue/tissue_simulation.h"

namespace needle_guidance::ros_conversions {

/// An rviz colour from components in [0, 1].
std_msgs::ColorRGBA colour(double r, double g, double b, double a = 1.0);

/// A marker with frame, namespace, id and type set, action ADD, identity pose, unit scale.
visualization_msgs::Marker baseMarker(const std::string& frame_id, const std::string& ns, int id,
                                      int type);

/// A point of frame scene at height z [m].
geometry_msgs::Point toMessage(const geometry::Point2& p_Scene, double z_m = 0.0);

/// A closed LINE_STRIP through `ring` (the first vertex repeated at the end) [m].
visualization_msgs::Marker outline(const std::vector<geometry::Point2>& ring,
                                   const std::string& frame_id, const std::string& ns, int id,
                                   double width_m, const std_msgs::ColorRGBA& colour);

/// Stage joint positions and velocities, names as in the URDF.
void toMessage(const robot::StageState& state, sensor_msgs::JointState& msg);

/// True tip pose of a rigid needle in frame scene: position (depth, height), orientation the
/// bevel rotation about +x.
void tipPoseToMessage(const robot::StageState& state, geometry_msgs::PoseStamped& msg);

/// rviz markers of a scene in frame `frame_id`: workspace outline, filled regions coloured by
/// material, obstacles (and their clearance outline), targets, boundary conditions.
visualization_msgs::MarkerArray sceneToMarkers(const scene::Scene& scene,
                                               const std::string& frame_id);

/// rviz markers of the deformed tissue in frame `frame_id`: filled triangles coloured by region
/// (colour_by "region") or by von Mises stress ("stress", blue 0 to red at the maximum), the mesh
/// wireframe, shaft nodes (orange), the tip node (red) and the seeds (yellow).
visualization_msgs::MarkerArray tissueToMarkers(const tissue::TissueSimulation& sim,
                                                const std::string& colour_by,
                                                const std::string& frame_id);

}  // namespace needle_guidance::ros_conversions
