// Triangle meshes of segmented regions (dissertation 2.3.2): constrained Delaunay triangulation
// of the domain with the region outlines and refinement lines as constraints, then Delaunay
// refinement (CGAL Mesh_2) with a quality bound and an element size graded towards the
// refinement features.
#include "needle_guidance/geometry/triangle_mesh.h"

#include <CGAL/Constrained_Delaunay_triangulation_2.h>
#include <CGAL/Delaunay_mesh_face_base_2.h>
#include <CGAL/Delaunay_mesh_size_criteria_2.h>
#include <CGAL/Delaunay_mesher_2.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Triangulation_face_base_with_info_2.h>
#include <CGAL/Triangulation_vertex_base_with_info_2.h>
#include <CGAL/intersections.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <map>
#include <queue>
#include <sstream>
#include <stdexcept>
#include <unordered_map>
#include <utility>

namespace needle_guidance::geometry {
namespace {

using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Vb = CGAL::Triangulation_vertex_base_with_info_2<int, Kernel>;
using FbInfo =
    CGAL::Triangulation_face_base_with_info_2<int, Kernel,
                                              CGAL::Constrained_triangulation_face_base_2<Kernel>>;
using Fb = CGAL::Delaunay_mesh_face_base_2<Kernel, FbInfo>;
using Tds = CGAL::Triangulation_data_structure_2<Vb, Fb>;
// Exact_predicates_tag: refinement lines may cross region outlines; the triangulation then
// inserts the crossing point as a vertex of both constraints.
using Cdt = CGAL::Constrained_Delaunay_triangulation_2<Kernel, Tds, CGAL::Exact_predicates_tag>;
using CdtPoint = Cdt::Point;
using FaceHandle = Cdt::Face_handle;

/// Largest quality bound accepted [deg]; Delaunay refinement is not known to terminate above.
constexpr double kMaxMinAngleDeg = 30.0;
/// Input points closer than this fraction of min_edge_m to a constraint are snapped onto it, so
/// that no near-degenerate feature (a vertex a rounding error away from an edge) forces
/// unbounded refinement.
constexpr double kSnapRelTol = 1e-6;

CdtPoint toCgal(const Point2& p) {
  return CdtPoint(p.x(), p.y());
}
Point2 fromCgal(const CdtPoint& p) {
  return Point2(p.x(), p.y());
}

std::string formatDouble(double value) {
  std::ostringstream out;
  out.precision(9);
  out << value;
  return out.str();
}

/// Target edge length [m] graded towards the refinement points and lines:
/// size(p) = min + (max - min) * clamp(dist(p, features) / grading_length, 0, 1).
class SizeField {
public:
  explicit SizeField(const MeshingOptions& options)
      : min_edge_m_(options.min_edge_m),
        max_edge_m_(options.max_edge_m),
        grading_length_m_(options.grading_length_m),
        points_(options.refine_points),
        lines_(options.refine_lines) {}

  double operator()(const Point2& p) const {
    if (min_edge_m_ == max_edge_m_) {
      return max_edge_m_;
    }
    double distance_m = grading_length_m_;
    for (const Point2& q : points_) {
      distance_m = std::min(distance_m, (p - q).norm());
    }
    for (const Segment& s : lines_) {
      distance_m = std::min(distance_m, pointSegmentDistance(p, s.a, s.b));
    }
    return min_edge_m_ +
           (max_edge_m_ - min_edge_m_) * std::clamp(distance_m / grading_length_m_, 0.0, 1.0);
  }

private:
  double min_edge_m_;
  double max_edge_m_;
  double grading_length_m_;
  std::vector<Point2> points_;
  std::vector<Segment> lines_;
};

/// Mesh criteria of CGAL's Delaunay_mesh_size_criteria_2 with the constant size bound replaced
/// by the graded size field evaluated at the triangle's centroid: a triangle is imperatively
/// bad when its longest edge exceeds the local size, and bad when its smallest angle is below
/// the quality bound.
class GradedSizeCriteria : public CGAL::Delaunay_mesh_size_criteria_2<Cdt> {
public:
  using Base = CGAL::Delaunay_mesh_size_criteria_2<Cdt>;
  using Quality = Base::Quality;

