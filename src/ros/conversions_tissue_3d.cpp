#include "needle_guidance/ros/conversions_tissue_3d.h"

#include <array>

#include "needle_guidance/ros/conversions.h"

namespace needle_guidance::ros_conversions {
namespace {

using tissue_3d::Vector3;

geometry_msgs::Point point(const Vector3& p) {
  geometry_msgs::Point m;
  m.x = p.x();
  m.y = p.y();
  m.z = p.z();
  return m;
}

std_msgs::ColorRGBA colour(float r, float g, float b, float a) {
  std_msgs::ColorRGBA c;
  c.r = r;
  c.g = g;
  c.b = b;
  c.a = a;
  return c;
}

/// World position of an embedded point under the nodal displacement u.
Vector3 deformed(const tissue_3d::EmbeddedPoint& p, const tissue_3d::TissueModel3& model,
                 const Eigen::VectorXd& u) {
  Vector3 x = p.reference_m;
  if (p.element < 0 || u.size() == 0) {
    return x;
  }
  const auto& nodes = model.mesh().elements[static_cast<std::size_t>(p.element)];
  for (int a = 0; a < 4; ++a) {
    x += p.weights(a) * u.segment<3>(3 * nodes[a]);
  }
  return x;
}

visualization_msgs::Marker sphereList(const std::string& ns, const std::vector<Vector3>& points,
                                      double diameter_m, const std_msgs::ColorRGBA& c,
                                      const std::string& frame_id) {
  visualization_msgs::Marker m =
      baseMarker(frame_id, ns, 0, visualization_msgs::Marker::SPHERE_LIST);
  m.scale.x = m.scale.y = m.scale.z = diameter_m;
  m.color = c;
  for (const Vector3& p : points) {
    m.points.push_back(point(p));
  }
  if (points.empty()) {
    m.action = visualization_msgs::Marker::DELETE;
  }
  return m;
}

visualization_msgs::Marker blockOutline(const tissue_3d::TissueScene3d& scene,
                                        const std::string& frame_id) {
  visualization_msgs::Marker m =
      baseMarker(frame_id, "block", 0, visualization_msgs::Marker::LINE_LIST);
  m.scale.x = 5e-4;
  m.color = colour(0.7F, 0.7F, 0.7F, 1.0F);
  const Vector3& lo = scene.block_min_m;
  const Vector3& hi = scene.block_max_m;
  auto corner = [&](int i) {
    return Vector3(i & 1 ? hi.x() : lo.x(), i & 2 ? hi.y() : lo.y(), i & 4 ? hi.z() : lo.z());
  };
  for (int i = 0; i < 8; ++i) {
    for (int bit : {1, 2, 4}) {
      if (!(i & bit)) {
        m.points.push_back(point(corner(i)));
        m.points.push_back(point(corner(i | bit)));
      }
    }
  }
  return m;
}

}  // namespace

std::vector<EmbeddedSurface3> embedSurfaces(const tissue_3d::TissueScene3d& scene,
                                            const tissue_3d::TissueModel3& model) {
  std::vector<EmbeddedSurface3> out;
  for (const tissue_3d::Region3& region : scene.regions) {
    EmbeddedSurface3 s;
    s.name = region.name;
    s.fixed = region.fixed;
    s.triangles = region.surface.triangles;
    for (const Vector3& v : region.surface.vertices) {
      tissue_3d::EmbeddedPoint p;
      p.reference_m = v;
      if (const auto located = model.locate(v)) {
        p = *located;
      }
      s.vertices.push_back(p);
    }
    out.push_back(std::move(s));
  }
  return out;
}

visualization_msgs::MarkerArray tissue3dToMarkers(const tissue_3d::TissueScene3d& scene,
                                                  const tissue_3d::TissueModel3& model,
                                                  const std::vector<EmbeddedSurface3>& surfaces,
                                                  const Eigen::VectorXd& displacement,
                                                  const tissue_3d::NeedleInsertion3& needle,
                                                  const std::string& frame_id) {
  static const std::array<std::array<float, 3>, 4> kPalette{
      {{0.55F, 0.35F, 0.75F}, {0.95F, 0.75F, 0.3F}, {0.85F, 0.3F, 0.3F}, {0.3F, 0.6F, 0.85F}}};
  visualization_msgs::MarkerArray out;
  out.markers.push_back(blockOutline(scene, frame_id));
  for (std::size_t r = 0; r < surfaces.size(); ++r) {
    const EmbeddedSurface3& s = surfaces[r];
    visualization_msgs::Marker m = baseMarker(frame_id, "region/" + s.name, static_cast<int>(r),
                                              visualization_msgs::Marker::TRIANGLE_LIST);
    const auto& c = kPalette[r % kPalette.size()];
    m.color = s.fixed ? colour(0.8F, 0.8F, 0.75F, 0.9F) : colour(c[0], c[1], c[2], 0.45F);
    std::vector<geometry_msgs::Point> world;
    world.reserve(s.vertices.size());
    for (const tissue_3d::EmbeddedPoint& p : s.vertices) {
      world.push_back(point(deformed(p, model, displacement)));
    }
    for (const auto& t : s.triangles) {
      for (int k : t) {
        m.points.push_back(world[static_cast<std::size_t>(k)]);
      }
    }
    out.markers.push_back(m);
  }
  visualization_msgs::Marker shaft =
      baseMarker(frame_id, "needle", 0, visualization_msgs::Marker::LINE_STRIP);
  shaft.scale.x = scene.needle.diameter_m;
  shaft.color = colour(0.2F, 0.2F, 0.25F, 1.0F);
  const double tip_x = needle.tipX();
  const Eigen::Vector2d& lateral = needle.lateral();
  shaft.points.push_back(point(Vector3(tip_x - scene.needle.length_m, lateral.x(), lateral.y())));
  shaft.points.push_back(point(Vector3(tip_x, lateral.x(), lateral.y())));
  out.markers.push_back(shaft);
  std::vector<Vector3> seeds;
  for (int i = 0; i < needle.seedCount(); ++i) {
    seeds.push_back(needle.seedWorld(i));
  }
  out.markers.push_back(sphereList("seeds", seeds, 2e-3, colour(1.0F, 0.9F, 0.1F, 1.0F), frame_id));
  std::vector<Vector3> targets;
  for (const tissue_3d::Target3& t : scene.targets) {
    targets.push_back(t.position_m);
  }
  out.markers.push_back(
      sphereList("targets", targets, 1.5e-3, colour(0.1F, 0.85F, 0.2F, 0.8F), frame_id));
  return out;
}

}  // namespace needle_guidance::ros_conversions
