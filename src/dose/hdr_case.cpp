#include "needle_guidance/dose/hdr_case.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace needle_guidance::dose {
namespace {

/// Even-odd point-in-polygon test.
bool insidePolygon(const std::vector<Point2d>& poly, const Point2d& p) {
  bool inside = false;
  for (std::size_t i = 0, j = poly.size() - 1; i < poly.size(); j = i++) {
    const Point2d& a = poly[i];
    const Point2d& b = poly[j];
    if ((a.y() > p.y()) != (b.y() > p.y()) &&
        p.x() < (b.x() - a.x()) * (p.y() - a.y()) / (b.y() - a.y()) + a.x()) {
      inside = !inside;
    }
  }
  return inside;
}

double polygonArea(const std::vector<Point2d>& poly) {
  double twice = 0.0;
  for (std::size_t i = 0, j = poly.size() - 1; i < poly.size(); j = i++) {
    twice += poly[j].x() * poly[i].y() - poly[i].x() * poly[j].y();
  }
  return 0.5 * std::abs(twice);
}

}  // namespace

void Structure::normalise() {
  for (std::size_t c = 0; c < contours.size(); ++c) {
    const Contour& contour = contours[c];
    if (contour.xy_m.size() < 3 || !std::isfinite(contour.z_m)) {
      throw std::invalid_argument("structure '" + name + "': contour " + std::to_string(c) +
                                  " needs >= 3 vertices and a finite z");
    }
    for (const Point2d& p : contour.xy_m) {
      if (!p.allFinite()) {
        throw std::invalid_argument("structure '" + name + "': contour " + std::to_string(c) +
                                    " has a non-finite vertex");
      }
    }
  }
  std::stable_sort(contours.begin(), contours.end(),
                   [](const Contour& a, const Contour& b) { return a.z_m < b.z_m; });
  std::vector<double> gaps;
  for (std::size_t i = 1; i < contours.size(); ++i) {
    if (contours[i].z_m - contours[i - 1].z_m > 1e-9) {
      gaps.push_back(contours[i].z_m - contours[i - 1].z_m);
    }
  }
  slice_spacing_m = 0.0;
  if (!gaps.empty()) {
    std::nth_element(gaps.begin(), gaps.begin() + static_cast<long>(gaps.size() / 2), gaps.end());
    slice_spacing_m = gaps[gaps.size() / 2];
  }
}

bool Structure::contains(const Point3& p) const {
  if (contours.empty()) {
    return false;
  }
  const double half = 0.5 * (sliceSpacing() > 0.0 ? sliceSpacing() : 1e-3);
  // The nearest slice within half a slice spacing; a point half-way between two slices belongs
  // to the lower one (counting both would let their contours cancel in the even-odd rule).
  double best = 1e300, slice_z = 0.0;
  for (const Contour& c : contours) {
    const double d = std::abs(c.z_m - p.z());
    if (d < best - 1e-12 || (d < best + 1e-12 && c.z_m < slice_z)) {
      best = std::min(best, d);
      slice_z = c.z_m;
    }
  }
  if (best > half + 1e-12) {
    return false;
  }
  bool inside = false;
  for (const Contour& c : contours) {
    if (std::abs(c.z_m - slice_z) < 1e-12 && insidePolygon(c.xy_m, p.head<2>())) {
      inside = !inside;  // even-odd over contours of that slice (holes)
    }
  }
  return inside;
}

double Structure::volume_m3() const {
  const double dz = sliceSpacing();
  double volume = 0.0;
  for (const Contour& c : contours) {
    volume += polygonArea(c.xy_m) * (dz > 0.0 ? dz : 0.0);
  }
  return volume;
}

void Structure::bounds(Point3& lo, Point3& hi) const {
  lo = Point3::Constant(1e300);
  hi = Point3::Constant(-1e300);
  for (const Contour& c : contours) {
    for (const Point2d& p : c.xy_m) {
      lo = lo.cwiseMin(Point3(p.x(), p.y(), c.z_m));
      hi = hi.cwiseMax(Point3(p.x(), p.y(), c.z_m));
    }
  }
}

int HdrCase::structureIndex(const std::string& wanted) const {
  for (std::size_t i = 0; i < structures.size(); ++i) {
    if (structures[i].name == wanted) {
      return static_cast<int>(i);
    }
  }
  return -1;
}

double dwellDoseRate(const HdrCase& c, const Tg43Source& source, const DwellPosition& dwell,
                     const Point3& p, SourceModel model, double min_distance_m) {
  const Point3 q = (p - dwell.position_m).norm() < min_distance_m
                       ? Point3(dwell.position_m + min_distance_m * dwell.axis.unitOrthogonal())
                       : p;
  return c.air_kerma_strength_U * source.doseRatePerU(q, dwell.position_m, dwell.axis, model);
}

double doseAt(const HdrCase& c, const Tg43Source& source, const std::vector<double>& times_s,
              const Point3& p) {
  double dose = 0.0;
  for (std::size_t j = 0; j < c.dwells.size() && j < times_s.size(); ++j) {
    if (times_s[j] > 0.0) {
      dose += times_s[j] * dwellDoseRate(c, source, c.dwells[j], p);
    }
  }
  return dose;
}

Eigen::MatrixXd doseRateMatrix(const HdrCase& c, const Tg43Source& source, SourceModel model,
                               double min_distance_m) {
  if (!(c.air_kerma_strength_U > 0.0) || !std::isfinite(c.air_kerma_strength_U)) {
    throw std::invalid_argument("doseRateMatrix: case '" + c.name +
                                "': air-kerma strength must be > 0 U");
  }
  Eigen::MatrixXd d(static_cast<Eigen::Index>(c.points.size()),
                    static_cast<Eigen::Index>(c.dwells.size()));
  for (std::size_t j = 0; j < c.dwells.size(); ++j) {
    for (std::size_t i = 0; i < c.points.size(); ++i) {
      d(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(j)) =
          dwellDoseRate(c, source, c.dwells[j], c.points[i].position_m, model, min_distance_m);
    }
  }
  return d;
}

}  // namespace needle_guidance::dose
