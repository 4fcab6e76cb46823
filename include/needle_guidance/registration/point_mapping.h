// Point mappings between the probe-out slice (fixed image F) and the probe-in slice (moving
// image M): T maps F to M, T^-1 maps M to F (dissertation 3.2, 3.3.2). One interface for the
// FEM registration, the baselines and the synthetic ground truth, so a benchmark can measure
// point errors the same way for every method.
#pragma once

#include <memory>
#include <optional>
#include <vector>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/geometry/triangle_mesh.h"

namespace needle_guidance::registration {

using geometry::Point2;

/// A transform between the two slices. Both directions return nullopt for a point where the
/// mapping is undefined (outside the mesh, inside the rectum lumen / probe), never NaN.
class PointMapping {
public:
  virtual ~PointMapping() = default;
  /// T: probe-out point [m] -> probe-in point [m].
  virtual std::optional<Point2> forward(const Point2& probe_out_m) const = 0;
  /// T^-1: probe-in point [m] -> probe-out point [m].
  virtual std::optional<Point2> inverse(const Point2& probe_in_m) const = 0;
};

/// Piecewise-affine map of a triangle mesh and its nodal displacements (3.2.2: linear
/// interpolation inside each element; 3.2.5). forward() locates the point in the reference
/// mesh, inverse() in the deformed mesh; inverted elements of the deformed mesh are located
/// with their orientation flipped and degenerate ones are skipped (see invertedElements()).
class MeshMapping final : public PointMapping {
public:
  /// @param[in] mesh reference mesh (probe-out) [m]
  /// @param[in] displacement_m per node [m] (size = node count); throws std::invalid_argument
  ///            on a size mismatch or a non-finite value
  MeshMapping(geometry::TriangleMesh mesh, std::vector<Point2> displacement_m);
  ~MeshMapping() override;

  std::optional<Point2> forward(const Point2& probe_out_m) const override;
  std::optional<Point2> inverse(const Point2& probe_in_m) const override;

  const geometry::TriangleMesh& referenceMesh() const { return reference_; }
  /// The mesh with every node moved by its displacement (triangles may be clockwise where
  /// elements inverted) [m].
  const geometry::TriangleMesh& deformedMesh() const { return deformed_; }
  const std::vector<Point2>& displacement() const { return displacement_; }
  /// Elements whose deformed signed area is <= 0 (T is not invertible there).
  int invertedElements() const { return inverted_; }

private:
  geometry::TriangleMesh reference_;
  geometry::TriangleMesh deformed_;
  geometry::TriangleMesh deformed_ccw_;  // deformed, degenerate triangles removed, all CCW
  std::vector<int> ccw_to_triangle_;
  std::vector<Point2> displacement_;
  int inverted_ = 0;
  std::unique_ptr<geometry::PointLocator> reference_locator_;
  std::unique_ptr<geometry::PointLocator> deformed_locator_;
};

/// A rigid translation T(x) = x + t, defined everywhere.
class TranslationMapping final : public PointMapping {
public:
  explicit TranslationMapping(const Point2& translation_m) : t_(translation_m) {}
  std::optional<Point2> forward(const Point2& p) const override { return Point2(p + t_); }
  std::optional<Point2> inverse(const Point2& p) const override { return Point2(p - t_); }
  const Point2& translation() const { return t_; }

private:
  Point2 t_;
};

/// The MRSI grid on the probe-in slice and its warp to the probe-out slice (3.3.3): grid
/// intersection points every spacing_m, row-major from `origin`, covering the probe-in
/// prostate's bounding box (centred on it).
struct WarpedGrid {
  double spacing_m = 0.007;
  int rows = 0;
  int cols = 0;
  Point2 origin = Point2::Zero();  ///< probe-in position of point (0, 0) [m]
  std::vector<Point2> probe_in;    ///< rows * cols points [m], index r * cols + c
  std::vector<std::optional<Point2>>
      probe_out;                      ///< T^-1 of each point [m]; nullopt where undefined
  std::vector<bool> inside_prostate;  ///< point inside the probe-in prostate
};

/// Lays the MRSI grid (spacing_m, default 7 mm) over the bounding box of `probe_in_prostate`
/// and maps every intersection point by T^-1 (3.3.3). Throws std::invalid_argument for a
/// non-positive spacing.
WarpedGrid warpMrsiGrid(const PointMapping& mapping, const geometry::Polygon& probe_in_prostate,
                        double spacing_m = 0.007);

/// Maps every vertex of a polygon by T; returns nullopt if a vertex is outside the mapping.
std::optional<std::vector<Point2>> mapPolygonForward(const PointMapping& mapping,
                                                     const std::vector<Point2>& vertices_m);

}  // namespace needle_guidance::registration
