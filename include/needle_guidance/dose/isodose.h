// Isodose lines on an axial dose slice (dissertation figure 6.6): the dose on a regular x-y grid
// at one z, and the closed lines where it crosses a level (OpenCV contour tracing of the
// thresholded grid, vertices refined to the linearly interpolated crossing). No ROS here.
#pragma once

#include <Eigen/Core>
#include <vector>

#include "needle_guidance/dose/hdr_case.h"

namespace needle_guidance::dose {

/// Dose on a regular axial grid: dose_Gy(i, j) is the dose at
/// (x0_m + j * spacing_m, y0_m + i * spacing_m, z_m) — rows along y, columns along x.
struct DoseSlice {
  double x0_m = 0.0;
  double y0_m = 0.0;
  double z_m = 0.0;
  double spacing_m = 1e-3;
  Eigen::MatrixXd dose_Gy;  ///< [Gy]
};

/// The z [m] of the target's contour nearest the middle of its contours' z range (the
/// mid-gland slice). Throws std::invalid_argument if the structure has no contours.
double midSliceZ(const Structure& s);

/// Dose [Gy] of `times_s` (one per c.dwells, at S_K c.air_kerma_strength_U) on the grid covering
/// [x_min_m, x_max_m] x [y_min_m, y_max_m] at z_m with spacing_m (the first node at the minimum
/// corner; the last at or just beyond the maximum). Throws std::invalid_argument for a times
/// size mismatch, spacing <= 0, an empty or non-finite box, or more than 4e6 nodes.
DoseSlice doseSlice(const HdrCase& c, const Tg43Source& source, const std::vector<double>& times_s,
                    double z_m, double x_min_m, double y_min_m, double x_max_m, double y_max_m,
                    double spacing_m = 1e-3);

/// Closed isodose lines of `level` on the grid `dose` (dose(i, j) at (x0_m + j * spacing_m,
/// y0_m + i * spacing_m), rows along y): the outer boundaries and the holes of the region where
/// dose >= level, in grid coordinates converted to metres. Each line is a closed polygon (the last
/// vertex joins the first, not repeated) with >= 2 vertices; a lone grid node above the level
/// gives no line. Vertices lie on the linear interpolation of the dose between a node inside
/// and its 4-neighbours outside (sub-grid accuracy); a region touching the grid's border is
/// closed along the border nodes. Any unit works for the dose as long as `level` uses the same.
/// Throws std::invalid_argument for an empty grid, non-finite values or level, or spacing <= 0.
std::vector<std::vector<Point2d>> isodoseLines(const Eigen::MatrixXd& dose, double x0_m,
                                               double y0_m, double spacing_m, double level);

}  // namespace needle_guidance::dose
