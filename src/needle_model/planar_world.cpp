// The continuous world of the planar needle (planar_world.h).
#include "needle_guidance/needle_model/planar_world.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/format.h"

namespace needle_guidance::needle_model {
namespace {

std::string num(double v) {
  return formatNumber(v, 10);
}

double cross2(const Point2& a, const Point2& b) {
  return a.x() * b.y() - a.y() * b.x();
}

/// The smallest t in [0, 1] at which segment a + t (b - a) meets segment [c, d], or +inf.
/// Collinear overlaps count from the first shared point.
double firstContact(const Point2& a, const Point2& b, const Point2& c, const Point2& d) {
  const Point2 r = b - a;
  const Point2 s = d - c;
  const double denom = cross2(r, s);
  const Point2 ca = c - a;
  constexpr double kInf = std::numeric_limits<double>::infinity();
  if (denom == 0.0) {
    if (cross2(ca, r) != 0.0) {
      return kInf;  // parallel, apart
    }
    const double rr = r.squaredNorm();
    if (rr == 0.0) {
      return geometry::pointSegmentDistance(a, c, d) == 0.0 ? 0.0 : kInf;
    }
    // Collinear: the parameters of c and d along a-b.
    double t0 = ca.dot(r) / rr;
    double t1 = (d - a).dot(r) / rr;
    if (t0 > t1) {
      std::swap(t0, t1);
    }
    if (t1 < 0.0 || t0 > 1.0) {
      return kInf;
    }
    return std::max(0.0, t0);
  }
  const double t = cross2(ca, s) / denom;
  const double u = cross2(ca, r) / denom;
  if (t < 0.0 || t > 1.0 || u < 0.0 || u > 1.0) {
    return kInf;
  }
  return t;
}

}  // namespace

std::string toString(ArcOutcome outcome) {
  switch (outcome) {
    case ArcOutcome::kFree:
      return "free";
    case ArcOutcome::kObstacle:
      return "obstacle";
    case ArcOutcome::kLeftWorkspace:
      return "left_workspace";
  }
  return "unknown";
}

PlanarWorld::PlanarWorld(const PlanarWorkspace& workspace, double chord_tolerance_m)
    : workspace_(workspace), chord_tolerance_m_(chord_tolerance_m) {
  const std::string where = "PlanarWorld: ";
  if (!(workspace_.workspace_max.x() > workspace_.workspace_min.x()) ||
      !(workspace_.workspace_max.y() > workspace_.workspace_min.y()) ||
      !workspace_.workspace_min.allFinite() || !workspace_.workspace_max.allFinite()) {
    throw std::invalid_argument(where + "the workspace rectangle is empty or not finite");
  }
  if (!(workspace_.radius_m > 0.0) || !std::isfinite(workspace_.radius_m)) {
    throw std::invalid_argument(where + "radius_m must be finite and > 0, got " +
                                num(workspace_.radius_m));
  }
  if (!(chord_tolerance_m_ > 0.0) || !std::isfinite(chord_tolerance_m_)) {
    throw std::invalid_argument(where + "chord_tolerance_m must be finite and > 0, got " +
                                num(chord_tolerance_m_));
  }
  if (!(workspace_.target.radius_m >= 0.0) || !workspace_.target.position.allFinite()) {
    throw std::invalid_argument(where + "target '" + workspace_.target.name +
                                "' needs a finite centre and a radius >= 0");
  }
  for (const auto& o : workspace_.obstacles) {
    if (!(o.clearance_m >= 0.0) || !std::isfinite(o.clearance_m)) {
      throw std::invalid_argument(where + "obstacle '" + o.name +
                                  "' clearance_m must be finite and >= 0, got " +
                                  num(o.clearance_m));
    }
    expanded_.push_back(o.polygon.offset(o.clearance_m, chord_tolerance_m_).counterClockwise());
    box_min_.push_back(expanded_.back().minCorner());
    box_max_.push_back(expanded_.back().maxCorner());
  }
}

bool PlanarWorld::inTarget(const Point2& p) const {
  return (p - workspace_.target.position).norm() <= workspace_.target.radius_m;
}

bool PlanarWorld::inWorkspace(const Point2& p) const {
  return p.x() >= workspace_.workspace_min.x() && p.x() <= workspace_.workspace_max.x() &&
         p.y() >= workspace_.workspace_min.y() && p.y() <= workspace_.workspace_max.y();
}

int PlanarWorld::obstacleAt(const Point2& p) const {
  for (std::size_t i = 0; i < expanded_.size(); ++i) {
    if (p.x() >= box_min_[i].x() && p.x() <= box_max_[i].x() && p.y() >= box_min_[i].y() &&
        p.y() <= box_max_[i].y() && expanded_[i].contains(p)) {
      return static_cast<int>(i);
    }
  }
  return -1;
}

ArcTrace PlanarWorld::traceArc(const TipPose& from, Control control, double beta_rad,
                               double arc_length_m) const {
  ArcTrace out;
  out.end = from;
  const double r = workspace_.radius_m;
  if (!from.p_SceneTip.allFinite() || !std::isfinite(from.theta_rad) || !std::isfinite(beta_rad) ||
      !std::isfinite(arc_length_m) || arc_length_m < 0.0 || !inWorkspace(from.p_SceneTip)) {
    out.outcome = ArcOutcome::kLeftWorkspace;
    return out;
  }
  if (const int o = obstacleAt(from.p_SceneTip); o >= 0) {
    out.outcome = ArcOutcome::kObstacle;
    out.obstacle = workspace_.obstacles[static_cast<std::size_t>(o)].name;
    return out;
  }
  // Chords of angle at most max_step stay within the chord tolerance of the arc.
  const double max_step = 2.0 * std::acos(std::max(-1.0, 1.0 - chord_tolerance_m_ / r));
  const int chords = std::max(1, static_cast<int>(std::ceil(arc_length_m / r / max_step - 1e-12)));
  const double piece = arc_length_m / chords;
  const Point2 lo = workspace_.workspace_min;
  const Point2 hi = workspace_.workspace_max;
  Point2 a = from.p_SceneTip;
  for (int i = 0; i < chords; ++i) {
    const Point2 b = advanceTip(from, control, beta_rad, piece * (i + 1), r).p_SceneTip;
    double t_hit = std::numeric_limits<double>::infinity();
    ArcOutcome what = ArcOutcome::kFree;
    int which = -1;
    // Leaving the rectangle: the first t at which a coordinate crosses a bound.
    const Point2 d = b - a;
    for (int axis = 0; axis < 2; ++axis) {
      if (b[axis] < lo[axis] && d[axis] != 0.0) {
        t_hit = std::min(t_hit, (lo[axis] - a[axis]) / d[axis]);
        what = ArcOutcome::kLeftWorkspace;
      }
      if (b[axis] > hi[axis] && d[axis] != 0.0) {
        t_hit = std::min(t_hit, (hi[axis] - a[axis]) / d[axis]);
        what = ArcOutcome::kLeftWorkspace;
      }
    }
    const Point2 cmin = a.cwiseMin(b);
    const Point2 cmax = a.cwiseMax(b);
    for (std::size_t o = 0; o < expanded_.size(); ++o) {
      if (cmax.x() < box_min_[o].x() || cmin.x() > box_max_[o].x() || cmax.y() < box_min_[o].y() ||
          cmin.y() > box_max_[o].y()) {
        continue;
      }
      const geometry::Polygon& poly = expanded_[o];
      for (std::size_t e = 0; e < poly.size(); ++e) {
        const geometry::Segment edge = poly.edge(e);
        const double t = firstContact(a, b, edge.a, edge.b);
        if (t < t_hit) {
          t_hit = t;
          what = ArcOutcome::kObstacle;
          which = static_cast<int>(o);
        }
      }
    }
    if (what != ArcOutcome::kFree) {
      out.outcome = what;
      out.free_length_m = piece * (i + std::clamp(t_hit, 0.0, 1.0));
      out.end = advanceTip(from, control, beta_rad, out.free_length_m, r);
      if (which >= 0) {
        out.obstacle = workspace_.obstacles[static_cast<std::size_t>(which)].name;
      }
      return out;
    }
    a = b;
  }
  out.free_length_m = arc_length_m;
  out.end = advanceTip(from, control, beta_rad, arc_length_m, r);
  return out;
}

}  // namespace needle_guidance::needle_model
