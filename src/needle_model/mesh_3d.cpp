// Mesh IO, validation, primitives and AABB-tree distance queries (mesh_3d.h), through CGAL.
#include "needle_guidance/needle_model/mesh_3d.h"
#include "needle_guidance/math.h"

#include <CGAL/AABB_face_graph_triangle_primitive.h>
#include <CGAL/AABB_traits.h>
#include <CGAL/AABB_tree.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/IO/polygon_soup_io.h>
#include <CGAL/Polygon_mesh_processing/orient_polygon_soup.h>
#include <CGAL/Polygon_mesh_processing/orientation.h>
#include <CGAL/Polygon_mesh_processing/polygon_soup_to_polygon_mesh.h>
#include <CGAL/Polygon_mesh_processing/repair_polygon_soup.h>
#include <CGAL/Polygon_mesh_processing/self_intersections.h>
#include <CGAL/Side_of_triangle_mesh.h>
#include <CGAL/Surface_mesh.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::needle_model {
namespace {

using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Point = Kernel::Point_3;
using SurfaceMesh = CGAL::Surface_mesh<Point>;
using Primitive = CGAL::AABB_face_graph_triangle_primitive<SurfaceMesh>;
using Tree = CGAL::AABB_tree<CGAL::AABB_traits<Kernel, Primitive>>;
using Inside = CGAL::Side_of_triangle_mesh<SurfaceMesh, Kernel>;
namespace PMP = CGAL::Polygon_mesh_processing;

/// A triangle whose area is below this fraction of its longest edge squared is degenerate.
constexpr double kDegenerateAreaRatio = 1e-12;

[[noreturn]] void refuse(const std::string& path, const std::string& reason) {
  throw std::invalid_argument("readMesh3: '" + path + "': " + reason);
}

SurfaceMesh toSurfaceMesh(const Mesh3& mesh) {
  std::vector<Point> points;
  points.reserve(mesh.vertices.size());
  for (const Vector3& v : mesh.vertices) {
    points.emplace_back(v.x(), v.y(), v.z());
  }
  std::vector<std::vector<std::size_t>> faces;
  for (const auto& t : mesh.triangles) {
    faces.push_back({std::size_t(t[0]), std::size_t(t[1]), std::size_t(t[2])});
  }
  SurfaceMesh out;
  PMP::polygon_soup_to_polygon_mesh(points, faces, out);
  return out;
}

/// Refuses faces that are not triangles or are degenerate (before any repair hides them).
void checkFaces(const std::string& path, const std::vector<Point>& points,
                const std::vector<std::vector<std::size_t>>& faces) {
  if (faces.empty()) {
    refuse(path, "no triangles");
  }
  for (std::size_t f = 0; f < faces.size(); ++f) {
    const auto& face = faces[f];
    if (face.size() != 3) {
      refuse(path, "face " + std::to_string(f) + " has " + std::to_string(face.size()) +
                       " vertices; only triangles are accepted");
    }
    for (std::size_t i : face) {
      if (i >= points.size()) {
        refuse(path, "face " + std::to_string(f) + " indexes vertex " + std::to_string(i) + " of " +
                         std::to_string(points.size()));
      }
    }
    const Vector3 a(points[face[0]].x(), points[face[0]].y(), points[face[0]].z());
    const Vector3 b(points[face[1]].x(), points[face[1]].y(), points[face[1]].z());
    const Vector3 c(points[face[2]].x(), points[face[2]].y(), points[face[2]].z());
    const double longest =
        std::max({(b - a).squaredNorm(), (c - b).squaredNorm(), (a - c).squaredNorm()});
    const double area2 = (b - a).cross(c - a).norm();
    if (longest == 0.0 || !(area2 > kDegenerateAreaRatio * longest)) {
      refuse(path, "triangle " + std::to_string(f) + " is degenerate (zero area)");
    }
  }
}

/// Every undirected edge must be shared by exactly two triangles (a closed 2-manifold surface).
/// The refusal names the first such edge and the faces (0-based, after the repairs) using it.
void checkClosed(const std::string& path, const std::vector<std::vector<std::size_t>>& faces) {
  std::map<std::pair<std::size_t, std::size_t>, std::vector<std::size_t>> edge_faces;
  for (std::size_t f = 0; f < faces.size(); ++f) {
    for (int i = 0; i < 3; ++i) {
      const std::size_t a = faces[f][i], b = faces[f][(i + 1) % 3];
      if (a != b) {
        edge_faces[{std::min(a, b), std::max(a, b)}].push_back(f);
      }
    }
  }
  for (const auto& [edge, users] : edge_faces) {
    if (users.size() != 2) {
      std::ostringstream os;
      os << "not closed: edge (" << edge.first << ", " << edge.second << ") is used by "
         << users.size() << " triangle(s), not 2 (face";
      for (std::size_t i = 0; i < users.size() && i < 4; ++i) {
        os << (i ? ", " : " ") << users[i];
      }
      os << ")";
      refuse(path, os.str());
    }
  }
}

/// The faces' cyclic vertex order, for counting which ones orienting reversed.
bool sameCycle(const std::vector<std::size_t>& a, const std::vector<std::size_t>& b) {
  for (int shift = 0; shift < 3; ++shift) {
    if (a[0] == b[shift] && a[1] == b[(shift + 1) % 3] && a[2] == b[(shift + 2) % 3]) {
      return true;
    }
  }
  return false;
}

/// Repairs what is safe to repair in a polygon soup, counting each repair: vertices no face
/// uses, duplicate vertices (not counted for STL, which repeats every corner by design) and
/// duplicate faces. Refuses non-triangles and degenerate triangles before and after merging.
void repairSoup(const std::string& path, std::vector<Point>& points,
                std::vector<std::vector<std::size_t>>& faces, MeshRepairs3& repairs) {
  checkFaces(path, points, faces);
  const bool stl = std::filesystem::path(path).extension() == ".stl" ||
                   std::filesystem::path(path).extension() == ".STL";
  const std::size_t merged = PMP::merge_duplicate_points_in_polygon_soup(points, faces);
  repairs.duplicate_vertices_merged = stl ? 0 : merged;
  checkFaces(path, points, faces);  // merging can make a sliver collapse
  repairs.duplicate_faces_removed = PMP::merge_duplicate_polygons_in_polygon_soup(
      points, faces, CGAL::parameters::erase_all_duplicates(false).require_same_orientation(false));
  repairs.unreferenced_vertices_removed =
      PMP::remove_isolated_points_in_polygon_soup(points, faces);
}

/// The soup as a closed, consistently and outward oriented surface mesh; counts the faces whose
/// orientation changed. Refuses a surface that is open, cannot be oriented or intersects itself,
/// naming the first offending faces.
SurfaceMesh orientedMesh(const std::string& path, std::vector<Point>& points,
                         std::vector<std::vector<std::size_t>>& faces, MeshRepairs3& repairs) {
  checkClosed(path, faces);
  const std::vector<std::vector<std::size_t>> as_read = faces;
  if (!PMP::orient_polygon_soup(points, faces)) {
    refuse(path, "not a manifold surface (it cannot be oriented consistently)");
  }
  SurfaceMesh mesh;
  PMP::polygon_soup_to_polygon_mesh(points, faces, mesh);
  if (!CGAL::is_closed(mesh) || !CGAL::is_valid_polygon_mesh(mesh)) {
    refuse(path, "not closed");
  }
  if (PMP::does_self_intersect(mesh)) {
    std::vector<std::pair<SurfaceMesh::Face_index, SurfaceMesh::Face_index>> pairs;
    PMP::self_intersections(mesh, std::back_inserter(pairs));
    std::ostringstream os;
    os << "self-intersecting: " << pairs.size() << " pair(s) of triangles intersect";
    if (!pairs.empty()) {
      os << ", the first faces " << std::size_t(pairs.front().first) << " and "
         << std::size_t(pairs.front().second);
    }
    refuse(path, os.str());
  }
  std::size_t flipped = 0;
  for (std::size_t f = 0; f < faces.size(); ++f) {
    flipped += sameCycle(faces[f], as_read[f]) ? 0 : 1;
  }
  if (!PMP::is_outward_oriented(mesh)) {
    PMP::reverse_face_orientations(mesh);
    flipped = faces.size() - flipped;
  }
  repairs.faces_reoriented = flipped;
  return mesh;
}

}  // namespace

