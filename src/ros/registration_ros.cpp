#include "needle_guidance/ros/registration_ros.h"

#include <visualization_msgs/MarkerArray.h>

#include <cmath>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/registration/registration_request.h"
#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/params.h"

namespace needle_guidance {
namespace {

namespace reg = registration;
constexpr const char* kName = "registration";
constexpr double kMmPerM = 1e3;
constexpr double kLineWidth_m = 0.4e-3;
constexpr double kGridPointSize_m = 1.2e-3;

geometry::Polygon fromMessage(const geometry_msgs::Polygon& msg) {
  std::vector<geometry::Point2> v;
  v.reserve(msg.points.size());
  for (const auto& p : msg.points) {
    v.emplace_back(p.x, p.y);
  }
  return geometry::Polygon(std::move(v));
}

/// Finite check of every vertex; names the first bad polygon.
std::optional<std::string> nonFinite(const Register::Request& req) {
  auto bad = [](const geometry_msgs::Polygon& p) {
    for (const auto& v : p.points) {
      if (!std::isfinite(v.x) || !std::isfinite(v.y))
        return true;
    }
    return false;
  };
  const std::vector<std::pair<const char*, const geometry_msgs::Polygon*>> named = {
      {"domain", &req.domain},   {"cg", &req.cg},
      {"pz", &req.pz},           {"rectum", &req.rectum},
      {"bladder", &req.bladder}, {"probe_in_prostate", &req.probe_in_prostate},
      {"probe", &req.probe}};
  for (const auto& [name, polygon] : named) {
    if (bad(*polygon))
      return std::string(name);
  }
  for (std::size_t i = 0; i < req.bones.size(); ++i) {
    if (bad(req.bones[i]))
      return "bones[" + std::to_string(i) + "]";
  }
  return std::nullopt;
}

using ros_conversions::toMessage;

/// A closed outline of frame scene in colour (r, g, b).
visualization_msgs::Marker outline(int id, const std::string& ns,
                                   const std::vector<geometry::Point2>& v, float r, float g,
                                   float b) {
  return ros_conversions::outline(v, "scene", ns, id, kLineWidth_m,
                                  ros_conversions::colour(r, g, b));
}

}  // namespace

RegistrationRos::RegistrationRos(ros::NodeHandle& /*nh*/, ros::NodeHandle& private_nh) {
  ROS_INFO("registration parameters:");
  defaults_.target_nodes = static_cast<int>(
      ros_params::integer(private_nh, "target_nodes", defaults_.target_nodes, 30, 20000, "nodes"));
  defaults_.alpha = ros_params::number(private_nh, "alpha", defaults_.alpha, 0.0, 10.0, "");
  defaults_.max_iterations = static_cast<int>(ros_params::integer(
      private_nh, "max_iterations", defaults_.max_iterations, 1, 100000, "iterations"));
  markers_pub_ = private_nh.advertise<visualization_msgs::MarkerArray>("markers", 1, true);
  register_srv_ = private_nh.advertiseService("register", &RegistrationRos::onRegister, this);
  ROS_INFO_STREAM_NAMED(kName, "registration: ready (~register)");
}

bool RegistrationRos::onRegister(Register::Request& req, Register::Response& res) {
  res.success = false;
  res.point_error_mm = res.rigid_point_error_mm = res.unregistered_point_error_mm = -1.0;
  reg::RegistrationRequest request;
  request.optimizer = req.optimizer;
  request.alpha = req.alpha;
  request.target_nodes = req.target_nodes;
  request.synthetic_seed = req.synthetic_seed;
  request.probe_type = req.probe_type;
  if (req.synthetic_seed == 0) {
    if (const auto bad = nonFinite(req)) {
      res.status = "refused";
      res.message = "polygon '" + *bad + "' has a non-finite vertex";
      return true;
    }
    reg::SliceSegmentation& out = request.probe_out;
    out.domain = fromMessage(req.domain);
    out.cg = reg::Outline(fromMessage(req.cg));
    out.pz = reg::Outline(fromMessage(req.pz));
    out.rectum = reg::Outline(fromMessage(req.rectum));
    for (const auto& b : req.bones)
      out.bones.emplace_back(fromMessage(b));
    if (!req.bladder.points.empty())
      out.bladder = reg::Outline(fromMessage(req.bladder));
    request.probe_in.prostate = reg::Outline(fromMessage(req.probe_in_prostate));
    request.probe_in.probe = reg::Outline(fromMessage(req.probe));
  }
  const Result<reg::RegistrationAnswer> answer = reg::runRegistration(request, defaults_);
  if (!answer) {
    res.status = "refused";
    res.message = answer.status().message();
    return true;
  }
  const reg::RegistrationResult& result = answer.value().result;
  const reg::SliceSegmentation& out = answer.value().probe_out;
  const reg::ProbeInSegmentation& in = answer.value().probe_in;
  res.status = reg::toString(result.status);
  res.message = result.message;
  res.success = reg::hasMapping(result.status);
  res.dice = result.dice;
  res.initial_dice = result.initial_dice;
  for (int c = 0; c < reg::kSoftClassCount; ++c) {
    res.modulus_kPa.push_back(result.modulus_Pa[static_cast<std::size_t>(c)] * 1e-3);
    res.modulus_at_bound.push_back(result.modulus_at_bound[static_cast<std::size_t>(c)]);
  }
  res.force_nodes = static_cast<int>(result.force_nodes.size());
  res.iterations = result.iterations;
  res.seconds = result.seconds;
  if (!res.success) {
    ROS_WARN_STREAM_NAMED(kName, "registration: " << res.status << ": " << res.message);
    return true;
  }
  const auto mm = [](double m) { return std::isfinite(m) ? m * kMmPerM : -1.0; };
  res.point_error_mm = mm(answer.value().point_error_m);
  res.rigid_point_error_mm = mm(answer.value().rigid_point_error_m);
  res.unregistered_point_error_mm = mm(answer.value().unregistered_point_error_m);
  const reg::WarpedGrid& grid = result.mrsi_grid;
  for (std::size_t i = 0; i < grid.probe_in.size(); ++i) {
    res.grid_probe_in.push_back(toMessage(grid.probe_in[i]));
    res.grid_valid.push_back(grid.probe_out[i].has_value());
    res.grid_probe_out.push_back(toMessage(grid.probe_out[i].value_or(grid.probe_in[i])));
  }

  // rviz: probe-in prostate (green), probe outline (grey), probe-out prostate before (blue) and
  // after the deformation (red), warped MRSI grid points on the probe-out slice (orange).
  visualization_msgs::MarkerArray markers;
  visualization_msgs::Marker clear;
  clear.action = visualization_msgs::Marker::DELETEALL;
  markers.markers.push_back(clear);
  markers.markers.push_back(
      outline(0, "probe_in_prostate", in.prostate.outer.vertices(), 0.1F, 0.7F, 0.1F));
  markers.markers.push_back(outline(1, "probe", in.probe.outer.vertices(), 0.4F, 0.4F, 0.4F));
  int id = 2;
  for (const auto& loop : reg::prostateLoops(out)) {
    markers.markers.push_back(outline(id++, "probe_out_prostate", loop, 0.1F, 0.3F, 0.9F));
    if (const auto mapped = reg::mapPolygonForward(*result.mapping, loop)) {
      markers.markers.push_back(
          outline(id++, "deformed_probe_out_prostate", *mapped, 0.9F, 0.1F, 0.1F));
    }
  }
  visualization_msgs::Marker pts = ros_conversions::baseMarker("scene", "warped_mrsi_grid", id++,
                                                               visualization_msgs::Marker::POINTS);
  pts.scale.x = pts.scale.y = kGridPointSize_m;
  pts.color = ros_conversions::colour(1.0, 0.55, 0.0);
  for (std::size_t i = 0; i < grid.probe_out.size(); ++i) {
    if (grid.probe_out[i] && grid.inside_prostate[i])
      pts.points.push_back(toMessage(*grid.probe_out[i]));
  }
  markers.markers.push_back(pts);
  markers_pub_.publish(markers);
  ROS_INFO_STREAM_NAMED(kName, "registration: " << res.status << ", Dice " << res.dice << " (from "
                                                << res.initial_dice << "), " << res.iterations
                                                << " iterations, " << res.seconds << " s");
  return true;
}

}  // namespace needle_guidance
