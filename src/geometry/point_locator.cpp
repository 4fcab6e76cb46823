// Point location in a fixed triangle mesh with a uniform bucket grid (dissertation 2.3.2: the
// anatomy model is queried at needle and target positions).
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "needle_guidance/geometry/triangle_mesh.h"

namespace needle_guidance::geometry {
namespace {

using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;

/// Largest number of grid cells along one axis (bounds memory for extreme aspect ratios).
constexpr long kMaxCellsPerAxis = 4096;

Kernel::Point_2 toCgal(const Point2& p) {
  return Kernel::Point_2(p.x(), p.y());
}

/// Exact orientation of (a, b, c): +1 left turn, -1 right turn, 0 collinear.
int orient(const Point2& a, const Point2& b, const Point2& c) {
  return static_cast<int>(CGAL::orientation(toCgal(a), toCgal(b), toCgal(c)));
}

}  // namespace

std::array<double, 3> barycentric(const Point2& p, const Point2& a, const Point2& b,
                                  const Point2& c) {
  const Point2 u = b - a;
  const Point2 v = c - a;
  const double twice_area = u.x() * v.y() - u.y() * v.x();
  if (!p.allFinite() || !a.allFinite() || !b.allFinite() || !c.allFinite() || twice_area == 0.0 ||
      !std::isfinite(twice_area) || orient(a, b, c) == 0) {
    throw std::invalid_argument("barycentric: degenerate triangle (twice signed area " +
                                std::to_string(twice_area) + ") or non-finite input");
  }
  const Point2 w = p - a;
  const double lambda_b = (w.x() * v.y() - w.y() * v.x()) / twice_area;
  const double lambda_c = (u.x() * w.y() - u.y() * w.x()) / twice_area;
  return {1.0 - lambda_b - lambda_c, lambda_b, lambda_c};
}

/// Triangles bucketed by the grid cells their bounding boxes overlap (compressed rows).
struct PointLocator::Grid {
  Point2 origin = Point2::Zero();  ///< lower-left corner of the grid [m]
  double cell_m = 1.0;             ///< cell side [m]
  long nx = 1;
  long ny = 1;
  std::vector<std::size_t> cell_start;  ///< nx * ny + 1 offsets into cell_triangles
  std::vector<int> cell_triangles;

