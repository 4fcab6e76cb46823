#include "needle_guidance/ros/conversions.h"

#include <ros/console.h>

#include <algorithm>
#include <cmath>

#include "needle_guidance/fem/embedded_needle.h"
#include "needle_guidance/geometry/triangle_mesh.h"

namespace needle_guidance::ros_conversions {
namespace {

/// Height of overlay markers (targets, labels, seeds) above the scene plane [m]: far enough above
/// the tissue and region fills (z <= 0) for the depth buffer of a top-down view to tell them apart
/// (1-2 mm were not: targets flickered under the fill).
constexpr double kMarkerOverlay_m = 0.01;

/// A fixed colour per region index: background first (fat: pale yellow), then tissue colours.
std_msgs::ColorRGBA regionColour(std::size_t index) {
  static const std::array<std::array<float, 3>, 6> kPalette{{{0.95F, 0.85F, 0.55F},
                                                             {0.85F, 0.45F, 0.45F},
                                                             {0.55F, 0.7F, 0.9F},
                                                             {0.6F, 0.85F, 0.55F},
                                                             {0.8F, 0.6F, 0.9F},
                                                             {0.9F, 0.65F, 0.35F}}};
  const auto& c = kPalette[index % kPalette.size()];
  return colour(c[0], c[1], c[2], 1.0F);  // opaque: no blending-order artefacts in rviz
}

visualization_msgs::Marker outline(const geometry::Polygon& polygon, const std::string& frame_id,
                                   const std::string& ns, int id, double width_m,
                                   const std_msgs::ColorRGBA& colour) {
  return ros_conversions::outline(polygon.vertices(), frame_id, ns, id, width_m, colour);
}

/// Filled triangles of a (coarse) mesh of `domain` with `regions`, coloured by region.
visualization_msgs::Marker filled(const geometry::Polygon& domain,
                                  const std::vector<geometry::MeshRegion>& regions,
                                  const std::string& frame_id, const std::string& ns, int id,
                                  const std::vector<std_msgs::ColorRGBA>& colours) {
  const double size_m = 0.25 * (domain.maxCorner() - domain.minCorner()).maxCoeff();
  geometry::MeshingOptions options;
  options.max_edge_m = size_m;
  options.min_edge_m = size_m;
  options.grading_length_m = size_m;
  options.min_angle_deg = 20.0;
  const geometry::TriangleMesh mesh = geometry::meshDomain(domain, ns, regions, options);
  visualization_msgs::Marker m =
      baseMarker(frame_id, ns, id, visualization_msgs::Marker::TRIANGLE_LIST);
  m.color = colour(1.0F, 1.0F, 1.0F, 1.0F);  // rviz multiplies vertex colours by this
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    const auto& colour =
        colours[static_cast<std::size_t>(mesh.triangle_region[t]) % colours.size()];
    for (int node : mesh.triangles[t]) {
      m.points.push_back(toMessage(mesh.nodes[static_cast<std::size_t>(node)]));
      m.points.back().z = -0.0005;  // just behind needle and mesh overlays
      m.colors.push_back(colour);
    }
  }
  return m;
}

}  // namespace

visualization_msgs::Marker baseMarker(const std::string& frame_id, const std::string& ns, int id,
                                      int type) {
  visualization_msgs::Marker m;
  m.header.frame_id = frame_id;
  m.ns = ns;
  m.id = id;
  m.type = type;
  m.action = visualization_msgs::Marker::ADD;
  m.pose.orientation.w = 1.0;
  m.scale.x = m.scale.y = m.scale.z = 1.0;
  return m;
}

std_msgs::ColorRGBA colour(double r, double g, double b, double a) {
  std_msgs::ColorRGBA c;
  c.r = static_cast<float>(r);
  c.g = static_cast<float>(g);
  c.b = static_cast<float>(b);
  c.a = static_cast<float>(a);
  return c;
}

geometry_msgs::Point toMessage(const geometry::Point2& p_Scene, double z_m) {
  geometry_msgs::Point p;
  p.x = p_Scene.x();
  p.y = p_Scene.y();
  p.z = z_m;
  return p;
}

