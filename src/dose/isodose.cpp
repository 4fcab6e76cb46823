#include "needle_guidance/dose/isodose.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <string>

namespace needle_guidance::dose {

double midSliceZ(const Structure& s) {
  if (s.contours.empty()) {
    throw std::invalid_argument("midSliceZ: structure '" + s.name + "' has no contours");
  }
  double z_lo = s.contours.front().z_m, z_hi = z_lo;
  for (const Contour& contour : s.contours) {
    z_lo = std::min(z_lo, contour.z_m);
    z_hi = std::max(z_hi, contour.z_m);
  }
  const double middle = 0.5 * (z_lo + z_hi);
  double best = s.contours.front().z_m;
  for (const Contour& contour : s.contours) {
    if (std::abs(contour.z_m - middle) < std::abs(best - middle)) {
      best = contour.z_m;
    }
  }
  return best;
}

DoseSlice doseSlice(const HdrCase& c, const Tg43Source& source, const std::vector<double>& times_s,
                    double z_m, double x_min_m, double y_min_m, double x_max_m, double y_max_m,
                    double spacing_m) {
  constexpr double kMaxNodes = 4e6;
  if (times_s.size() != c.dwells.size()) {
    throw std::invalid_argument("doseSlice: " + std::to_string(times_s.size()) +
                                " dwell times for " + std::to_string(c.dwells.size()) +
                                " dwell positions");
  }
  if (!(spacing_m > 0.0) || !std::isfinite(spacing_m)) {
    throw std::invalid_argument("doseSlice: grid spacing must be finite and > 0");
  }
  if (!std::isfinite(z_m) || !std::isfinite(x_min_m) || !std::isfinite(y_min_m) ||
      !std::isfinite(x_max_m) || !std::isfinite(y_max_m) || !(x_max_m >= x_min_m) ||
      !(y_max_m >= y_min_m)) {
    throw std::invalid_argument("doseSlice: the box must be finite with max >= min");
  }
  // The last node at or just beyond the maximum (1e-9: a box of whole spacings keeps its edge).
  const double nx = std::ceil((x_max_m - x_min_m) / spacing_m - 1e-9) + 1.0;
  const double ny = std::ceil((y_max_m - y_min_m) / spacing_m - 1e-9) + 1.0;
  if (nx * ny > kMaxNodes) {
    throw std::invalid_argument("doseSlice: " + std::to_string(nx * ny) +
                                " grid nodes exceed the limit of 4e6");
  }
  DoseSlice slice;
  slice.x0_m = x_min_m;
  slice.y0_m = y_min_m;
  slice.z_m = z_m;
  slice.spacing_m = spacing_m;
  slice.dose_Gy.resize(static_cast<Eigen::Index>(ny), static_cast<Eigen::Index>(nx));
  for (Eigen::Index i = 0; i < slice.dose_Gy.rows(); ++i) {
    for (Eigen::Index j = 0; j < slice.dose_Gy.cols(); ++j) {
      const Point3 p(x_min_m + static_cast<double>(j) * spacing_m,
                     y_min_m + static_cast<double>(i) * spacing_m, z_m);
      slice.dose_Gy(i, j) = doseAt(c, source, times_s, p);
    }
  }
  return slice;
}

std::vector<std::vector<Point2d>> isodoseLines(const Eigen::MatrixXd& dose, double x0_m,
                                               double y0_m, double spacing_m, double level) {
  if (dose.size() == 0) {
    throw std::invalid_argument("isodoseLines: empty dose grid");
  }
  if (!dose.allFinite()) {
    throw std::invalid_argument("isodoseLines: the dose grid has non-finite values");
  }
  if (!std::isfinite(level) || !std::isfinite(x0_m) || !std::isfinite(y0_m) || !(spacing_m > 0.0) ||
      !std::isfinite(spacing_m)) {
    throw std::invalid_argument(
        "isodoseLines: level, origin must be finite and spacing finite and > 0");
  }
  const int rows = static_cast<int>(dose.rows());
  const int cols = static_cast<int>(dose.cols());
  // One node of zeros around the grid, so regions touching the border are closed there.
  cv::Mat mask = cv::Mat::zeros(rows + 2, cols + 2, CV_8UC1);
  for (int i = 0; i < rows; ++i) {
    for (int j = 0; j < cols; ++j) {
      if (dose(i, j) >= level) {
        mask.at<unsigned char>(i + 1, j + 1) = 255;
      }
    }
  }
  std::vector<std::vector<cv::Point>> traced;
  cv::findContours(mask, traced, cv::RETR_LIST, cv::CHAIN_APPROX_NONE);

  // Offset [grid steps] from an inside node to its nearest crossing along one axis: the smallest
  // interpolated crossing towards an outside 4-neighbour in the grid, signed; 0 when none.
  auto crossing = [&](int i, int j, int di, int dj) {
    double best = std::numeric_limits<double>::infinity();
    double sign = 0.0;
    for (const int s : {-1, 1}) {
      const int ni = i + s * di, nj = j + s * dj;
      if (ni < 0 || nj < 0 || ni >= rows || nj >= cols || dose(ni, nj) >= level) {
        continue;
      }
      const double inside = dose(i, j), outside = dose(ni, nj);
      const double t = (inside - level) / (inside - outside);  // in [0, 1)
      if (t < best) {
        best = t;
        sign = s;
      }
    }
    return sign == 0.0 ? 0.0 : sign * best;
  };

  std::vector<std::vector<Point2d>> lines;
  for (const auto& contour : traced) {
    if (contour.size() < 2) {
      continue;  // a lone node: no line to draw
    }
    std::vector<Point2d> line;
    line.reserve(contour.size());
    for (const cv::Point& q : contour) {
      const int i = q.y - 1, j = q.x - 1;  // padded image -> grid
      const double tx = crossing(i, j, 0, 1);
      const double ty = crossing(i, j, 1, 0);
      // The level line through the two axis crossings (tx, 0) and (0, ty), locally straight:
      // its point nearest the node; one crossing alone is used as it is.
      double ox = tx, oy = ty;
      if (tx != 0.0 && ty != 0.0) {
        const double w = 1.0 / (1.0 / (tx * tx) + 1.0 / (ty * ty));
        ox = w / tx;
        oy = w / ty;
      }
      line.emplace_back(x0_m + (j + ox) * spacing_m, y0_m + (i + oy) * spacing_m);
    }
    lines.push_back(std::move(line));
  }
  return lines;
}

}  // namespace needle_guidance::dose
