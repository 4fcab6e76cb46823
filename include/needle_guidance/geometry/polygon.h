// Simple polygons in the plane of frame `scene` (dissertation 2.3.2, 5.3).
#pragma once

#include <Eigen/Core>
#include <optional>
#include <string>
#include <vector>

namespace needle_guidance::geometry {

/// A point or vector in the x–y plane of frame `scene` [m].
using Point2 = Eigen::Vector2d;

/// A closed line segment between two points [m].
struct Segment {
  Point2 a;
  Point2 b;
};

/// Where a polygon's boundary crosses itself: the two edges (edge i joins vertex i and i+1).
struct SelfIntersection {
  std::size_t edge_a = 0;
  std::size_t edge_b = 0;
  Point2 point = Point2::Zero();  ///< a point shared by both edges [m]
};

/// A simple polygon given by its vertices, implicitly closed (the last vertex joins the first;
/// the first vertex is not repeated). Orientation may be either; see isCounterClockwise().
class Polygon {
public:
  Polygon() = default;
  /// @param[in] vertices at least 3 vertices [m]; throws std::invalid_argument on fewer,
  ///            on a non-finite coordinate, or on two consecutive equal vertices.
  explicit Polygon(std::vector<Point2> vertices);

  /// Vertices in the order given [m].
  const std::vector<Point2>& vertices() const { return vertices_; }
  std::size_t size() const { return vertices_.size(); }
  /// Edge i from vertex i to vertex (i+1) mod n.
  Segment edge(std::size_t i) const;

  /// Signed area (shoelace) [m^2]: positive when counter-clockwise.
  double signedArea() const;
  /// Absolute area [m^2].
  double area() const;
  bool isCounterClockwise() const { return signedArea() > 0.0; }
  /// The same polygon with counter-clockwise orientation.
  Polygon counterClockwise() const;

  /// True if p is inside or on the boundary (boundary within tol_m counts as inside).
  bool contains(const Point2& p, double tol_m = 0.0) const;
  /// Distance from p to the nearest boundary point [m] (zero on the boundary).
  double distanceToBoundary(const Point2& p) const;

  /// First pair of non-adjacent edges that touch or cross, or nullopt for a simple polygon.
  /// Also reports a zero-area (collinear) polygon as self-intersecting.
  std::optional<SelfIntersection> selfIntersection() const;

  /// Axis-aligned bounds [m].
  Point2 minCorner() const;
  Point2 maxCorner() const;

  /// Outward offset (Minkowski sum with a disc of radius clearance_m, arcs approximated by
  /// polygon vertices at most max_chord_error_m inside the true arc) [m]. clearance_m = 0
  /// returns a copy; clearance_m < 0 throws std::invalid_argument. The result is
  /// counter-clockwise and simple. Used to expand obstacles by a minimum clearance (5.3).
  Polygon offset(double clearance_m, double max_chord_error_m = 1e-4) const;

private:
  std::vector<Point2> vertices_;
};

/// Distance from p to the closed segment [a, b] [m].
double pointSegmentDistance(const Point2& p, const Point2& a, const Point2& b);

/// True if two closed segments share at least one point (exact predicates, robust to
/// collinear overlap and shared end points).
bool segmentsIntersect(const Segment& s, const Segment& t);

/// True if the interiors of two simple polygons overlap with positive area. Polygons that only
/// share boundary (edges or vertices) do not overlap.
bool polygonsOverlap(const Polygon& a, const Polygon& b);

/// True if the segment enters the interior of the polygon or crosses its boundary.
bool segmentIntersectsPolygon(const Segment& s, const Polygon& poly);

/// True if the simple polygon `inner` lies inside the closed simple polygon `outer` (their
/// boundaries may touch or share edges). Exact predicates. Throws std::invalid_argument if
/// either polygon self-intersects.
bool polygonInside(const Polygon& inner, const Polygon& outer);

}  // namespace needle_guidance::geometry
