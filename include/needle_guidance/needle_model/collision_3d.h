// Collision and clearance of needle paths in a 3-D steering scene: the tissue
// boundary mesh and obstacle meshes expanded by their clearance, queried through AABB trees
// (mesh_3d.h). Paths are checked by sphere tracing: at each point the free margin (distance to
// the nearest expanded obstacle or to the tissue boundary) is a radius the unit-speed path
// cannot leave before it has advanced that arc length, so the check never skips a contact and
// needs few queries in open tissue. Plain C++; no ROS.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "needle_guidance/needle_model/mesh_3d.h"

namespace needle_guidance::needle_model {

/// An obstacle: a closed mesh and the clearance it is expanded by (Minkowski sum with a ball).
struct ObstacleMesh3 {
  std::string name;
  Mesh3 mesh;
  double clearance_m = 0.0;  ///< >= 0 [m]
};

/// What a point or path touches.
enum class Contact3 {
  kFree = 0,
  kObstacle = 1,       ///< within an expanded obstacle
  kOutsideTissue = 2,  ///< outside the tissue boundary (or on it, for a path)
};
/// "free" | "obstacle" | "outside_tissue".
std::string toString(Contact3 contact);

/// A point's classification with inside tests (for starts and targets).
struct PointCheck {
  Contact3 contact = Contact3::kFree;
  std::string obstacle;   ///< the obstacle's name for kObstacle
  double margin_m = 0.0;  ///< free margin at the point (<= 0 unless kFree) [m]
};

/// A path check.
struct PathCheck {
  Contact3 contact = Contact3::kFree;
  std::string obstacle;       ///< for kObstacle: the nearest expanded obstacle at contact
  double contact_s_m = 0.0;   ///< arc length of the first point within tolerance [m]
  double min_margin_m = 0.0;  ///< smallest margin met (a lower bound on the path's) [m]
  int queries = 0;            ///< distance queries made
  bool free() const { return contact == Contact3::kFree; }
};

/// The scene's collision geometry.
class CollisionWorld3 {
public:
  /// @param[in] tissue closed outward mesh of the tissue (the needle stays inside)
  /// @param[in] obstacles closed meshes with clearances
  /// @param[in] tolerance_m a path is in contact where its margin drops below this [m], > 0
  /// Throws std::invalid_argument for a non-positive tolerance or a negative clearance.
  CollisionWorld3(const Mesh3& tissue, std::vector<ObstacleMesh3> obstacles, double tolerance_m);

  /// Full classification with inside tests: outside tissue, inside an expanded obstacle, free.
  PointCheck classify(const Vector3& p_Scene) const;
  /// Free margin at a point already known to lie in the free space [m]; index of the nearest
  /// obstacle (-1 for the tissue boundary) in `nearest` if given.
  double margin(const Vector3& p_Scene, int* nearest = nullptr) const;
  /// Margin to the nearest expanded obstacle only (+inf without obstacles) [m].
  double obstacleMargin(const Vector3& p_Scene, int* nearest = nullptr) const;
  /// Sphere tracing of a unit-speed path s -> point_at(s), s in [0, length_m], whose start is
  /// known to be free (see classify). An obstacle is touched where the margin drops below the
  /// tolerance; the tissue is left where a point lies outside it (a path may start on the tissue
  /// boundary: the entry). A free path's points all keep a margin of at least tolerance / 2 from
  /// every expanded obstacle.
  /// With extra_margin_m > 0 an obstacle counts as touched within tolerance + extra_margin_m.
  PathCheck checkPath(const std::function<Vector3(double)>& point_at, double length_m,
                      double extra_margin_m = 0.0) const;
  /// The constant-curvature arc of advanceArc from `pose`.
  PathCheck checkArc(const TipPose3& pose, double curvature_per_m, double length_m,
                     double extra_margin_m = 0.0) const;
  /// A polyline (its first point known to be free).
  PathCheck checkPolyline(const std::vector<Vector3>& points) const;

  double tolerance() const { return tolerance_m_; }
  /// Axis-aligned bounds of the tissue mesh [m].
  const Vector3& tissueMin() const { return tissue_.minCorner(); }
  const Vector3& tissueMax() const { return tissue_.maxCorner(); }
  const std::vector<ObstacleMesh3>& obstacles() const { return obstacles_; }

private:
  MeshDistance tissue_;
  std::vector<ObstacleMesh3> obstacles_;
  std::vector<MeshDistance> obstacle_distance_;
  double tolerance_m_;
};

}  // namespace needle_guidance::needle_model