bool MeshRepairs3::empty() const {
  return unreferenced_vertices_removed == 0 && duplicate_vertices_merged == 0 &&
         duplicate_faces_removed == 0 && faces_reoriented == 0;
}

std::string MeshRepairs3::toString() const {
  std::string text;
  const auto add = [&text](std::size_t n, const char* what) {
    if (n > 0) {
      text += (text.empty() ? "" : ", ") + std::to_string(n) + " " + what;
    }
  };
  add(unreferenced_vertices_removed, "unreferenced vertices removed");
  add(duplicate_vertices_merged, "duplicate vertices merged");
  add(duplicate_faces_removed, "duplicate faces removed");
  add(faces_reoriented, "faces reoriented outwards");
  return text.empty() ? "nothing" : text;
}

Mesh3 readMesh3(const std::string& path, double scale_to_m, MeshRepairs3* repairs_out) {
  if (!(scale_to_m > 0.0) || !std::isfinite(scale_to_m)) {
    refuse(path, "scale_to_m must be finite and > 0");
  }
  if (!std::filesystem::is_regular_file(path)) {
    refuse(path, "no such file");
  }
  std::vector<Point> points;
  std::vector<std::vector<std::size_t>> faces;
  bool read = false;
  try {
    read = CGAL::IO::read_polygon_soup(path, points, faces);
  } catch (const std::exception& e) {
    refuse(path, std::string("cannot be read: ") + e.what());
  }
  if (!read) {
    refuse(path, "cannot be read as STL, OFF, OBJ or PLY (by its extension)");
  }
  MeshRepairs3 repairs;
  repairSoup(path, points, faces, repairs);
  const SurfaceMesh mesh = orientedMesh(path, points, faces, repairs);
  if (repairs_out) {
    *repairs_out = repairs;
  }
  Mesh3 out;
  std::map<SurfaceMesh::Vertex_index, int> index;
  for (auto v : mesh.vertices()) {
    index[v] = static_cast<int>(out.vertices.size());
    const Point& p = mesh.point(v);
    out.vertices.emplace_back(p.x() * scale_to_m, p.y() * scale_to_m, p.z() * scale_to_m);
  }
  for (auto f : mesh.faces()) {
    std::array<int, 3> tri{};
    int i = 0;
    for (auto v : CGAL::vertices_around_face(mesh.halfedge(f), mesh)) {
      tri[static_cast<std::size_t>(i++)] = index[v];
    }
    out.triangles.push_back(tri);
  }
  return out;
}