  /// @param[in] squared_sine_bound sin^2 of the minimum angle
  /// @param[in] size_field kept by pointer; must outlive the criteria
  GradedSizeCriteria(double squared_sine_bound, const SizeField* size_field)
      : CGAL::Delaunay_mesh_criteria_2<Cdt>(squared_sine_bound),
        Base(squared_sine_bound, 0.0),
        size_field_(size_field) {}

  /// Badness test used by the mesher (the name is required by CGAL's mesher).
  // NOLINTNEXTLINE(readability-identifier-naming)
  class Is_bad : public CGAL::Delaunay_mesh_criteria_2<Cdt>::Is_bad {
  public:
    using Parent = CGAL::Delaunay_mesh_criteria_2<Cdt>::Is_bad;

    Is_bad(double squared_sine_bound, const SizeField* size_field, const Kernel& traits)
        : Parent(squared_sine_bound, traits), size_field_(size_field) {}

    CGAL::Mesh_2::Face_badness operator()(const Quality q) const {
      if (q.size() > 1) {
        return CGAL::Mesh_2::IMPERATIVELY_BAD;
      }
      if (q.sine() < this->B) {
        return CGAL::Mesh_2::BAD;
      }
      return CGAL::Mesh_2::NOT_BAD;
    }

    CGAL::Mesh_2::Face_badness operator()(const FaceHandle& fh, Quality& q) const {
      const CdtPoint& pa = fh->vertex(0)->point();
      const CdtPoint& pb = fh->vertex(1)->point();
      const CdtPoint& pc = fh->vertex(2)->point();
      // Squared edge lengths sorted so that shortest <= middle <= longest.
      double shortest = CGAL::to_double(CGAL::squared_distance(pb, pc));
      double middle = CGAL::to_double(CGAL::squared_distance(pc, pa));
      double longest = CGAL::to_double(CGAL::squared_distance(pa, pb));
      if (shortest > middle) {
        std::swap(shortest, middle);
      }
      if (middle > longest) {
        std::swap(middle, longest);
      }
      if (shortest > middle) {
        std::swap(shortest, middle);
      }
      const double max_sq_length = longest;
      const double second_max_sq_length = middle;

      const Point2 centroid((pa.x() + pb.x() + pc.x()) / 3.0, (pa.y() + pb.y() + pc.y()) / 3.0);
      const double size_m = (*size_field_)(centroid);
      q.second = max_sq_length / (size_m * size_m);
      if (q.size() > 1) {
        q.first = 1;  // the sine is not needed
        return CGAL::Mesh_2::IMPERATIVELY_BAD;
      }
      const double twice_area = 2.0 * CGAL::to_double(CGAL::area(pa, pb, pc));
      q.first = (twice_area * twice_area) / (max_sq_length * second_max_sq_length);  // sin^2
      return q.sine() < this->B ? CGAL::Mesh_2::BAD : CGAL::Mesh_2::NOT_BAD;
    }

  private:
    const SizeField* size_field_;
  };

