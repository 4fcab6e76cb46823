// Piecewise-affine warp of the reference image by the FEM displacement (dissertation 2.3.7):
// the reference node coordinates of mesh G are the texture coordinates, the deformed node
// coordinates of G' place the triangles. Inside a triangle the map is affine because the
// linear-element interpolation is (2.2.2).
#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <stdexcept>
#include <vector>

#include "needle_guidance/tissue/image_warp.h"

namespace needle_guidance::tissue {
namespace {

// Pixel centres with all barycentric coordinates >= -kInsideTol are drawn, so that rounding
// cannot open gaps along edges shared by two triangles (both draw such pixels, alike).
constexpr double kInsideTol = 1e-9;
// Deformed triangles with |2 x area| below this are degenerate and not drawn [px^2].
constexpr double kMinDoubleArea_px2 = 1e-12;
constexpr int kMaskShiftBits = 8;  // sub-pixel precision of the cv::fillConvexPoly mask

struct PixelTriangle {
  cv::Point2d dst[3];  // deformed, where it is drawn [px]
  cv::Point2d src[3];  // reference, where its texture comes from [px]
};

void validateInputs(const cv::Mat& reference, const ImageGeometry& g,
                    const geometry::TriangleMesh& mesh, const Eigen::VectorXd& u) {
  g.validate("warpImage");
  if (reference.type() != CV_8UC1 || reference.size() != g.size()) {
    std::ostringstream msg;
    msg << "warpImage: reference image must be CV_8UC1 of " << g.cols << " x " << g.rows
        << " px, got type " << reference.type() << " of " << reference.cols << " x "
        << reference.rows << " px";
    throw std::invalid_argument(msg.str());
  }
  const Eigen::Index dofs = 2 * static_cast<Eigen::Index>(mesh.nodeCount());
  if (u.size() != dofs) {
    throw std::invalid_argument("warpImage: u has " + std::to_string(u.size()) +
                                " entries, expected " + std::to_string(dofs) + " (2 x " +
                                std::to_string(mesh.nodeCount()) + " nodes)");
  }
  for (Eigen::Index i = 0; i < u.size(); ++i) {
    if (!std::isfinite(u[i])) {
      std::ostringstream msg;
      msg << "warpImage: u[" << i << "] (node " << i / 2 << ", " << (i % 2 == 0 ? "x" : "y")
          << ") = " << u[i] << " is not finite";
      throw std::invalid_argument(msg.str());
    }
  }
  const int nodes = static_cast<int>(mesh.nodeCount());
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    for (int n : mesh.triangles[t]) {
      if (n < 0 || n >= nodes) {
        throw std::invalid_argument("warpImage: triangle " + std::to_string(t) +
                                    " has node index " + std::to_string(n) + " outside [0, " +
                                    std::to_string(nodes) + ")");
      }
    }
  }
}

std::vector<PixelTriangle> pixelTriangles(const ImageGeometry& g,
                                          const geometry::TriangleMesh& mesh,
                                          const Eigen::VectorXd& u) {
  std::vector<cv::Point2d> ref_px(mesh.nodeCount()), def_px(mesh.nodeCount());
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    ref_px[i] = g.toPixel(mesh.nodes[i]);
    def_px[i] = g.toPixel(mesh.nodes[i] + Point2(u[2 * i], u[2 * i + 1]));
  }
  std::vector<PixelTriangle> triangles(mesh.triangleCount());
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    for (int k = 0; k < 3; ++k) {
      triangles[t].dst[k] = def_px[mesh.triangles[t][k]];
      triangles[t].src[k] = ref_px[mesh.triangles[t][k]];
    }
  }
  return triangles;
}

double doubleArea(const cv::Point2d p[3]) {
  return (p[1] - p[0]).cross(p[2] - p[0]);
}

// Bilinear sample at continuous pixel coordinates, borders replicated.
inline double sampleBilinear(const cv::Mat& image, double x, double y) {
  const int max_col = image.cols - 1, max_row = image.rows - 1;
  x = std::clamp(x, 0.0, static_cast<double>(max_col));
  y = std::clamp(y, 0.0, static_cast<double>(max_row));
  const int x0 = std::min(static_cast<int>(x), max_col),
            y0 = std::min(static_cast<int>(y), max_row);
  const int x1 = std::min(x0 + 1, max_col), y1 = std::min(y0 + 1, max_row);
  const double fx = x - x0, fy = y - y0;
  const uchar* row0 = image.ptr<uchar>(y0);
  const uchar* row1 = image.ptr<uchar>(y1);
  const double top = row0[x0] + fx * (row0[x1] - row0[x0]);
  const double bottom = row1[x0] + fx * (row1[x1] - row1[x0]);
  return top + fy * (bottom - top);
}

