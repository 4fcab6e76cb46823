// The continuous world of the planar needle (dissertation 5.3), without any discretisation:
// exact constant-curvature arcs from any pose, continuous deflection angles, and contact checks
// against the expanded obstacles and the workspace boundary along the arc. The simulated
// steerable needle of the insertion robot moves in it; the steering module's Monte Carlo truth
// check and shortest-path baseline use it through steering::ContinuousWorkspace. Plain C++; no
// ROS.
#pragma once

#include <string>
#include <vector>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/needle_model/needle_2d.h"
#include "needle_guidance/scene/scene.h"

namespace needle_guidance::needle_model {

/// What the planar needle moves in: the workspace rectangle, the obstacles (expanded by their
/// clearance), one circular target and the needle's radius of curvature.
struct PlanarWorkspace {
  Point2 workspace_min = Point2::Zero();   ///< [m]
  Point2 workspace_max = Point2::Zero();   ///< [m]
  std::vector<scene::Obstacle> obstacles;  ///< polygons as given plus clearance_m [m]
  scene::Target target;                    ///< the closed disc [m]
  double radius_m = 0.0;                   ///< r, radius of curvature of the needle path [m]
};

/// What happened along one arc.
enum class ArcOutcome {
  kFree,           ///< the whole arc stays inside the workspace and outside every obstacle
  kObstacle,       ///< the arc touches an expanded obstacle (or starts inside one)
  kLeftWorkspace,  ///< the arc leaves the workspace rectangle (or starts outside it)
};
/// "free" | "obstacle" | "left_workspace".
std::string toString(ArcOutcome outcome);

/// Result of PlanarWorld::traceArc.
struct ArcTrace {
  ArcOutcome outcome = ArcOutcome::kFree;
  /// Arc length travelled before the first contact (the whole arc when free) [m].
  double free_length_m = 0.0;
  /// The pose at the end of the arc, or at the first contact [m, rad].
  TipPose end;
  /// Name of the obstacle touched first ("" unless kObstacle).
  std::string obstacle;
};

/// A PlanarWorkspace with its obstacles expanded by their clearance (to within
/// chord_tolerance_m, independent of any grid), ready for arc tracing.
class PlanarWorld {
public:
  /// Throws std::invalid_argument for an empty workspace, a negative clearance or target
  /// radius, a non-positive radius of curvature or chord tolerance.
  explicit PlanarWorld(const PlanarWorkspace& workspace, double chord_tolerance_m = 1e-5);

  const PlanarWorkspace& workspace() const { return workspace_; }
  /// Expanded obstacles, counter-clockwise, in workspace().obstacles order [m].
  const std::vector<geometry::Polygon>& expandedObstacles() const { return expanded_; }

  /// True if p lies in the closed target disc.
  bool inTarget(const Point2& p) const;
  /// True if p lies inside (or on) the closed workspace rectangle.
  bool inWorkspace(const Point2& p) const;
  /// Index of the expanded obstacle containing p, or -1.
  int obstacleAt(const Point2& p) const;

  /// Traces the arc of advanceTip(from, control, beta_rad, arc_length_m, r) and reports the
  /// first contact with an expanded obstacle or the workspace boundary (a tip exactly on the
  /// boundary is inside). The arc is followed as a polyline whose chords lie within the chord
  /// tolerance of the true arc. Non-finite input gives kLeftWorkspace with free_length_m = 0.
  ArcTrace traceArc(const TipPose& from, Control control, double beta_rad,
                    double arc_length_m) const;

private:
  PlanarWorkspace workspace_;
  double chord_tolerance_m_;
  std::vector<geometry::Polygon> expanded_;
  std::vector<Point2> box_min_, box_max_;
};

}  // namespace needle_guidance::needle_model