visualization_msgs::Marker outline(const std::vector<geometry::Point2>& ring,
                                   const std::string& frame_id, const std::string& ns, int id,
                                   double width_m, const std_msgs::ColorRGBA& colour) {
  visualization_msgs::Marker m =
      baseMarker(frame_id, ns, id, visualization_msgs::Marker::LINE_STRIP);
  m.scale.x = width_m;
  m.color = colour;
  for (const auto& v : ring) {
    m.points.push_back(toMessage(v));
  }
  if (!ring.empty()) {
    m.points.push_back(toMessage(ring.front()));
  }
  return m;
}

void toMessage(const robot::StageState& state, sensor_msgs::JointState& msg) {
  msg.name.clear();
  // height, insertion, bevel; the lateral axis is added by the stage that has one.
  constexpr std::size_t kJoints = static_cast<std::size_t>(robot::StageJoint::kBevel) + 1;
  msg.position.assign(state.position.begin(), state.position.begin() + kJoints);
  msg.velocity.assign(state.velocity.begin(), state.velocity.begin() + kJoints);
  msg.effort.clear();
  for (std::size_t i = 0; i < kJoints; ++i) {
    msg.name.emplace_back(robot::jointName(static_cast<robot::StageJoint>(i)));
  }
}

void tipPoseToMessage(const robot::StageState& state, geometry_msgs::PoseStamped& msg) {
  msg.header.frame_id = "scene";
  msg.pose.position.x = state.depth_m();
  msg.pose.position.y = state.height_m();
  msg.pose.position.z = state.lateral_m();  // 0 without a lateral axis
  msg.pose.orientation.x = std::sin(0.5 * state.bevel_rad());
  msg.pose.orientation.y = 0.0;
  msg.pose.orientation.z = 0.0;
  msg.pose.orientation.w = std::cos(0.5 * state.bevel_rad());
}

visualization_msgs::MarkerArray sceneToMarkers(const scene::Scene& scene,
                                               const std::string& frame_id) {
  visualization_msgs::MarkerArray array;
  const geometry::Polygon workspace = scene.workspacePolygon();
  array.markers.push_back(
      outline(workspace, frame_id, "workspace", 0, 0.0006, colour(0.2F, 0.2F, 0.2F, 1.0F)));

  if (!scene.regions.empty() || !scene.background_material.empty()) {
    const std::vector<geometry::MeshRegion> regions = scene.meshRegions();
    std::vector<std_msgs::ColorRGBA> colours{
        scene.background_material.empty() ? colour(0.0F, 0.0F, 0.0F, 0.0F) : regionColour(0)};
    for (std::size_t i = 0; i < scene.regions.size(); ++i) {
      colours.push_back(scene.regions[i].rigid ? colour(0.9F, 0.9F, 0.85F, 1.0F)
                                               : regionColour(i + 1));
      array.markers.push_back(outline(scene.regions[i].polygon, frame_id, "region_outlines",
                                      static_cast<int>(i), 0.0004, colour(0.4F, 0.1F, 0.1F, 1.0F)));
    }
    try {
      array.markers.push_back(filled(workspace, regions, frame_id, "regions", 0, colours));
    } catch (const std::exception& e) {
      ROS_WARN_STREAM("sceneToMarkers: regions drawn as outlines only: " << e.what());
    }
  }

  for (std::size_t i = 0; i < scene.obstacles.size(); ++i) {
    const scene::Obstacle& obstacle = scene.obstacles[i];
    const int id = static_cast<int>(i);
    try {
      array.markers.push_back(filled(obstacle.polygon, {}, frame_id, "obstacles", id,
                                     {colour(0.35F, 0.35F, 0.4F, 1.0F)}));
    } catch (const std::exception& e) {
      ROS_WARN_STREAM("sceneToMarkers: obstacle '" << obstacle.name
                                                   << "' outline only: " << e.what());
    }
    array.markers.push_back(outline(obstacle.polygon, frame_id, "obstacle_outlines", id, 0.0004,
                                    colour(0.1F, 0.1F, 0.1F, 1.0F)));
    if (obstacle.clearance_m > 0.0) {
      array.markers.push_back(outline(obstacle.polygon.offset(obstacle.clearance_m), frame_id,
                                      "obstacle_clearance", id, 0.0002,
                                      colour(0.9F, 0.5F, 0.1F, 1.0F)));
    }
  }

  for (std::size_t i = 0; i < scene.boundary.size(); ++i) {
    const scene::BoundarySegment& b = scene.boundary[i];
    if (b.condition != scene::BoundaryCondition::kFixed) {
      continue;
    }
    visualization_msgs::Marker m = baseMarker(frame_id, "fixed_boundary", static_cast<int>(i),
                                              visualization_msgs::Marker::LINE_LIST);
    m.scale.x = 0.0015;
    m.color = colour(0.15F, 0.15F, 0.15F, 1.0F);
    m.points.push_back(toMessage(b.segment.a));
    m.points.push_back(toMessage(b.segment.b));
    array.markers.push_back(m);
  }

  for (std::size_t i = 0; i < scene.targets.size(); ++i) {
    const scene::Target& target = scene.targets[i];
    const int id = static_cast<int>(i);
    visualization_msgs::Marker sphere =
        baseMarker(frame_id, "targets", id, visualization_msgs::Marker::SPHERE);
    sphere.pose.position = toMessage(target.position);
    // Above the tissue fill and its wireframe (z < 0) wherever the mesh has moved, so that every
    // target stays visible from the top view.
    sphere.pose.position.z = kMarkerOverlay_m;
    const double diameter_m = std::max(2.0 * target.radius_m, 0.0015);
    sphere.scale.x = sphere.scale.y = sphere.scale.z = diameter_m;
    sphere.color = colour(0.1F, 0.7F, 0.2F, 1.0F);
    array.markers.push_back(sphere);
    visualization_msgs::Marker label =
        baseMarker(frame_id, "target_labels", id, visualization_msgs::Marker::TEXT_VIEW_FACING);
    label.pose.position = toMessage(target.position);
    label.pose.position.y += 0.5 * diameter_m + 0.0012;
    label.pose.position.z = kMarkerOverlay_m;
    label.scale.z = 0.002;
    label.color = colour(0.0F, 0.15F, 0.0F, 1.0F);  // dark on the light tissue colours
    label.text = target.name;
    array.markers.push_back(label);
  }
  return array;
}

