// Simple polygons in the plane of frame `scene` (dissertation 2.3.2 input anatomy model; 5.3
// obstacles expanded by a Minkowski sum for clearance).
//
// Predicates (orientation, segment intersection, point-in-polygon) are exact: they use the
// filtered exact predicates of CGAL's Exact_predicates_inexact_constructions_kernel on the
// double coordinates as given. Only constructions (intersection points, offsets converted back
// to double) are rounded.
#include "needle_guidance/geometry/polygon.h"

#include <CGAL/Exact_predicates_exact_constructions_kernel.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Polygon_2.h>
#include <CGAL/Polygon_with_holes_2.h>
#include <CGAL/intersections.h>
#include <CGAL/minkowski_sum_2.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <utility>

namespace needle_guidance::geometry {
namespace {

using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using CgalPoint = Kernel::Point_2;
using CgalSegment = Kernel::Segment_2;

/// Smallest number of vertices of the regular polygon that approximates the offset disc.
constexpr int kMinCircleVertices = 8;
/// Largest number of vertices of that regular polygon (bounds the Minkowski-sum cost).
constexpr int kMaxCircleVertices = 4096;

CgalPoint toCgal(const Point2& p) {
  return CgalPoint(p.x(), p.y());
}

/// Exact orientation of (a, b, c): +1 left turn, -1 right turn, 0 collinear.
int orient(const Point2& a, const Point2& b, const Point2& c) {
  return static_cast<int>(CGAL::orientation(toCgal(a), toCgal(b), toCgal(c)));
}

/// Exact test: p lies on the closed segment [a, b].
bool onSegment(const Point2& p, const Point2& a, const Point2& b) {
  if (orient(a, b, p) != 0) {
    return false;
  }
  return std::min(a.x(), b.x()) <= p.x() && p.x() <= std::max(a.x(), b.x()) &&
         std::min(a.y(), b.y()) <= p.y() && p.y() <= std::max(a.y(), b.y());
}

/// Exact test: the relative interiors of [a, b] and [c, d] cross at a single point.
bool properlyCross(const Point2& a, const Point2& b, const Point2& c, const Point2& d) {
  return orient(a, b, c) * orient(a, b, d) < 0 && orient(c, d, a) * orient(c, d, b) < 0;
}

enum class Side { kInside, kOutside, kBoundary };

/// Exact point classification by winding number (non-zero winding counts as inside).
Side pointSide(const std::vector<Point2>& vertices, const Point2& p) {
  const std::size_t n = vertices.size();
  int winding = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const Point2& a = vertices[i];
    const Point2& b = vertices[(i + 1) % n];
    if (onSegment(p, a, b)) {
      return Side::kBoundary;
    }
    if (a.y() <= p.y()) {
      if (b.y() > p.y() && orient(a, b, p) > 0) {
        ++winding;
      }
    } else {
      if (b.y() <= p.y() && orient(a, b, p) < 0) {
        --winding;
      }
    }
  }
  return winding != 0 ? Side::kInside : Side::kOutside;
}

/// Which open sides of a polygon a closed segment visits.
struct SidesVisited {
  bool interior = false;
  bool exterior = false;
};

/// Exact classification of which sides (interior / exterior) of `vertices` the segment [a, b]
/// passes through. Without proper crossings, the segment meets the boundary only at polygon
/// vertices on it and at its own end points; between consecutive such contacts it lies either
/// on one polygon edge or entirely on one side, which a sample point decides.
SidesVisited sidesVisited(const Point2& a, const Point2& b, const std::vector<Point2>& vertices) {
  SidesVisited visited;
  const std::size_t n = vertices.size();
  if (a == b) {
    const Side side = pointSide(vertices, a);
    visited.interior = side == Side::kInside;
    visited.exterior = side == Side::kOutside;
    return visited;
  }
  for (std::size_t i = 0; i < n; ++i) {
    if (properlyCross(a, b, vertices[i], vertices[(i + 1) % n])) {
      return {true, true};
    }
  }
  std::vector<Point2> contacts{a, b};
  for (const Point2& v : vertices) {
    if (onSegment(v, a, b)) {
      contacts.push_back(v);
    }
  }
  const Point2 direction = b - a;
  std::sort(contacts.begin(), contacts.end(), [&](const Point2& p, const Point2& q) {
    return (p - a).dot(direction) < (q - a).dot(direction);
  });
  contacts.erase(std::unique(contacts.begin(), contacts.end()), contacts.end());
  constexpr double kSampleFractions[] = {0.5, 0.25, 0.75, 0.125, 0.875};
  for (std::size_t k = 0; k + 1 < contacts.size(); ++k) {
    const Point2& p = contacts[k];
    const Point2& q = contacts[k + 1];
    bool on_boundary = false;
    for (std::size_t i = 0; i < n && !on_boundary; ++i) {
      const Point2& e0 = vertices[i];
      const Point2& e1 = vertices[(i + 1) % n];
      on_boundary = onSegment(p, e0, e1) && onSegment(q, e0, e1);
    }
    if (on_boundary) {
      continue;
    }
    // The open piece (p, q) does not meet the boundary; a rounded sample point could, in a
    // near-degenerate case, land on it, so a few samples are tried.
    for (double fraction : kSampleFractions) {
      const Side side = pointSide(vertices, p + fraction * (q - p));
      if (side == Side::kBoundary) {
        continue;
      }
      (side == Side::kInside ? visited.interior : visited.exterior) = true;
      break;
    }
    if (visited.interior && visited.exterior) {
      break;
    }
  }
  return visited;
}

/// A point common to two closed segments known to intersect.
Point2 commonPoint(const Segment& s, const Segment& t) {
  if (s.a == s.b) {
    return s.a;
  }
  if (t.a == t.b) {
    return t.a;
  }
  const auto result = CGAL::intersection(CgalSegment(toCgal(s.a), toCgal(s.b)),
                                         CgalSegment(toCgal(t.a), toCgal(t.b)));
  if (result) {
    if (const CgalPoint* p = boost::get<CgalPoint>(&*result)) {
      return Point2(p->x(), p->y());
    }
    if (const CgalSegment* seg = boost::get<CgalSegment>(&*result)) {
      return Point2(seg->source().x(), seg->source().y());
    }
  }
  return s.a;
}

std::string formatPoint(const Point2& p) {
  std::ostringstream out;
  out.precision(17);
  out << "(" << p.x() << ", " << p.y() << ")";
  return out.str();
}

}  // namespace