void writeMesh3(const std::string& path, const Mesh3& mesh, double scale_to_m) {
  std::vector<Point> points;
  for (const Vector3& v : mesh.vertices) {
    points.emplace_back(v.x() / scale_to_m, v.y() / scale_to_m, v.z() / scale_to_m);
  }
  std::vector<std::vector<std::size_t>> faces;
  for (const auto& t : mesh.triangles) {
    faces.push_back({std::size_t(t[0]), std::size_t(t[1]), std::size_t(t[2])});
  }
  if (!CGAL::IO::write_polygon_soup(path, points, faces, CGAL::parameters::stream_precision(10))) {
    throw std::runtime_error("writeMesh3: cannot write '" + path + "'");
  }
}

Mesh3 boxMesh(const Vector3& lo, const Vector3& hi) {
  Mesh3 m;
  for (int i = 0; i < 8; ++i) {
    m.vertices.emplace_back((i & 1) ? hi.x() : lo.x(), (i & 2) ? hi.y() : lo.y(),
                            (i & 4) ? hi.z() : lo.z());
  }
  // Outward (counter-clockwise seen from outside) quads split into triangles.
  const int quads[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4},
                           {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
  for (const auto& q : quads) {
    m.triangles.push_back({q[0], q[1], q[2]});
    m.triangles.push_back({q[0], q[2], q[3]});
  }
  return m;
}

Mesh3 tubeMesh(const std::vector<Vector3>& centerline, double radius_m, int sides) {
  if (centerline.size() < 2 || sides < 3 || !(radius_m > 0.0)) {
    throw std::invalid_argument("tubeMesh: needs >= 2 centerline points, sides >= 3, radius > 0");
  }
  const std::size_t n = centerline.size();
  // Parallel-transported ring frames; each ring is perpendicular to the mean tangent there.
  std::vector<Vector3> tangents(n);
  for (std::size_t i = 0; i < n; ++i) {
    const Vector3 a = centerline[i == 0 ? 0 : i - 1];
    const Vector3 b = centerline[i + 1 == n ? n - 1 : i + 1];
    if ((b - a).norm() == 0.0) {
      throw std::invalid_argument("tubeMesh: consecutive centerline points coincide at " +
                                  std::to_string(i));
    }
    tangents[i] = (b - a).normalized();
  }
  Vector3 u = tangents[0].unitOrthogonal();
  Mesh3 m;
  for (std::size_t i = 0; i < n; ++i) {
    u = (u - u.dot(tangents[i]) * tangents[i]).normalized();
    const Vector3 w = tangents[i].cross(u);
    for (int k = 0; k < sides; ++k) {
      const double phi = 2.0 * kPi * k / sides;
      m.vertices.push_back(centerline[i] + radius_m * (std::cos(phi) * u + std::sin(phi) * w));
    }
  }
  const int s = sides;
  for (int i = 0; i + 1 < static_cast<int>(n); ++i) {
    for (int k = 0; k < s; ++k) {
      const int a = i * s + k, b = i * s + (k + 1) % s, c = (i + 1) * s + k,
                d = (i + 1) * s + (k + 1) % s;
      m.triangles.push_back({a, b, d});
      m.triangles.push_back({a, d, c});
    }
  }
  const int first = static_cast<int>(m.vertices.size());
  m.vertices.push_back(centerline.front());
  m.vertices.push_back(centerline.back());
  const int last_ring = (static_cast<int>(n) - 1) * s;
  for (int k = 0; k < s; ++k) {
    m.triangles.push_back({first, (k + 1) % s, k});
    m.triangles.push_back({first + 1, last_ring + k, last_ring + (k + 1) % s});
  }
  return m;
}

Mesh3 ellipsoidMesh(const Vector3& center, const Vector3& semi_axes_m, int rings, int sides) {
  if (rings < 2 || sides < 3 || !(semi_axes_m.minCoeff() > 0.0)) {
    throw std::invalid_argument("ellipsoidMesh: needs rings >= 2, sides >= 3, axes > 0");
  }
  Mesh3 m;
  m.vertices.push_back(center + Vector3(0, 0, -semi_axes_m.z()));
  for (int r = 1; r < rings; ++r) {
    const double theta = kPi * r / rings - kPi / 2.0;
    for (int k = 0; k < sides; ++k) {
      const double phi = 2.0 * kPi * k / sides;
      m.vertices.push_back(center + Vector3(semi_axes_m.x() * std::cos(theta) * std::cos(phi),
                                            semi_axes_m.y() * std::cos(theta) * std::sin(phi),
                                            semi_axes_m.z() * std::sin(theta)));
    }
  }
  m.vertices.push_back(center + Vector3(0, 0, semi_axes_m.z()));
  const int top = static_cast<int>(m.vertices.size()) - 1;
  for (int k = 0; k < sides; ++k) {
    m.triangles.push_back({0, 1 + (k + 1) % sides, 1 + k});
  }
  for (int r = 0; r + 2 < rings; ++r) {
    for (int k = 0; k < sides; ++k) {
      const int a = 1 + r * sides + k, b = 1 + r * sides + (k + 1) % sides;
      m.triangles.push_back({a, b, b + sides});
      m.triangles.push_back({a, b + sides, a + sides});
    }
  }
  const int last = 1 + (rings - 2) * sides;
  for (int k = 0; k < sides; ++k) {
    m.triangles.push_back({top, last + k, last + (k + 1) % sides});
  }
  return m;
}

struct MeshDistance::Impl {
  SurfaceMesh mesh;
  std::unique_ptr<Tree> tree;
  std::unique_ptr<Inside> inside;
};

MeshDistance::MeshDistance(const Mesh3& mesh) : impl_(std::make_unique<Impl>()) {
  impl_->mesh = toSurfaceMesh(mesh);
  impl_->tree =
      std::make_unique<Tree>(faces(impl_->mesh).first, faces(impl_->mesh).second, impl_->mesh);
  impl_->tree->accelerate_distance_queries();
  impl_->inside = std::make_unique<Inside>(*impl_->tree);
  // Build the lazily built search structures now, so const queries from several threads
  // (the bench's trials) never race to build them.
  impl_->tree->build();
  (void)impl_->tree->squared_distance(Point(0.0, 0.0, 0.0));
  (void)(*impl_->inside)(Point(0.0, 0.0, 0.0));
  min_ = Vector3::Constant(std::numeric_limits<double>::infinity());
  max_ = -min_;
  for (const Vector3& v : mesh.vertices) {
    min_ = min_.cwiseMin(v);
    max_ = max_.cwiseMax(v);
  }
}

MeshDistance::~MeshDistance() = default;
MeshDistance::MeshDistance(MeshDistance&&) noexcept = default;
MeshDistance& MeshDistance::operator=(MeshDistance&&) noexcept = default;

double MeshDistance::distance(const Vector3& p) const {
  return std::sqrt(impl_->tree->squared_distance(Point(p.x(), p.y(), p.z())));
}

bool MeshDistance::insideOrOn(const Vector3& p) const {
  return (*impl_->inside)(Point(p.x(), p.y(), p.z())) != CGAL::ON_UNBOUNDED_SIDE;
}

}  // namespace needle_guidance::needle_model
