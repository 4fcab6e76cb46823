// Closed triangle meshes of the 3-D steering scenes: reading STL / OFF / OBJ through
// CGAL's IO with validation, writing, simple primitives (box, tube along a polyline, sphere)
// for the shipped scenes and the tests, and the bounding-volume-hierarchy distance queries the
// planner's collision checks use (CGAL AABB tree). Plain C++; CGAL stays inside the .cpp.
#pragma once

#include <array>
#include <cstddef>
#include <memory>
#include <string>
#include <vector>

#include "needle_guidance/needle_model/needle_3d.h"

namespace needle_guidance::needle_model {

/// A triangle mesh in frame scene [m]; triangles index vertices.
struct Mesh3 {
  std::vector<Vector3> vertices;
  std::vector<std::array<int, 3>> triangles;
};

/// What readMesh3 repaired in a file: each is safe to repair and leaves the surface the file
/// describes.
struct MeshRepairs3 {
  std::size_t unreferenced_vertices_removed = 0;  ///< vertices no face uses
  std::size_t duplicate_vertices_merged = 0;      ///< equal points merged (not counted for STL)
  std::size_t duplicate_faces_removed = 0;        ///< faces on the same three vertices
  std::size_t faces_reoriented = 0;               ///< faces turned to a consistent outward order
  bool empty() const;
  /// "42 unreferenced vertices removed, 10 faces reoriented outwards", or "nothing".
  std::string toString() const;
};

/// Reads a mesh with CGAL's polygon-soup IO (the format from the extension: .stl, .off, .obj;
/// also .ply) and scales it by scale_to_m (a file in mm: 1e-3). Repairs what is safe with CGAL
/// Polygon Mesh Processing and reports it in `repairs` when given: vertices no face uses and
/// duplicate faces are removed, duplicate vertices merged, the faces oriented consistently and
/// outwards. Throws std::invalid_argument naming the file (and the first offending faces, 0-based
/// after the repairs) for: an unreadable file or unknown extension, no triangles, a face that is
/// not a triangle, a degenerate triangle (two equal vertices or zero area), a mesh that is not
/// closed (an edge not shared by exactly two triangles, or not a manifold), or a
/// self-intersecting mesh.
Mesh3 readMesh3(const std::string& path, double scale_to_m, MeshRepairs3* repairs = nullptr);
/// Writes a mesh (format from the extension), coordinates divided by scale_to_m. Throws
/// std::runtime_error naming the file if it cannot be written.
void writeMesh3(const std::string& path, const Mesh3& mesh, double scale_to_m);

/// An axis-aligned box [m], outward oriented.
Mesh3 boxMesh(const Vector3& min_corner, const Vector3& max_corner);
/// A closed tube of radius_m along a polyline (at least two points), with flat end caps and
/// `sides` vertices per ring (>= 3). Consecutive polyline points must differ. Throws
/// std::invalid_argument otherwise.
Mesh3 tubeMesh(const std::vector<Vector3>& centerline, double radius_m, int sides);
/// An ellipsoid with semi-axes (a, b, c) about `center` from a UV sphere with `rings` >= 2
/// latitude rings and `sides` >= 3 longitudes.
Mesh3 ellipsoidMesh(const Vector3& center, const Vector3& semi_axes_m, int rings, int sides);

/// Distance and inside queries on one closed mesh through an AABB tree (CGAL).
class MeshDistance {
public:
  /// Builds the tree. The mesh must be closed and outward oriented (readMesh3's output).
  explicit MeshDistance(const Mesh3& mesh);
  ~MeshDistance();
  MeshDistance(MeshDistance&&) noexcept;
  MeshDistance& operator=(MeshDistance&&) noexcept;

  /// Unsigned distance from p to the surface [m].
  double distance(const Vector3& p) const;
  /// True if p is inside the closed surface or on it.
  bool insideOrOn(const Vector3& p) const;
  /// Axis-aligned bounds of the mesh [m].
  const Vector3& minCorner() const { return min_; }
  const Vector3& maxCorner() const { return max_; }

private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  Vector3 min_ = Vector3::Zero();
  Vector3 max_ = Vector3::Zero();
};

}  // namespace needle_guidance::needle_model