double pointSegmentDistance(const Point2& p, const Point2& a, const Point2& b) {
  const Point2 ab = b - a;
  const double length_sq = ab.squaredNorm();
  double t = length_sq > 0.0 ? (p - a).dot(ab) / length_sq : 0.0;
  t = std::clamp(t, 0.0, 1.0);
  return (a + t * ab - p).norm();
}

Polygon::Polygon(std::vector<Point2> vertices) : vertices_(std::move(vertices)) {
  const std::size_t n = vertices_.size();
  if (n < 3) {
    throw std::invalid_argument("Polygon: needs at least 3 vertices, got " + std::to_string(n));
  }
  for (std::size_t i = 0; i < n; ++i) {
    if (!vertices_[i].allFinite()) {
      throw std::invalid_argument("Polygon: vertex " + std::to_string(i) +
                                  " has a non-finite coordinate " + formatPoint(vertices_[i]));
    }
  }
  for (std::size_t i = 0; i < n; ++i) {
    if (vertices_[i] == vertices_[(i + 1) % n]) {
      throw std::invalid_argument("Polygon: vertices " + std::to_string(i) + " and " +
                                  std::to_string((i + 1) % n) + " are equal " +
                                  formatPoint(vertices_[i]));
    }
  }
}

Segment Polygon::edge(std::size_t i) const {
  if (i >= vertices_.size()) {
    throw std::invalid_argument("Polygon::edge: index " + std::to_string(i) + " out of range for " +
                                std::to_string(vertices_.size()) + " edges");
  }
  return Segment{vertices_[i], vertices_[(i + 1) % vertices_.size()]};
}

double Polygon::signedArea() const {
  // Shoelace relative to the first vertex, which limits cancellation for polygons far from
  // the origin.
  const std::size_t n = vertices_.size();
  if (n < 3) {
    return 0.0;
  }
  const Point2& origin = vertices_[0];
  double twice_area = 0.0;
  for (std::size_t i = 1; i + 1 < n; ++i) {
    const Point2 u = vertices_[i] - origin;
    const Point2 v = vertices_[i + 1] - origin;
    twice_area += u.x() * v.y() - u.y() * v.x();
  }
  return 0.5 * twice_area;
}

