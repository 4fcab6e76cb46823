// Piecewise-affine mesh mappings, translations and the MRSI grid warp (3.2.2, 3.2.5, 3.3.3).
#include "needle_guidance/registration/point_mapping.h"

#include <cmath>
#include <stdexcept>
#include <string>

namespace needle_guidance::registration {
namespace {
/// Points within this distance of the mesh count as inside it [m].
constexpr double kLocateTol_m = 1e-9;
}  // namespace

MeshMapping::MeshMapping(geometry::TriangleMesh mesh, std::vector<Point2> displacement_m)
    : reference_(std::move(mesh)), displacement_(std::move(displacement_m)) {
  if (displacement_.size() != reference_.nodes.size()) {
    throw std::invalid_argument("MeshMapping: " + std::to_string(displacement_.size()) +
                                " displacements for " + std::to_string(reference_.nodes.size()) +
                                " nodes");
  }
  deformed_ = reference_;
  for (std::size_t i = 0; i < displacement_.size(); ++i) {
    if (!displacement_[i].allFinite()) {
      throw std::invalid_argument("MeshMapping: non-finite displacement at node " +
                                  std::to_string(i));
    }
    deformed_.nodes[i] += displacement_[i];
  }
  deformed_ccw_.nodes = deformed_.nodes;
  deformed_ccw_.region_names = deformed_.region_names;
  const double total_area = std::abs(reference_.totalArea());
  const double degenerate_m2 =
      1e-12 * total_area / std::max<std::size_t>(reference_.triangles.size(), 1);
  for (std::size_t t = 0; t < deformed_.triangles.size(); ++t) {
    auto tri = deformed_.triangles[t];
    const double area = deformed_.triangleArea(t);
    if (area <= 0.0)
      ++inverted_;
    if (std::abs(area) <= degenerate_m2)
      continue;
    if (area < 0.0)
      std::swap(tri[1], tri[2]);
    deformed_ccw_.triangles.push_back(tri);
    deformed_ccw_.triangle_region.push_back(deformed_.triangle_region[t]);
    ccw_to_triangle_.push_back(static_cast<int>(t));
  }
  reference_locator_ = std::make_unique<geometry::PointLocator>(reference_);
  deformed_locator_ = std::make_unique<geometry::PointLocator>(deformed_ccw_);
}

MeshMapping::~MeshMapping() = default;

std::optional<Point2> MeshMapping::forward(const Point2& probe_out_m) const {
  const auto location = reference_locator_->locate(probe_out_m, kLocateTol_m);
  if (!location)
    return std::nullopt;
  const auto& tri = reference_.triangles[static_cast<std::size_t>(location->triangle)];
  Point2 y = Point2::Zero();
  for (int k = 0; k < 3; ++k)
    y += location->barycentric[static_cast<std::size_t>(k)] *
         deformed_.nodes[static_cast<std::size_t>(tri[static_cast<std::size_t>(k)])];
  return y;
}

std::optional<Point2> MeshMapping::inverse(const Point2& probe_in_m) const {
  const auto location = deformed_locator_->locate(probe_in_m, kLocateTol_m);
  if (!location)
    return std::nullopt;
  const auto& tri = deformed_ccw_.triangles[static_cast<std::size_t>(location->triangle)];
  Point2 x = Point2::Zero();
  for (int k = 0; k < 3; ++k)
    x += location->barycentric[static_cast<std::size_t>(k)] *
         reference_.nodes[static_cast<std::size_t>(tri[static_cast<std::size_t>(k)])];
  return x;
}

WarpedGrid warpMrsiGrid(const PointMapping& mapping, const geometry::Polygon& probe_in_prostate,
                        double spacing_m) {
  if (!(spacing_m > 0.0) || !std::isfinite(spacing_m)) {
    throw std::invalid_argument("warpMrsiGrid: spacing must be positive, got " +
                                std::to_string(spacing_m));
  }
  WarpedGrid grid;
  grid.spacing_m = spacing_m;
  if (probe_in_prostate.size() < 3)
    return grid;
  const Point2 lo = probe_in_prostate.minCorner();
  const Point2 hi = probe_in_prostate.maxCorner();
  const Point2 centre = 0.5 * (lo + hi);
  grid.cols = static_cast<int>(std::ceil((hi.x() - lo.x()) / spacing_m)) + 1;
  grid.rows = static_cast<int>(std::ceil((hi.y() - lo.y()) / spacing_m)) + 1;
  grid.origin = centre - 0.5 * spacing_m * Point2(grid.cols - 1, grid.rows - 1);
  for (int r = 0; r < grid.rows; ++r) {
    for (int c = 0; c < grid.cols; ++c) {
      const Point2 p = grid.origin + spacing_m * Point2(c, r);
      grid.probe_in.push_back(p);
      grid.probe_out.push_back(mapping.inverse(p));
      grid.inside_prostate.push_back(probe_in_prostate.contains(p));
    }
  }
  return grid;
}

std::optional<std::vector<Point2>> mapPolygonForward(const PointMapping& mapping,
                                                     const std::vector<Point2>& vertices_m) {
  std::vector<Point2> out;
  out.reserve(vertices_m.size());
  for (const Point2& v : vertices_m) {
    const auto y = mapping.forward(v);
    if (!y)
      return std::nullopt;
    out.push_back(*y);
  }
  return out;
}

}  // namespace needle_guidance::registration
