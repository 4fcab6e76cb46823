// Triangle meshes of segmented regions (dissertation 2.3.2) and point location.
#pragma once

#include <array>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/geometry/polygon.h"

namespace needle_guidance::geometry {

/// A conforming 2-D triangle mesh in frame `scene`. Every triangle is counter-clockwise
/// (positive signed area) and carries the index of the region it lies in.
struct TriangleMesh {
  std::vector<Point2> nodes;                  ///< node positions [m]
  std::vector<std::array<int, 3>> triangles;  ///< node indices, counter-clockwise
  std::vector<int> triangle_region;           ///< region index per triangle
  std::vector<std::string> region_names;      ///< name per region index

  std::size_t nodeCount() const { return nodes.size(); }
  std::size_t triangleCount() const { return triangles.size(); }
  /// Signed area of triangle t [m^2] (positive for a valid mesh).
  double triangleArea(std::size_t t) const;
  /// Sum of triangle areas [m^2].
  double totalArea() const;
  /// Indices of nodes that lie on the outer boundary (edges used by one triangle only).
  std::vector<int> boundaryNodes() const;
};

/// A region to mesh: a simple polygon and its name. Regions lie inside the domain and must not
/// overlap each other; their edges are constrained edges of the mesh.
struct MeshRegion {
  std::string name;
  Polygon polygon;
};

/// Element-size control for meshing. Sizes are maximum edge lengths [m].
struct MeshingOptions {
  double max_edge_m = 0.005;       ///< size far from the refinement features [m]
  double min_edge_m = 0.001;       ///< size at the refinement points and lines [m]
  double grading_length_m = 0.01;  ///< size grows linearly from min to max over this distance [m]
  double min_angle_deg = 25.0;     ///< quality bound on the smallest angle [deg] (<= 30)
  std::vector<Point2> refine_points;  ///< e.g. targets
  std::vector<Segment> refine_lines;  ///< e.g. needle paths
};

/// Constrained Delaunay triangulation of the domain with the region polygons as constraints and
/// Delaunay quality refinement (CGAL), element size graded towards options' points and lines.
/// Triangles inside regions[i] get region index i + 1; the rest get index 0 (the background,
/// region_names[0] = background_name). Refinement lines are inserted as constrained edges so
/// that node chains lie on them. Throws std::invalid_argument naming the region for an invalid
/// input (self-intersecting, outside the domain, overlapping another region) and for
/// non-positive or inconsistent sizes.
TriangleMesh meshDomain(const Polygon& domain, const std::string& background_name,
                        const std::vector<MeshRegion>& regions, const MeshingOptions& options);

/// A triangle and the barycentric coordinates of a point inside it.
struct MeshLocation {
  int triangle = -1;
  std::array<double, 3> barycentric{0.0, 0.0, 0.0};  ///< weights of the triangle's nodes, sum 1
};

/// Locates points in a fixed mesh (uniform bucket grid over the mesh's bounds).
class PointLocator {
public:
  /// Keeps a reference to the mesh: the mesh must outlive the locator and not change.
  explicit PointLocator(const TriangleMesh& mesh);
  ~PointLocator();
  PointLocator(const PointLocator&) = delete;
  PointLocator& operator=(const PointLocator&) = delete;

  /// The triangle containing p (boundary within tol_m counts) and p's barycentric
  /// coordinates, or nullopt when p is outside the mesh.
  std::optional<MeshLocation> locate(const Point2& p, double tol_m = 1e-12) const;

private:
  struct Grid;
  const TriangleMesh& mesh_;
  std::unique_ptr<Grid> grid_;
};

/// Barycentric coordinates of p with respect to triangle (a, b, c). Throws
/// std::invalid_argument for a degenerate triangle.
std::array<double, 3> barycentric(const Point2& p, const Point2& a, const Point2& b,
                                  const Point2& c);

}  // namespace needle_guidance::geometry