double Polygon::area() const {
  return std::abs(signedArea());
}

Polygon Polygon::counterClockwise() const {
  if (isCounterClockwise()) {
    return *this;
  }
  std::vector<Point2> reversed(vertices_.rbegin(), vertices_.rend());
  // Keep vertex 0 first so that indices stay recognisable.
  std::rotate(reversed.begin(), reversed.end() - 1, reversed.end());
  return Polygon(std::move(reversed));
}

bool Polygon::contains(const Point2& p, double tol_m) const {
  if (vertices_.size() < 3) {
    return false;
  }
  if (pointSide(vertices_, p) != Side::kOutside) {
    return true;
  }
  return tol_m > 0.0 && distanceToBoundary(p) <= tol_m;
}

double Polygon::distanceToBoundary(const Point2& p) const {
  const std::size_t n = vertices_.size();
  double distance_m = std::numeric_limits<double>::infinity();
  for (std::size_t i = 0; i < n; ++i) {
    distance_m =
        std::min(distance_m, pointSegmentDistance(p, vertices_[i], vertices_[(i + 1) % n]));
  }
  return distance_m;
}

std::optional<SelfIntersection> Polygon::selfIntersection() const {
  const std::size_t n = vertices_.size();
  if (n < 3) {
    return std::nullopt;
  }
  // Sweep over the edges sorted by their smallest x; only pairs with overlapping bounding
  // boxes are tested exactly. All intersecting pairs are considered so that the
  // lexicographically first pair is reported.
  std::vector<std::size_t> order(n);
  std::vector<double> x_min(n), x_max(n), y_min(n), y_max(n);
  for (std::size_t i = 0; i < n; ++i) {
    order[i] = i;
    const Point2& a = vertices_[i];
    const Point2& b = vertices_[(i + 1) % n];
    x_min[i] = std::min(a.x(), b.x());
    x_max[i] = std::max(a.x(), b.x());
    y_min[i] = std::min(a.y(), b.y());
    y_max[i] = std::max(a.y(), b.y());
  }
  std::sort(order.begin(), order.end(),
            [&](std::size_t i, std::size_t j) { return x_min[i] < x_min[j]; });
  std::optional<SelfIntersection> first;
  auto consider = [&](std::size_t i, std::size_t j, const Point2& point) {
    if (i > j) {
      std::swap(i, j);
    }
    if (!first || std::make_pair(i, j) < std::make_pair(first->edge_a, first->edge_b)) {
      first = SelfIntersection{i, j, point};
    }
  };
  for (std::size_t k = 0; k < n; ++k) {
    const std::size_t i = order[k];
    for (std::size_t l = k + 1; l < n && x_min[order[l]] <= x_max[i]; ++l) {
      const std::size_t j = order[l];
      if (y_min[j] > y_max[i] || y_min[i] > y_max[j]) {
        continue;
      }
      const std::size_t lo = std::min(i, j);
      const std::size_t hi = std::max(i, j);
      const bool adjacent = hi == lo + 1 || (lo == 0 && hi == n - 1);
      if (adjacent) {
        // Adjacent edges share a vertex; they overlap beyond it only when they fold back
        // along one line (a spike, or a zero-area polygon).
        const std::size_t shared = (hi == lo + 1) ? hi : 0;
        const Point2& before = vertices_[(shared + n - 1) % n];
        const Point2& at = vertices_[shared];
        const Point2& after = vertices_[(shared + 1) % n];
        if (orient(before, at, after) == 0 &&
            !CGAL::collinear_are_ordered_along_line(toCgal(before), toCgal(at), toCgal(after))) {
          consider(lo, hi, at);
        }
      } else {
        const Segment s = edge(lo);
        const Segment t = edge(hi);
        if (segmentsIntersect(s, t)) {
          consider(lo, hi, commonPoint(s, t));
        }
      }
    }
  }
  if (!first && signedArea() == 0.0) {
    // Not reachable for exact input (a polygon without touching edges has positive area), but
    // kept so that a zero-area polygon can never be reported as simple.
    first = SelfIntersection{0, 1, vertices_[1]};
  }
  return first;
}

Point2 Polygon::minCorner() const {
  Point2 corner = Point2::Constant(std::numeric_limits<double>::infinity());
  for (const Point2& v : vertices_) {
    corner = corner.cwiseMin(v);
  }
  return corner;
}

