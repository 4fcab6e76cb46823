// Sphere-traced collision checks against expanded obstacle meshes and the tissue boundary.
#include "needle_guidance/needle_model/collision_3d.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace needle_guidance::needle_model {
namespace {

/// Lower bound of the distance from p to a box [m] (0 inside).
double boxDistance(const Vector3& p, const Vector3& lo, const Vector3& hi) {
  const Vector3 d = (lo - p).cwiseMax(p - hi).cwiseMax(Vector3::Zero());
  return d.norm();
}

}  // namespace

std::string toString(Contact3 contact) {
  switch (contact) {
    case Contact3::kFree:
      return "free";
    case Contact3::kObstacle:
      return "obstacle";
    case Contact3::kOutsideTissue:
      return "outside_tissue";
  }
  return "unknown";
}

CollisionWorld3::CollisionWorld3(const Mesh3& tissue, std::vector<ObstacleMesh3> obstacles,
                                 double tolerance_m)
    : tissue_(tissue), obstacles_(std::move(obstacles)), tolerance_m_(tolerance_m) {
  if (!(tolerance_m > 0.0) || !std::isfinite(tolerance_m)) {
    throw std::invalid_argument("CollisionWorld3: tolerance_m = " + std::to_string(tolerance_m) +
                                " must be > 0");
  }
  for (const ObstacleMesh3& o : obstacles_) {
    if (!(o.clearance_m >= 0.0) || !std::isfinite(o.clearance_m)) {
      throw std::invalid_argument("CollisionWorld3: obstacle '" + o.name +
                                  "' has clearance_m = " + std::to_string(o.clearance_m));
    }
    obstacle_distance_.emplace_back(o.mesh);
  }
}

PointCheck CollisionWorld3::classify(const Vector3& p) const {
  PointCheck out;
  if (!p.allFinite() || !tissue_.insideOrOn(p)) {
    out.contact = Contact3::kOutsideTissue;
    out.margin_m = p.allFinite() ? -tissue_.distance(p) : -std::numeric_limits<double>::infinity();
    return out;
  }
  for (std::size_t i = 0; i < obstacles_.size(); ++i) {
    const double d = obstacle_distance_[i].distance(p);
    if (obstacle_distance_[i].insideOrOn(p) || d < obstacles_[i].clearance_m) {
      out.contact = Contact3::kObstacle;
      out.obstacle = obstacles_[i].name;
      out.margin_m = obstacle_distance_[i].insideOrOn(p) ? -d - obstacles_[i].clearance_m
                                                         : d - obstacles_[i].clearance_m;
      return out;
    }
  }
  out.margin_m = margin(p);
  return out;
}

double CollisionWorld3::margin(const Vector3& p, int* nearest) const {
  const double obstacle = obstacleMargin(p, nearest);
  const double tissue = tissue_.distance(p);
  if (tissue <= obstacle && nearest != nullptr) {
    *nearest = -1;
  }
  return std::min(tissue, obstacle);
}

double CollisionWorld3::obstacleMargin(const Vector3& p, int* nearest) const {
  double best = std::numeric_limits<double>::infinity();
  int best_index = -1;
  for (std::size_t i = 0; i < obstacles_.size(); ++i) {
    const MeshDistance& m = obstacle_distance_[i];
    const double c = obstacles_[i].clearance_m;
    if (boxDistance(p, m.minCorner(), m.maxCorner()) - c >= best) {
      continue;  // the box bounds the mesh: it cannot be nearer
    }
    const double d = m.distance(p) - c;
    if (d < best) {
      best = d;
      best_index = static_cast<int>(i);
    }
  }
  if (nearest != nullptr) {
    *nearest = best_index;
  }
  return best;
}

PathCheck CollisionWorld3::checkPath(const std::function<Vector3(double)>& point_at,
                                     double length_m, double extra_margin_m) const {
  PathCheck out;
  out.min_margin_m = std::numeric_limits<double>::infinity();
  double s = 0.0;
  while (true) {
    const Vector3 p = point_at(s);
    int nearest = -1;
    const double obstacle = obstacleMargin(p, &nearest) - extra_margin_m;
    const double tissue = tissue_.distance(p);
    out.queries += 1;
    out.min_margin_m = std::min(out.min_margin_m, obstacle);
    if (obstacle < tolerance_m_) {
      out.contact = Contact3::kObstacle;
      out.obstacle = obstacles_[static_cast<std::size_t>(nearest)].name;
      out.contact_s_m = s;
      return out;
    }
    if (tissue < tolerance_m_ && !tissue_.insideOrOn(p)) {
      out.contact = Contact3::kOutsideTissue;
      out.contact_s_m = s;
      return out;
    }
    if (s >= length_m) {
      return out;
    }
    // Nothing within the margin of this point; near the tissue boundary (the entry) advance by
    // half the tolerance and test inside again.
    const double m = std::min(obstacle, tissue);
    s = std::min(length_m, s + std::max(m - 0.5 * tolerance_m_, 0.5 * tolerance_m_));
  }
}

PathCheck CollisionWorld3::checkArc(const TipPose3& pose, double curvature_per_m, double length_m,
                                    double extra_margin_m) const {
  return checkPath([&](double s) { return advanceArc(pose, curvature_per_m, s).p_SceneTip; },
                   length_m, extra_margin_m);
}

PathCheck CollisionWorld3::checkPolyline(const std::vector<Vector3>& points) const {
  PathCheck total;
  total.min_margin_m = std::numeric_limits<double>::infinity();
  double s0 = 0.0;
  for (std::size_t i = 0; i + 1 < points.size(); ++i) {
    const Vector3 a = points[i];
    const Vector3 b = points[i + 1];
    const double len = (b - a).norm();
    if (len == 0.0) {
      continue;
    }
    PathCheck seg = checkPath([&](double s) { return a + (b - a) * (s / len); }, len);
    total.queries += seg.queries;
    total.min_margin_m = std::min(total.min_margin_m, seg.min_margin_m);
    if (!seg.free()) {
      total.contact = seg.contact;
      total.obstacle = seg.obstacle;
      total.contact_s_m = s0 + seg.contact_s_m;
      return total;
    }
    s0 += len;
  }
  return total;
}

}  // namespace needle_guidance::needle_model