  long clampX(double x) const {
    return std::clamp(static_cast<long>(std::floor((x - origin.x()) / cell_m)), 0L, nx - 1);
  }
  long clampY(double y) const {
    return std::clamp(static_cast<long>(std::floor((y - origin.y()) / cell_m)), 0L, ny - 1);
  }
};

PointLocator::PointLocator(const TriangleMesh& mesh)
    : mesh_(mesh), grid_(std::make_unique<Grid>()) {
  Grid& grid = *grid_;
  if (mesh.triangles.empty()) {
    grid.cell_start.assign(2, 0);
    return;
  }
  Point2 lo = Point2::Constant(std::numeric_limits<double>::infinity());
  Point2 hi = -lo;
  for (const auto& triangle : mesh.triangles) {
    for (int k : triangle) {
      if (k < 0 || static_cast<std::size_t>(k) >= mesh.nodes.size()) {
        throw std::invalid_argument("PointLocator: triangle node index " + std::to_string(k) +
                                    " out of range for " + std::to_string(mesh.nodes.size()) +
                                    " nodes");
      }
      lo = lo.cwiseMin(mesh.nodes[static_cast<std::size_t>(k)]);
      hi = hi.cwiseMax(mesh.nodes[static_cast<std::size_t>(k)]);
    }
  }
  // About one triangle per cell.
  const Point2 extent = (hi - lo).cwiseMax(Point2::Constant(1e-300));
  grid.origin = lo;
  grid.cell_m = std::sqrt(extent.x() * extent.y() / static_cast<double>(mesh.triangles.size()));
  grid.cell_m =
      std::max({grid.cell_m, extent.x() / kMaxCellsPerAxis, extent.y() / kMaxCellsPerAxis});
  grid.nx =
      std::clamp(static_cast<long>(std::ceil(extent.x() / grid.cell_m)), 1L, kMaxCellsPerAxis);
  grid.ny =
      std::clamp(static_cast<long>(std::ceil(extent.y() / grid.cell_m)), 1L, kMaxCellsPerAxis);

  const auto cell_range = [&](std::size_t t, long& x0, long& x1, long& y0, long& y1) {
    const auto& triangle = mesh.triangles[t];
    Point2 t_lo = mesh.nodes[static_cast<std::size_t>(triangle[0])];
    Point2 t_hi = t_lo;
    for (int k = 1; k < 3; ++k) {
      t_lo = t_lo.cwiseMin(
          mesh.nodes[static_cast<std::size_t>(triangle[static_cast<std::size_t>(k)])]);
      t_hi = t_hi.cwiseMax(
          mesh.nodes[static_cast<std::size_t>(triangle[static_cast<std::size_t>(k)])]);
    }
    x0 = grid.clampX(t_lo.x());
    x1 = grid.clampX(t_hi.x());
    y0 = grid.clampY(t_lo.y());
    y1 = grid.clampY(t_hi.y());
  };
  const auto cells = static_cast<std::size_t>(grid.nx * grid.ny);
  grid.cell_start.assign(cells + 1, 0);
  for (std::size_t t = 0; t < mesh.triangles.size(); ++t) {
    long x0, x1, y0, y1;
    cell_range(t, x0, x1, y0, y1);
    for (long y = y0; y <= y1; ++y) {
      for (long x = x0; x <= x1; ++x) {
        ++grid.cell_start[static_cast<std::size_t>(y * grid.nx + x) + 1];
      }
    }
  }
  for (std::size_t c = 0; c < cells; ++c) {
    grid.cell_start[c + 1] += grid.cell_start[c];
  }
  grid.cell_triangles.resize(grid.cell_start[cells]);
  std::vector<std::size_t> fill(grid.cell_start.begin(), grid.cell_start.end() - 1);
  for (std::size_t t = 0; t < mesh.triangles.size(); ++t) {
    long x0, x1, y0, y1;
    cell_range(t, x0, x1, y0, y1);
    for (long y = y0; y <= y1; ++y) {
      for (long x = x0; x <= x1; ++x) {
        grid.cell_triangles[fill[static_cast<std::size_t>(y * grid.nx + x)]++] =
            static_cast<int>(t);
      }
    }
  }
}

PointLocator::~PointLocator() = default;

std::optional<MeshLocation> PointLocator::locate(const Point2& p, double tol_m) const {
  const Grid& grid = *grid_;
  if (mesh_.triangles.empty() || !p.allFinite()) {
    return std::nullopt;
  }
  tol_m = std::max(tol_m, 0.0);
  const double grid_width_m = grid.cell_m * static_cast<double>(grid.nx);
  const double grid_height_m = grid.cell_m * static_cast<double>(grid.ny);
  if (p.x() < grid.origin.x() - tol_m || p.y() < grid.origin.y() - tol_m ||
      p.x() > grid.origin.x() + grid_width_m + tol_m ||
      p.y() > grid.origin.y() + grid_height_m + tol_m) {
    return std::nullopt;
  }
  const long x0 = grid.clampX(p.x() - tol_m);
  const long x1 = grid.clampX(p.x() + tol_m);
  const long y0 = grid.clampY(p.y() - tol_m);
  const long y1 = grid.clampY(p.y() + tol_m);

  // A triangle containing p exactly wins at once; otherwise the candidate whose edges p is
  // least far outside of (by distance, within tol_m) is returned.
  std::optional<MeshLocation> best;
  double best_outside_m = std::numeric_limits<double>::infinity();
  for (long y = y0; y <= y1; ++y) {
    for (long x = x0; x <= x1; ++x) {
      const auto cell = static_cast<std::size_t>(y * grid.nx + x);
      for (std::size_t k = grid.cell_start[cell]; k < grid.cell_start[cell + 1]; ++k) {
        const int t = grid.cell_triangles[k];
        const auto& triangle = mesh_.triangles[static_cast<std::size_t>(t)];
        const Point2& a = mesh_.nodes[static_cast<std::size_t>(triangle[0])];
        const Point2& b = mesh_.nodes[static_cast<std::size_t>(triangle[1])];
        const Point2& c = mesh_.nodes[static_cast<std::size_t>(triangle[2])];
        if (orient(a, b, p) >= 0 && orient(b, c, p) >= 0 && orient(c, a, p) >= 0) {
          return MeshLocation{t, barycentric(p, a, b, c)};
        }
        if (tol_m == 0.0) {
          continue;
        }
        // p is outside this triangle: its distance to the triangle is the distance to the
        // nearest edge.
        const double outside_m =
            std::min({pointSegmentDistance(p, a, b), pointSegmentDistance(p, b, c),
                      pointSegmentDistance(p, c, a)});
        if (outside_m <= tol_m && outside_m < best_outside_m) {
          best_outside_m = outside_m;
          best = MeshLocation{t, barycentric(p, a, b, c)};
        }
      }
    }
  }
  return best;
}

}  // namespace needle_guidance::geometry