void drawBarycentricScan(const cv::Mat& reference, const std::vector<PixelTriangle>& triangles,
                         cv::Mat& out) {
  const int max_col = out.cols - 1, max_row = out.rows - 1;
  for (const PixelTriangle& tri : triangles) {
    const cv::Point2d& a = tri.dst[0];
    const cv::Point2d e1 = tri.dst[1] - a, e2 = tri.dst[2] - a;
    const double area2 = e1.cross(e2);
    if (!(std::abs(area2) > kMinDoubleArea_px2)) {
      continue;
    }
    const double x_lo = std::min({tri.dst[0].x, tri.dst[1].x, tri.dst[2].x});
    const double x_hi = std::max({tri.dst[0].x, tri.dst[1].x, tri.dst[2].x});
    const double y_lo = std::min({tri.dst[0].y, tri.dst[1].y, tri.dst[2].y});
    const double y_hi = std::max({tri.dst[0].y, tri.dst[1].y, tri.dst[2].y});
    // Pixels are clipped to the image; a triangle entirely outside is skipped.
    const int c0 = static_cast<int>(std::max(0.0, std::ceil(x_lo - kInsideTol)));
    const int c1 =
        static_cast<int>(std::min(static_cast<double>(max_col), std::floor(x_hi + kInsideTol)));
    const int r0 = static_cast<int>(std::max(0.0, std::ceil(y_lo - kInsideTol)));
    const int r1 =
        static_cast<int>(std::min(static_cast<double>(max_row), std::floor(y_hi + kInsideTol)));
    if (c0 > c1 || r0 > r1) {
      continue;
    }
    // Barycentric l1, l2 of p = a + l1 e1 + l2 e2 are affine in (col, row); so is the source
    // position A + l1 (B - A) + l2 (C - A).
    const double inv = 1.0 / area2;
    const cv::Point2d& src_a = tri.src[0];
    const cv::Point2d f1 = tri.src[1] - src_a, f2 = tri.src[2] - src_a;
    for (int r = r0; r <= r1; ++r) {
      uchar* out_row = out.ptr<uchar>(r);
      const double dy = r - a.y;
      for (int c = c0; c <= c1; ++c) {
        const double dx = c - a.x;
        const double l1 = (dx * e2.y - dy * e2.x) * inv;
        const double l2 = (e1.x * dy - e1.y * dx) * inv;
        if (l1 < -kInsideTol || l2 < -kInsideTol || 1.0 - l1 - l2 < -kInsideTol) {
          continue;
        }
        const double sx = src_a.x + l1 * f1.x + l2 * f2.x;
        const double sy = src_a.y + l1 * f1.y + l2 * f2.y;
        out_row[c] = cv::saturate_cast<uchar>(sampleBilinear(reference, sx, sy));
      }
    }
  }
}

void drawOpenCvAffine(const cv::Mat& reference, const std::vector<PixelTriangle>& triangles,
                      cv::Mat& out) {
  const cv::Rect image_rect(0, 0, out.cols, out.rows);
  cv::Mat patch, mask;
  for (const PixelTriangle& tri : triangles) {
    if (!(std::abs(doubleArea(tri.dst)) > kMinDoubleArea_px2)) {
      continue;
    }
    const double x_lo = std::min({tri.dst[0].x, tri.dst[1].x, tri.dst[2].x});
    const double x_hi = std::max({tri.dst[0].x, tri.dst[1].x, tri.dst[2].x});
    const double y_lo = std::min({tri.dst[0].y, tri.dst[1].y, tri.dst[2].y});
    const double y_hi = std::max({tri.dst[0].y, tri.dst[1].y, tri.dst[2].y});
    // Clamped before the casts: a wild displacement must not overflow int.
    auto clampCol = [&](double x) {
      return static_cast<int>(std::clamp(x, -1.0, double(out.cols)));
    };
    auto clampRow = [&](double y) {
      return static_cast<int>(std::clamp(y, -1.0, double(out.rows)));
    };
    const int c0 = clampCol(std::floor(x_lo)), r0 = clampRow(std::floor(y_lo));
    const cv::Rect box =
        cv::Rect(c0, r0, clampCol(std::ceil(x_hi)) - c0 + 1, clampRow(std::ceil(y_hi)) - r0 + 1) &
        image_rect;
    if (box.empty()) {
      continue;
    }
    // Map from the patch's pixel coordinates to the reference (hence WARP_INVERSE_MAP).
    cv::Point2f dst_local[3], src[3];
    std::vector<cv::Point> mask_polygon(3);
    constexpr double kScale = 1 << kMaskShiftBits;
    for (int k = 0; k < 3; ++k) {
      const cv::Point2d local = tri.dst[k] - cv::Point2d(box.x, box.y);
      dst_local[k] = cv::Point2f(static_cast<float>(local.x), static_cast<float>(local.y));
      src[k] = cv::Point2f(static_cast<float>(tri.src[k].x), static_cast<float>(tri.src[k].y));
      mask_polygon[k] = cv::Point(static_cast<int>(std::lround(local.x * kScale)),
                                  static_cast<int>(std::lround(local.y * kScale)));
    }
    const cv::Mat patch_to_src = cv::getAffineTransform(dst_local, src);
    cv::warpAffine(reference, patch, patch_to_src, box.size(),
                   cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
    mask.create(box.size(), CV_8U);
    mask.setTo(0);
    cv::fillConvexPoly(mask, mask_polygon, cv::Scalar(255), cv::LINE_8, kMaskShiftBits);
    cv::Mat out_box = out(box);
    patch.copyTo(out_box, mask);
  }
}

}  // namespace

cv::Mat warpImage(const cv::Mat& reference, const ImageGeometry& g,
                  const geometry::TriangleMesh& reference_mesh, const Eigen::VectorXd& u,
                  WarpMethod method) {
  validateInputs(reference, g, reference_mesh, u);
  const std::vector<PixelTriangle> triangles = pixelTriangles(g, reference_mesh, u);
  cv::Mat out(g.rows, g.cols, CV_8UC1, cv::Scalar(0));
  switch (method) {
    case WarpMethod::kBarycentricScan:
      drawBarycentricScan(reference, triangles, out);
      break;
    case WarpMethod::kOpenCvAffine:
      drawOpenCvAffine(reference, triangles, out);
      break;
  }
  return out;
}

}  // namespace needle_guidance::tissue