Point2 Polygon::maxCorner() const {
  Point2 corner = Point2::Constant(-std::numeric_limits<double>::infinity());
  for (const Point2& v : vertices_) {
    corner = corner.cwiseMax(v);
  }
  return corner;
}

Polygon Polygon::offset(double clearance_m, double max_chord_error_m) const {
  if (!std::isfinite(clearance_m) || clearance_m < 0.0) {
    throw std::invalid_argument("Polygon::offset: clearance_m must be finite and >= 0, got " +
                                std::to_string(clearance_m));
  }
  if (!std::isfinite(max_chord_error_m) || max_chord_error_m <= 0.0) {
    throw std::invalid_argument("Polygon::offset: max_chord_error_m must be finite and > 0, got " +
                                std::to_string(max_chord_error_m));
  }
  if (vertices_.size() < 3) {
    throw std::invalid_argument("Polygon::offset: empty polygon");
  }
  if (clearance_m == 0.0) {
    return *this;
  }
  if (const auto crossing = selfIntersection()) {
    throw std::invalid_argument("Polygon::offset: polygon self-intersects at edges " +
                                std::to_string(crossing->edge_a) + " and " +
                                std::to_string(crossing->edge_b));
  }

  // Obstacle expansion by the minimum clearance (5.3): the Minkowski sum of the polygon with a
  // disc of radius clearance_m. The disc is replaced by the regular N-gon inscribed in it, so
  // every vertex of the result lies on the true offset curve and every edge is at most the
  // sagitta clearance_m * (1 - cos(pi / N)) <= max_chord_error_m inside it. N is a multiple of
  // 4 with a vertex on each axis, so axis-aligned edges are offset by exactly clearance_m.
  // CGAL's reduced-convolution Minkowski sum handles non-convex polygons (the union of the
  // swept edges, which is hard to get right by hand); it needs exact constructions, hence the
  // exact kernel here.
  using ExactKernel = CGAL::Exact_predicates_exact_constructions_kernel;
  using ExactPolygon = CGAL::Polygon_2<ExactKernel>;
  const double half_angle_rad = std::acos(std::max(-1.0, 1.0 - max_chord_error_m / clearance_m));
  const double needed = half_angle_rad > 0.0 ? M_PI / half_angle_rad : kMaxCircleVertices + 1.0;
  if (needed > kMaxCircleVertices) {
    throw std::invalid_argument(
        "Polygon::offset: max_chord_error_m = " + std::to_string(max_chord_error_m) +
        " is too small for clearance_m = " + std::to_string(clearance_m) + " (needs more than " +
        std::to_string(kMaxCircleVertices) + " arc vertices)");
  }
  int circle_vertices = std::max(kMinCircleVertices, static_cast<int>(std::ceil(needed)));
  circle_vertices = (circle_vertices + 3) / 4 * 4;

  ExactPolygon disc;
  for (int k = 0; k < circle_vertices; ++k) {
    const double angle_rad = 2.0 * M_PI * k / circle_vertices;
    double x = std::cos(angle_rad);
    double y = std::sin(angle_rad);
    // Exact axis points (cos(pi/2) is not exactly 0 in floating point).
    if (4 * k == circle_vertices) {
      x = 0.0;
      y = 1.0;
    }
    if (2 * k == circle_vertices) {
      x = -1.0;
      y = 0.0;
    }
    if (4 * k == 3 * circle_vertices) {
      x = 0.0;
      y = -1.0;
    }
    disc.push_back(ExactKernel::Point_2(clearance_m * x, clearance_m * y));
  }
  ExactPolygon original;
  const Polygon ccw = counterClockwise();
  for (const Point2& v : ccw.vertices()) {
    original.push_back(ExactKernel::Point_2(v.x(), v.y()));
  }
  const CGAL::Polygon_with_holes_2<ExactKernel> sum = CGAL::minkowski_sum_2(original, disc);

  // Holes of the sum (pockets enclosed by the expanded obstacle) are dropped: the expanded
  // obstacle is the filled outer boundary, which is the conservative choice for clearance.
  std::vector<Point2> result;
  result.reserve(sum.outer_boundary().size());
  for (auto it = sum.outer_boundary().vertices_begin(); it != sum.outer_boundary().vertices_end();
       ++it) {
    const Point2 p(CGAL::to_double(it->x()), CGAL::to_double(it->y()));
    if (result.empty() || result.back() != p) {
      result.push_back(p);
    }
  }
  while (result.size() > 1 && result.front() == result.back()) {
    result.pop_back();
  }
  Polygon expanded(std::move(result));
  return expanded.counterClockwise();
}