namespace {

/// World positions of the shaft's nodes (node-moving model) or tissue points (embedded track).
std::vector<geometry::Point2> shaftWorld(const tissue::TissueSimulation& sim,
                                         const std::vector<geometry::Point2>& nodes) {
  std::vector<geometry::Point2> out;
  if (sim.needleModel() == tissue::NeedleModel::kNodeMoving) {
    for (int node : sim.needle().shaftNodes()) {
      out.push_back(nodes[static_cast<std::size_t>(node)]);
    }
    return out;
  }
  for (const geometry::Point2& p : sim.shaftReference()) {
    out.emplace_back(sim.trackNeedle().worldOf(p));
  }
  return out;
}

/// World position of the tip node, or of the tip's tissue point (on the needle tip).
std::optional<geometry::Point2> tipWorld(const tissue::TissueSimulation& sim,
                                         const std::vector<geometry::Point2>& nodes) {
  if (sim.needleModel() == tissue::NeedleModel::kNodeMoving) {
    if (sim.needle().tipNode() < 0) {
      return std::nullopt;
    }
    return nodes[static_cast<std::size_t>(sim.needle().tipNode())];
  }
  if (!sim.needleInTissue()) {
    return std::nullopt;
  }
  return geometry::Point2(sim.tipX(), sim.trackNeedle().lateral()(0));
}

}  // namespace

