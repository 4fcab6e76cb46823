// Exact polygon overlap by Green's theorem and the Dice similarity coefficient (3.3.2).
#include "needle_guidance/registration/dice.h"

#include <algorithm>
#include <cmath>

namespace needle_guidance::registration {
namespace {

using geometry::Point2;

/// Distance below which a sub-edge midpoint counts as lying on the other boundary [m].
constexpr double kOnBoundaryTol_m = 1e-10;

double cross(const Point2& a, const Point2& b) {
  return a.x() * b.y() - a.y() * b.x();
}

/// Calls edge(a, b) for every directed edge a -> b of the region's loops of 3 or more points.
template <class EdgeFn>
void forEachEdge(const Loops& region, EdgeFn edge) {
  for (const auto& loop : region) {
    const std::size_t n = loop.size();
    if (n < 3)
      continue;
    for (std::size_t i = 0; i < n; ++i)
      edge(loop[i], loop[(i + 1) % n]);
  }
}

/// Winding number of the region's loops around p (non-zero = inside).
int winding(const Loops& region, const Point2& p) {
  int w = 0;
  forEachEdge(region, [&](const Point2& a, const Point2& b) {
    if (a.y() <= p.y()) {
      if (b.y() > p.y() && cross(b - a, p - a) > 0.0)
        ++w;
    } else if (b.y() <= p.y() && cross(b - a, p - a) < 0.0) {
      --w;
    }
  });
  return w;
}

/// If p lies on an edge of the region, +1 when that edge runs along `direction`, -1 when
/// against it; 0 when p is not on the boundary (the first such edge decides).
int onBoundary(const Loops& region, const Point2& p, const Point2& direction) {
  int side = 0;
  forEachEdge(region, [&](const Point2& a, const Point2& b) {
    if (side != 0 || p.x() < std::min(a.x(), b.x()) - kOnBoundaryTol_m ||
        p.x() > std::max(a.x(), b.x()) + kOnBoundaryTol_m ||
        p.y() < std::min(a.y(), b.y()) - kOnBoundaryTol_m ||
        p.y() > std::max(a.y(), b.y()) + kOnBoundaryTol_m) {
      return;
    }
    if (geometry::pointSegmentDistance(p, a, b) <= kOnBoundaryTol_m) {
      side = (b - a).dot(direction) > 0.0 ? 1 : -1;
    }
  });
  return side;
}

/// Green's-theorem contribution 1/2 sum cross(p, q) of the parts of `a`'s boundary inside
/// `b`. Pieces on b's boundary count when same_orientation_counts and the directions agree.
double boundaryInside(const Loops& a, const Loops& b, bool same_orientation_counts) {
  double sum = 0.0;
  std::vector<double> cuts;
  for (const auto& loop : a) {
    const std::size_t n = loop.size();
    if (n < 3)
      continue;
    for (std::size_t i = 0; i < n; ++i) {
      const Point2& p = loop[i];
      const Point2 r = loop[(i + 1) % n] - p;
      const double rr = r.squaredNorm();
      if (rr == 0.0)
        continue;
      const Point2 lo = p.cwiseMin(loop[(i + 1) % n]);
      const Point2 hi = p.cwiseMax(loop[(i + 1) % n]);
      cuts.assign({0.0, 1.0});
      forEachEdge(b, [&](const Point2& q, const Point2& q2) {
        if (std::max(q.x(), q2.x()) < lo.x() || std::min(q.x(), q2.x()) > hi.x() ||
            std::max(q.y(), q2.y()) < lo.y() || std::min(q.y(), q2.y()) > hi.y()) {
          return;
        }
        const Point2 s = q2 - q;
        const double denom = cross(r, s);
        const Point2 qp = q - p;
        if (std::abs(denom) > 1e-14 * std::sqrt(rr * s.squaredNorm())) {
          const double t = cross(qp, s) / denom;
          const double u = cross(qp, r) / denom;
          if (t > 0.0 && t < 1.0 && u >= -1e-12 && u <= 1.0 + 1e-12)
            cuts.push_back(t);
        } else if (std::abs(cross(qp, r)) <= 1e-14 * rr + kOnBoundaryTol_m * std::sqrt(rr)) {
          // Collinear: the other edge's end points split this edge.
          for (const Point2& e : {q, q2}) {
            const double t = (e - p).dot(r) / rr;
            if (t > 0.0 && t < 1.0)
              cuts.push_back(t);
          }
        }
      });
      std::sort(cuts.begin(), cuts.end());
      for (std::size_t k = 0; k + 1 < cuts.size(); ++k) {
        if (cuts[k + 1] - cuts[k] <= 1e-15)
          continue;
        const Point2 x0 = p + cuts[k] * r;
        const Point2 x1 = p + cuts[k + 1] * r;
        const Point2 mid = 0.5 * (x0 + x1);
        const int on = onBoundary(b, mid, r);
        const bool inside = on != 0 ? (same_orientation_counts && on > 0) : winding(b, mid) != 0;
        if (inside)
          sum += 0.5 * cross(x0, x1);
      }
    }
  }
  return sum;
}

}  // namespace

double loopsArea(const Loops& region) {
  double area = 0.0;
  forEachEdge(region, [&area](const Point2& a, const Point2& b) { area += 0.5 * cross(a, b); });
  return area;
}

double intersectionArea(const Loops& a, const Loops& b) {
  return std::max(0.0, boundaryInside(a, b, true) + boundaryInside(b, a, false));
}

double diceSimilarity(const Loops& a, const Loops& b) {
  const double total = loopsArea(a) + loopsArea(b);
  if (!(total > 0.0))
    return 0.0;
  return std::clamp(2.0 * intersectionArea(a, b) / total, 0.0, 1.0);
}

Loops toLoops(const geometry::Polygon& polygon) {
  const geometry::Polygon ccw = polygon.size() >= 3 ? polygon.counterClockwise() : polygon;
  return Loops{ccw.vertices()};
}

}  // namespace needle_guidance::registration