  /// The badness functor CGAL's mesher asks for (name required by CGAL).
  // NOLINTNEXTLINE(readability-identifier-naming)
  Is_bad is_bad_object() const { return Is_bad(this->bound(), size_field_, this->traits); }

private:
  const SizeField* size_field_;
};

/// A closed constraint polyline that may receive extra vertices by snapping.
struct Outline {
  std::string name;            ///< for error messages
  std::vector<Point2> points;  ///< closed polyline [m]
};

/// Snaps p onto the outlines: onto a vertex within tol_m (p moves), or, within tol_m of an edge
/// interior, inserts p as a new vertex of that edge (the outline bends by at most tol_m).
/// `skip` is an outline p belongs to (or nullptr).
void snapPoint(Point2& p, std::vector<Outline>& outlines, const Outline* skip, double tol_m) {
  for (Outline& outline : outlines) {
    if (&outline == skip) {
      continue;
    }
    std::vector<Point2>& pts = outline.points;
    for (const Point2& v : pts) {
      if (v != p && (v - p).norm() <= tol_m) {
        p = v;
        break;
      }
    }
  }
  for (Outline& outline : outlines) {
    if (&outline == skip) {
      continue;
    }
    std::vector<Point2>& pts = outline.points;
    const std::size_t n = pts.size();
    bool on_vertex = false;
    for (const Point2& v : pts) {
      on_vertex = on_vertex || v == p;
    }
    if (on_vertex) {
      continue;
    }
    for (std::size_t i = 0; i < n; ++i) {
      const Point2& a = pts[i];
      const Point2& b = pts[(i + 1) % n];
      if (pointSegmentDistance(p, a, b) <= tol_m) {
        pts.insert(pts.begin() + static_cast<std::ptrdiff_t>(i + 1), p);
        break;
      }
    }
  }
}

/// Pieces of the segment inside the closed domain (dissertation: needle paths clipped to the
/// tissue). Piece end points are the segment's end points or boundary crossing points.
std::vector<Segment> clipToDomain(const Segment& line, const Polygon& domain) {
  const Point2 direction = line.b - line.a;
  const double length_sq = direction.squaredNorm();
  std::vector<std::pair<double, Point2>> cuts{{0.0, line.a}, {1.0, line.b}};
  const Kernel::Segment_2 cgal_line(toCgal(line.a), toCgal(line.b));
  for (std::size_t i = 0; i < domain.size(); ++i) {
    const Segment e = domain.edge(i);
    if (!segmentsIntersect(line, e)) {
      continue;
    }
    const auto result = CGAL::intersection(cgal_line, Kernel::Segment_2(toCgal(e.a), toCgal(e.b)));
    if (!result) {
      continue;
    }
    auto add = [&](const CdtPoint& q) {
      const Point2 p = fromCgal(q);
      cuts.emplace_back(std::clamp((p - line.a).dot(direction) / length_sq, 0.0, 1.0), p);
    };
    if (const CdtPoint* p = boost::get<CdtPoint>(&*result)) {
      add(*p);
    }
    if (const Kernel::Segment_2* s = boost::get<Kernel::Segment_2>(&*result)) {
      add(s->source());
      add(s->target());
    }
  }
  std::sort(cuts.begin(), cuts.end(),
            [](const auto& x, const auto& y) { return x.first < y.first; });
  std::vector<Segment> pieces;
  bool open = false;
  for (std::size_t k = 0; k + 1 < cuts.size(); ++k) {
    if (cuts[k + 1].first <= cuts[k].first) {
      continue;
    }
    const Point2 middle = line.a + 0.5 * (cuts[k].first + cuts[k + 1].first) * direction;
    if (domain.contains(middle)) {
      if (open) {
        pieces.back().b = cuts[k + 1].second;
      } else {
        pieces.push_back(Segment{cuts[k].second, cuts[k + 1].second});
        open = true;
      }
    } else {
      open = false;
    }
  }
  return pieces;
}

void validateOptions(const MeshingOptions& options) {
  auto require = [](bool ok, const std::string& message) {
    if (!ok) {
      throw std::invalid_argument("meshDomain: " + message);
    }
  };
  require(std::isfinite(options.max_edge_m) && options.max_edge_m > 0.0,
          "max_edge_m must be positive and finite, got " + formatDouble(options.max_edge_m));
  require(std::isfinite(options.min_edge_m) && options.min_edge_m > 0.0,
          "min_edge_m must be positive and finite, got " + formatDouble(options.min_edge_m));
  require(options.min_edge_m <= options.max_edge_m,
          "min_edge_m = " + formatDouble(options.min_edge_m) +
              " exceeds max_edge_m = " + formatDouble(options.max_edge_m));
  require(std::isfinite(options.grading_length_m) && options.grading_length_m > 0.0,
          "grading_length_m must be positive and finite, got " +
              formatDouble(options.grading_length_m));
  require(std::isfinite(options.min_angle_deg) && options.min_angle_deg >= 0.0 &&
              options.min_angle_deg <= kMaxMinAngleDeg,
          "min_angle_deg must be in [0, 30], got " + formatDouble(options.min_angle_deg));
  for (std::size_t i = 0; i < options.refine_points.size(); ++i) {
    require(options.refine_points[i].allFinite(),
            "refine point " + std::to_string(i) + " is not finite");
  }
  for (std::size_t i = 0; i < options.refine_lines.size(); ++i) {
    require(options.refine_lines[i].a.allFinite() && options.refine_lines[i].b.allFinite(),
            "refine line " + std::to_string(i) + " is not finite");
  }
}

void validateRegions(const Polygon& domain, const std::vector<MeshRegion>& regions) {
  if (domain.size() < 3) {
    throw std::invalid_argument("meshDomain: domain polygon is empty");
  }
  if (const auto crossing = domain.selfIntersection()) {
    throw std::invalid_argument("meshDomain: domain polygon self-intersects at edges " +
                                std::to_string(crossing->edge_a) + " and " +
                                std::to_string(crossing->edge_b));
  }
  for (const MeshRegion& region : regions) {
    const std::string label = "meshDomain: region '" + region.name + "' polygon";
    if (region.polygon.size() < 3) {
      throw std::invalid_argument(label + " is empty");
    }
    if (const auto crossing = region.polygon.selfIntersection()) {
      throw std::invalid_argument(label + " self-intersects at edges " +
                                  std::to_string(crossing->edge_a) + " and " +
                                  std::to_string(crossing->edge_b));
    }
    if (!polygonInside(region.polygon, domain)) {
      throw std::invalid_argument(label + " is not inside the domain");
    }
  }
  for (std::size_t i = 0; i < regions.size(); ++i) {
    for (std::size_t j = i + 1; j < regions.size(); ++j) {
      if (polygonsOverlap(regions[i].polygon, regions[j].polygon)) {
        throw std::invalid_argument("meshDomain: region '" + regions[i].name +
                                    "' polygon overlaps region '" + regions[j].name + "'");
      }
    }
  }
}

/// Labels the connected components of finite faces (connected across unconstrained edges);
/// returns one representative face per component (the largest, for a robust centroid test).
std::vector<FaceHandle> labelComponents(Cdt& cdt, bool in_domain_only) {
  for (auto f = cdt.all_faces_begin(); f != cdt.all_faces_end(); ++f) {
    f->info() = -1;
  }
  std::vector<FaceHandle> representatives;
  for (auto start = cdt.finite_faces_begin(); start != cdt.finite_faces_end(); ++start) {
    if (start->info() >= 0 || (in_domain_only && !start->is_in_domain())) {
      continue;
    }
    const int component = static_cast<int>(representatives.size());
    FaceHandle best = start;
    double best_area = -1.0;
    std::queue<FaceHandle> queue;
    start->info() = component;
    queue.push(start);
    while (!queue.empty()) {
      const FaceHandle f = queue.front();
      queue.pop();
      const double area = std::abs(CGAL::to_double(
          CGAL::area(f->vertex(0)->point(), f->vertex(1)->point(), f->vertex(2)->point())));
      if (area > best_area) {
        best_area = area;
        best = f;
      }
      for (int i = 0; i < 3; ++i) {
        const FaceHandle neighbor = f->neighbor(i);
        if (f->is_constrained(i) || cdt.is_infinite(neighbor) || neighbor->info() >= 0) {
          continue;
        }
        if (in_domain_only && !neighbor->is_in_domain()) {
          continue;
        }
        neighbor->info() = component;
        queue.push(neighbor);
      }
    }
    representatives.push_back(best);
  }
  return representatives;
}

Point2 centroid(const FaceHandle& f) {
  return (fromCgal(f->vertex(0)->point()) + fromCgal(f->vertex(1)->point()) +
          fromCgal(f->vertex(2)->point())) /
         3.0;
}

}  // namespace

double TriangleMesh::triangleArea(std::size_t t) const {
  if (t >= triangles.size()) {
    throw std::invalid_argument("TriangleMesh::triangleArea: index " + std::to_string(t) +
                                " out of range for " + std::to_string(triangles.size()) +
                                " triangles");
  }
  const Point2& a = nodes.at(static_cast<std::size_t>(triangles[t][0]));
  const Point2& b = nodes.at(static_cast<std::size_t>(triangles[t][1]));
  const Point2& c = nodes.at(static_cast<std::size_t>(triangles[t][2]));
  const Point2 u = b - a;
  const Point2 v = c - a;
  return 0.5 * (u.x() * v.y() - u.y() * v.x());
}

double TriangleMesh::totalArea() const {
  double area_m2 = 0.0;
  for (std::size_t t = 0; t < triangles.size(); ++t) {
    area_m2 += triangleArea(t);
  }
  return area_m2;
}

std::vector<int> TriangleMesh::boundaryNodes() const {
  std::unordered_map<std::uint64_t, int> edge_use;
  edge_use.reserve(triangles.size() * 3);
  for (const auto& triangle : triangles) {
    for (int k = 0; k < 3; ++k) {
      const auto lo = static_cast<std::uint32_t>(std::min(triangle[k], triangle[(k + 1) % 3]));
      const auto hi = static_cast<std::uint32_t>(std::max(triangle[k], triangle[(k + 1) % 3]));
      ++edge_use[(static_cast<std::uint64_t>(lo) << 32) | hi];
    }
  }
  std::vector<int> boundary;
  for (const auto& [key, count] : edge_use) {
    if (count != 1) {
      continue;
    }
    boundary.push_back(static_cast<int>(key >> 32));
    boundary.push_back(static_cast<int>(key & 0xffffffffu));
  }
  std::sort(boundary.begin(), boundary.end());
  boundary.erase(std::unique(boundary.begin(), boundary.end()), boundary.end());
  return boundary;
}

TriangleMesh meshDomain(const Polygon& domain, const std::string& background_name,
                        const std::vector<MeshRegion>& regions, const MeshingOptions& options) {
  validateOptions(options);
  validateRegions(domain, regions);
  const double snap_tol_m = kSnapRelTol * options.min_edge_m;

  // Constraint outlines: the domain (index 0) and the regions (index i + 1), possibly with
  // extra vertices where other input points touch them.
  std::vector<Outline> outlines;
  outlines.push_back(Outline{"domain", domain.vertices()});
  for (const MeshRegion& region : regions) {
    outlines.push_back(Outline{region.name, region.polygon.vertices()});
  }
  for (std::size_t k = 1; k < outlines.size(); ++k) {
    std::vector<Point2> own = outlines[k].points;
    for (Point2& p : own) {
      snapPoint(p, outlines, &outlines[k], snap_tol_m);
    }
    outlines[k].points = own;
    // A snap onto a neighbour's vertex could in principle make two consecutive vertices equal.
    auto& pts = outlines[k].points;
    pts.erase(std::unique(pts.begin(), pts.end()), pts.end());
    while (pts.size() > 1 && pts.front() == pts.back()) {
      pts.pop_back();
    }
  }

  // Refinement lines are clipped to the domain (their crossing points become domain
  // vertices); refinement points inside the domain become mesh nodes.
  std::vector<Segment> line_pieces;
  std::vector<Point2> points;
  for (const Segment& line : options.refine_lines) {
    if (line.a == line.b) {
      points.push_back(line.a);
      continue;
    }
    for (Segment piece : clipToDomain(line, domain)) {
      snapPoint(piece.a, outlines, nullptr, snap_tol_m);
      snapPoint(piece.b, outlines, nullptr, snap_tol_m);
      if (piece.a != piece.b) {
        line_pieces.push_back(piece);
      }
    }
  }
  for (const Point2& p : options.refine_points) {
    points.push_back(p);
  }
  for (Point2& p : points) {
    if (!domain.contains(p)) {
      continue;
    }
    snapPoint(p, outlines, nullptr, snap_tol_m);
  }

  Cdt cdt;
  for (const Outline& outline : outlines) {
    std::vector<Cdt::Vertex_handle> handles;
    handles.reserve(outline.points.size());
    for (const Point2& p : outline.points) {
      handles.push_back(cdt.insert(toCgal(p)));
    }
    for (std::size_t i = 0; i < handles.size(); ++i) {
      const auto& a = handles[i];
      const auto& b = handles[(i + 1) % handles.size()];
      if (a != b) {
        cdt.insert_constraint(a, b);
      }
    }
  }
  for (const Segment& piece : line_pieces) {
    cdt.insert_constraint(toCgal(piece.a), toCgal(piece.b));
  }
  for (const Point2& p : points) {
    if (domain.contains(p)) {
      cdt.insert(toCgal(p));
    }
  }

  // Mark the faces inside the domain: every component between constraints lies entirely on
  // one side of the domain outline.
  const Polygon constrained_domain(outlines[0].points);
  for (auto f = cdt.all_faces_begin(); f != cdt.all_faces_end(); ++f) {
    f->set_in_domain(false);
  }
  {
    const std::vector<FaceHandle> representatives = labelComponents(cdt, false);
    std::vector<bool> inside(representatives.size());
    for (std::size_t k = 0; k < representatives.size(); ++k) {
      inside[k] = constrained_domain.contains(centroid(representatives[k]));
    }
    for (auto f = cdt.finite_faces_begin(); f != cdt.finite_faces_end(); ++f) {
      f->set_in_domain(inside[static_cast<std::size_t>(f->info())]);
    }
  }

  // Delaunay refinement with the graded size field (sizes from the unclipped features).
  const SizeField size_field(options);
  const double sine = std::sin(options.min_angle_deg * M_PI / 180.0);
  CGAL::Delaunay_mesher_2<Cdt, GradedSizeCriteria> mesher(
      cdt, GradedSizeCriteria(sine * sine, &size_field));
  mesher.init(true);
  mesher.refine_mesh();

  // Extract the in-domain faces with deduplicated nodes; tag each component by the region that
  // contains its centroid (region outlines are constraints, so no face straddles one).
  TriangleMesh mesh;
  mesh.region_names.push_back(background_name);
  for (const MeshRegion& region : regions) {
    mesh.region_names.push_back(region.name);
  }
  std::vector<Polygon> region_outlines;
  for (std::size_t k = 1; k < outlines.size(); ++k) {
    region_outlines.emplace_back(outlines[k].points);
  }

  const std::vector<FaceHandle> representatives = labelComponents(cdt, true);
  std::vector<int> component_region(representatives.size(), 0);
  for (std::size_t k = 0; k < representatives.size(); ++k) {
    const Point2 c = centroid(representatives[k]);
    for (std::size_t i = 0; i < region_outlines.size(); ++i) {
      if (region_outlines[i].contains(c)) {
        component_region[k] = static_cast<int>(i + 1);
        break;
      }
    }
  }

  for (auto v = cdt.finite_vertices_begin(); v != cdt.finite_vertices_end(); ++v) {
    v->info() = -1;
  }
  for (auto f = cdt.finite_faces_begin(); f != cdt.finite_faces_end(); ++f) {
    if (!f->is_in_domain()) {
      continue;
    }
    std::array<int, 3> triangle{};
    for (int k = 0; k < 3; ++k) {
      const auto v = f->vertex(k);
      if (v->info() < 0) {
        v->info() = static_cast<int>(mesh.nodes.size());
        mesh.nodes.push_back(fromCgal(v->point()));
      }
      triangle[static_cast<std::size_t>(k)] = v->info();
    }
    mesh.triangles.push_back(triangle);  // CGAL faces are counter-clockwise
    mesh.triangle_region.push_back(component_region[static_cast<std::size_t>(f->info())]);
  }
  return mesh;
}

}  // namespace needle_guidance::geometry