visualization_msgs::MarkerArray tissueToMarkers(const tissue::TissueSimulation& sim,
                                                const std::string& colour_by,
                                                const std::string& frame_id) {
  visualization_msgs::MarkerArray array;
  const auto& mesh = sim.mesh();
  const std::vector<geometry::Point2> nodes = sim.deformedNodes();
  // Stress colours need the node-moving model's elements; the embedded track colours by region.
  const bool by_stress =
      colour_by == "stress" && sim.needleModel() == tissue::NeedleModel::kNodeMoving;
  Eigen::VectorXd stress;
  double max_stress = 0.0;
  if (by_stress) {
    stress = sim.model().elementVonMises(sim.integrator().displacement());
    // Scale by the 95th percentile: the peak at the tip would wash out everything else.
    std::vector<double> sorted(stress.data(), stress.data() + stress.size());
    const std::size_t p95 = sorted.empty() ? 0 : (sorted.size() * 95) / 100;
    if (!sorted.empty()) {
      std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(p95),
                       sorted.end());
      max_stress = std::max(sorted[p95], 1e-12);
    }
  }
  visualization_msgs::Marker fill =
      baseMarker(frame_id, "tissue", 0, visualization_msgs::Marker::TRIANGLE_LIST);
  fill.color = colour(1.0F, 1.0F, 1.0F, 1.0F);
  visualization_msgs::Marker wire =
      baseMarker(frame_id, "tissue_wireframe", 0, visualization_msgs::Marker::LINE_LIST);
  wire.scale.x = 0.00008;
  wire.color = colour(0.3F, 0.3F, 0.3F, 0.6F);
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    std_msgs::ColorRGBA tint;
    if (by_stress) {
      const float s = static_cast<float>(
          std::clamp(stress[static_cast<Eigen::Index>(t)] / max_stress, 0.0, 1.0));
      tint = colour(s, 0.2F * (1.0F - s), 1.0F - s, 1.0F);
    } else {
      tint = regionColour(static_cast<std::size_t>(mesh.triangle_region[t]));
    }
    const auto& tri = mesh.triangles[t];
    for (int k = 0; k < 3; ++k) {
      fill.points.push_back(
          toMessage(nodes[static_cast<std::size_t>(tri[static_cast<std::size_t>(k)])]));
      fill.points.back().z = -0.0003;  // above the scene fill, below needle and targets
      fill.colors.push_back(tint);
      const int a = tri[static_cast<std::size_t>(k)];
      const int b = tri[static_cast<std::size_t>((k + 1) % 3)];
      if (a < b) {  // each interior edge once (its other triangle sees it reversed)
        wire.points.push_back(toMessage(nodes[static_cast<std::size_t>(a)]));
        wire.points.push_back(toMessage(nodes[static_cast<std::size_t>(b)]));
        wire.points[wire.points.size() - 2].z = wire.points.back().z = -0.0002;
      }
    }
  }
  array.markers.push_back(fill);
  array.markers.push_back(wire);

  visualization_msgs::Marker shaft =
      baseMarker(frame_id, "shaft_nodes", 0, visualization_msgs::Marker::SPHERE_LIST);
  shaft.scale.x = shaft.scale.y = shaft.scale.z = 0.0006;
  shaft.color = colour(1.0F, 0.55F, 0.0F, 1.0F);
  for (const geometry::Point2& p : shaftWorld(sim, nodes)) {
    shaft.points.push_back(toMessage(p));
    shaft.points.back().z = 0.0006;
  }
  if (shaft.points.empty()) {
    shaft.action = visualization_msgs::Marker::DELETE;  // rviz rejects empty point lists
  }
  array.markers.push_back(shaft);
  visualization_msgs::Marker tip =
      baseMarker(frame_id, "tip_node", 0, visualization_msgs::Marker::SPHERE);
  tip.scale.x = tip.scale.y = tip.scale.z = 0.0009;
  tip.color = colour(0.9F, 0.0F, 0.0F, 1.0F);
  if (const std::optional<geometry::Point2> p = tipWorld(sim, nodes)) {
    tip.pose.position = toMessage(*p);
    tip.pose.position.z = kMarkerOverlay_m + 0.0015;
  } else {
    tip.action = visualization_msgs::Marker::DELETE;
  }
  array.markers.push_back(tip);
  visualization_msgs::Marker seeds =
      baseMarker(frame_id, "seeds", 0, visualization_msgs::Marker::SPHERE_LIST);
  seeds.scale.x = seeds.scale.y = seeds.scale.z = 0.0012;
  seeds.color = colour(1.0F, 0.9F, 0.0F, 1.0F);
  for (const auto& seed : sim.seeds()) {
    seeds.points.push_back(toMessage(sim.seedPosition(seed)));
    seeds.points.back().z = kMarkerOverlay_m + 0.001;  // a seed shows on top of its target
  }
  if (seeds.points.empty()) {
    seeds.action = visualization_msgs::Marker::DELETE;
  }
  array.markers.push_back(seeds);
  return array;
}

}  // namespace needle_guidance::ros_conversions
