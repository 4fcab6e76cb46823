// 3-D steering conversions (conversions_3d.h).
#include "needle_guidance/ros/conversions_3d.h"

#include <Eigen/Geometry>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/delivery_conversions.h"

namespace needle_guidance::ros_conversions {
namespace {

geometry_msgs::Point point(const needle_model::Vector3& p) {
  return toPointMessage(p);
}

visualization_msgs::Marker marker(const std::string& frame_id, const std::string& ns, int id,
                                  int type, const std_msgs::ColorRGBA& c) {
  visualization_msgs::Marker m = baseMarker(frame_id, ns, id, type);
  m.color = c;
  return m;
}

visualization_msgs::Marker meshMarker(const needle_model::Mesh3& mesh, const std::string& frame_id,
                                      const std::string& ns, int id, const std_msgs::ColorRGBA& c) {
  visualization_msgs::Marker m =
      marker(frame_id, ns, id, visualization_msgs::Marker::TRIANGLE_LIST, c);
  m.points.reserve(mesh.triangles.size() * 3);
  for (const auto& t : mesh.triangles) {
    for (int v : t) {
      m.points.push_back(point(mesh.vertices[static_cast<std::size_t>(v)]));
    }
  }
  return m;
}

}  // namespace

geometry_msgs::Pose toMessage(const needle_model::TipPose3& tip) {
  geometry_msgs::Pose m;
  m.position = point(tip.p_SceneTip);
  const Eigen::Quaterniond q(tip.R_SceneTip);
  m.orientation.w = q.w();
  m.orientation.x = q.x();
  m.orientation.y = q.y();
  m.orientation.z = q.z();
  return m;
}

std::string fromMessage(const geometry_msgs::Pose& pose, needle_model::TipPose3& tip) {
  const auto& p = pose.position;
  const auto& o = pose.orientation;
  if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z)) {
    return "tip position is not finite";
  }
  if (!std::isfinite(o.w) || !std::isfinite(o.x) || !std::isfinite(o.y) || !std::isfinite(o.z)) {
    return "tip orientation is not finite";
  }
  const Eigen::Quaterniond q(o.w, o.x, o.y, o.z);
  if (std::abs(q.norm() - 1.0) > 1e-3) {
    std::ostringstream out;
    out << "tip orientation quaternion has norm " << q.norm() << ", not 1";
    return out.str();
  }
  tip.p_SceneTip = needle_model::Vector3(p.x, p.y, p.z);
  tip.R_SceneTip = q.normalized().toRotationMatrix();
  return "";
}

std::string fromMessage(const geometry_msgs::PoseWithCovarianceStamped& msg,
                        const std::string& frame_id, needle_model::TipPose3& tip) {
  if (msg.header.frame_id != frame_id) {
    return "tip pose in frame '" + msg.header.frame_id + "', expected '" + frame_id + "'";
  }
  needle_model::TipPose3 decoded;
  if (const std::string bad = fromMessage(msg.pose.pose, decoded); !bad.empty()) {
    return bad;
  }
  for (std::size_t k = 0; k < msg.pose.covariance.size(); ++k) {
    if (!std::isfinite(msg.pose.covariance[k])) {
      return "tip covariance entry " + std::to_string(k) + " is not finite";
    }
    if (k % 7 == 0 && msg.pose.covariance[k] < 0.0) {
      return "tip covariance has a negative variance at entry " + std::to_string(k);
    }
  }
  tip = decoded;
  return "";
}

std::vector<needle_model::Control3> controlsFromArrays(const std::vector<double>& rotate_rad,
                                                       const std::vector<double>& curvature_per_m,
                                                       const std::vector<double>& insertion_m) {
  if (rotate_rad.size() != curvature_per_m.size() || rotate_rad.size() != insertion_m.size()) {
    throw std::invalid_argument(
        "plan arrays of different lengths (" + std::to_string(rotate_rad.size()) + ", " +
        std::to_string(curvature_per_m.size()) + ", " + std::to_string(insertion_m.size()) + ")");
  }
  std::vector<needle_model::Control3> out;
  for (std::size_t k = 0; k < rotate_rad.size(); ++k) {
    const needle_model::Control3 c{rotate_rad[k], curvature_per_m[k], insertion_m[k]};
    if (!std::isfinite(c.rotate_rad) || !std::isfinite(c.curvature_per_m) ||
        !std::isfinite(c.length_m) || c.curvature_per_m < 0.0 || c.length_m < 0.0) {
      throw std::invalid_argument("plan control " + std::to_string(k) +
                                  " is not finite or has a negative curvature or length");
    }
    out.push_back(c);
  }
  return out;
}

void controlsToArrays(const std::vector<needle_model::Control3>& controls,
                      std::vector<double>& rotate_rad, std::vector<double>& curvature_per_m,
                      std::vector<double>& insertion_m) {
  for (const needle_model::Control3& c : controls) {
    rotate_rad.push_back(c.rotate_rad);
    curvature_per_m.push_back(c.curvature_per_m);
    insertion_m.push_back(c.length_m);
  }
}

visualization_msgs::MarkerArray sceneToMarkers(const needle_model::Scene3d& scene,
                                               const std::string& frame_id) {
  visualization_msgs::MarkerArray out;
  out.markers.push_back(
      meshMarker(scene.tissue, frame_id, "tissue", 0, colour(0.95, 0.8, 0.6, 0.18)));
  for (std::size_t k = 0; k < scene.obstacles.size(); ++k) {
    out.markers.push_back(meshMarker(scene.obstacles[k].mesh, frame_id, "obstacles",
                                     static_cast<int>(k), colour(0.85, 0.2, 0.2, 0.85)));
  }
  visualization_msgs::Marker target =
      marker(frame_id, "target", 0, visualization_msgs::Marker::SPHERE, colour(0.1, 0.8, 0.2, 0.8));
  target.pose.position = point(scene.target.center_m);
  target.scale.x = target.scale.y = target.scale.z = 2.0 * scene.target.radius_m;
  out.markers.push_back(target);
  visualization_msgs::Marker entry = marker(
      frame_id, "entry", 0, visualization_msgs::Marker::CYLINDER, colour(0.2, 0.4, 0.95, 0.6));
  entry.pose.position = point(scene.entry.center_m);
  const Eigen::Quaterniond q =
      Eigen::Quaterniond::FromTwoVectors(needle_model::Vector3::UnitZ(), scene.entry.direction);
  entry.pose.orientation.w = q.w();
  entry.pose.orientation.x = q.x();
  entry.pose.orientation.y = q.y();
  entry.pose.orientation.z = q.z();
  entry.scale.x = entry.scale.y = std::max(2.0 * scene.entry.radius_m, 1e-3);
  entry.scale.z = 5e-4;
  out.markers.push_back(entry);
  return out;
}

visualization_msgs::Marker lineStrip(const std::vector<needle_model::Vector3>& points,
                                     const std::string& frame_id, const std::string& ns,
                                     const std_msgs::ColorRGBA& c, double width_m) {
  visualization_msgs::Marker m = marker(frame_id, ns, 0, visualization_msgs::Marker::LINE_STRIP, c);
  m.scale.x = width_m;
  for (const auto& p : points) {
    m.points.push_back(point(p));
  }
  return m;
}

}  // namespace needle_guidance::ros_conversions