bool segmentsIntersect(const Segment& s, const Segment& t) {
  const bool s_point = s.a == s.b;
  const bool t_point = t.a == t.b;
  if (s_point && t_point) {
    return s.a == t.a;
  }
  if (s_point) {
    return onSegment(s.a, t.a, t.b);
  }
  if (t_point) {
    return onSegment(t.a, s.a, s.b);
  }
  return CGAL::do_intersect(CgalSegment(toCgal(s.a), toCgal(s.b)),
                            CgalSegment(toCgal(t.a), toCgal(t.b)));
}

bool polygonsOverlap(const Polygon& a, const Polygon& b) {
  for (const auto& [polygon, name] : {std::pair<const Polygon*, const char*>{&a, "a"},
                                      std::pair<const Polygon*, const char*>{&b, "b"}}) {
    if (polygon->size() < 3) {
      throw std::invalid_argument(std::string("polygonsOverlap: polygon ") + name + " is empty");
    }
    if (const auto crossing = polygon->selfIntersection()) {
      throw std::invalid_argument(std::string("polygonsOverlap: polygon ") + name +
                                  " self-intersects at edges " + std::to_string(crossing->edge_a) +
                                  " and " + std::to_string(crossing->edge_b));
    }
  }
  // Bounding boxes whose interiors are disjoint cannot hold overlapping interiors.
  const Point2 lo = a.minCorner().cwiseMax(b.minCorner());
  const Point2 hi = a.maxCorner().cwiseMin(b.maxCorner());
  if (lo.x() >= hi.x() || lo.y() >= hi.y()) {
    return false;
  }
  // For simple polygons A and B: if no edge of A enters int(B) and no edge of B enters int(A),
  // then int(A) and int(B) are either disjoint or equal (a component of their intersection is
  // bounded by boundary of both, hence is all of int(A) and all of int(B)). They are equal
  // exactly when the boundary of A also never leaves B, i.e. no edge of A enters ext(B).
  bool a_enters_exterior_of_b = false;
  for (std::size_t i = 0; i < a.size(); ++i) {
    const Segment e = a.edge(i);
    const SidesVisited visited = sidesVisited(e.a, e.b, b.vertices());
    if (visited.interior) {
      return true;
    }
    a_enters_exterior_of_b = a_enters_exterior_of_b || visited.exterior;
  }
  for (std::size_t i = 0; i < b.size(); ++i) {
    const Segment e = b.edge(i);
    if (sidesVisited(e.a, e.b, a.vertices()).interior) {
      return true;
    }
  }
  return !a_enters_exterior_of_b;
}

bool segmentIntersectsPolygon(const Segment& s, const Polygon& poly) {
  // "Enters the interior": a segment that only touches the boundary (grazes a vertex or runs
  // along an edge from outside) does not count; crossing the boundary always enters.
  if (poly.size() < 3) {
    return false;
  }
  return sidesVisited(s.a, s.b, poly.vertices()).interior;
}

bool polygonInside(const Polygon& inner, const Polygon& outer) {
  for (const auto& [polygon, name] : {std::pair<const Polygon*, const char*>{&inner, "inner"},
                                      std::pair<const Polygon*, const char*>{&outer, "outer"}}) {
    if (polygon->size() < 3) {
      throw std::invalid_argument(std::string("polygonInside: polygon ") + name + " is empty");
    }
    if (const auto crossing = polygon->selfIntersection()) {
      throw std::invalid_argument(std::string("polygonInside: polygon ") + name +
                                  " self-intersects at edges " + std::to_string(crossing->edge_a) +
                                  " and " + std::to_string(crossing->edge_b));
    }
  }
  // The exterior of a simple polygon is connected and unbounded: if the boundary of `inner`
  // never enters it, neither does the interior of `inner`.
  for (std::size_t i = 0; i < inner.size(); ++i) {
    const Segment e = inner.edge(i);
    if (sidesVisited(e.a, e.b, outer.vertices()).exterior) {
      return false;
    }
  }
  return true;
}

}  // namespace needle_guidance::geometry
