// Extruded planar workspaces and the 3-D loop under the MDP's policy (planar_check_3d.h).
#include "needle_guidance/steering_3d/planar_check_3d.h"
#include "needle_guidance/math.h"

#include <cmath>
#include <stdexcept>

#include "needle_guidance/steering/continuous_workspace.h"

namespace needle_guidance::steering_3d {

using namespace needle_model;  // the needle, meshes and scene the planner works on
namespace {

double cross(const Eigen::Vector2d& a, const Eigen::Vector2d& b, const Eigen::Vector2d& c) {
  return (b - a).x() * (c - a).y() - (b - a).y() * (c - a).x();
}

/// Drops vertices collinear with their neighbours (relative to the edge lengths).
std::vector<Eigen::Vector2d> withoutCollinear(std::vector<Eigen::Vector2d> poly) {
  bool changed = true;
  while (changed && poly.size() > 3) {
    changed = false;
    for (std::size_t i = 0; i < poly.size(); ++i) {
      const auto& a = poly[(i + poly.size() - 1) % poly.size()];
      const auto& b = poly[i];
      const auto& c = poly[(i + 1) % poly.size()];
      if (std::abs(cross(a, b, c)) <= 1e-12 * (b - a).norm() * (c - b).norm()) {
        poly.erase(poly.begin() + static_cast<long>(i));
        changed = true;
        break;
      }
    }
  }
  return poly;
}

/// Ear clipping of a simple counter-clockwise polygon.
std::vector<std::array<int, 3>> earClip(const std::vector<Eigen::Vector2d>& poly) {
  std::vector<int> idx(poly.size());
  for (std::size_t i = 0; i < poly.size(); ++i) {
    idx[i] = static_cast<int>(i);
  }
  std::vector<std::array<int, 3>> out;
  std::size_t guard = 0;
  while (idx.size() > 3 && guard++ < 4 * poly.size() * poly.size()) {
    for (std::size_t i = 0; i < idx.size(); ++i) {
      const int ia = idx[(i + idx.size() - 1) % idx.size()], ib = idx[i],
                ic = idx[(i + 1) % idx.size()];
      const auto &a = poly[ia], &b = poly[ib], &c = poly[ic];
      if (cross(a, b, c) <= 0.0) {
        continue;  // reflex
      }
      bool empty = true;
      for (int j : idx) {
        if (j == ia || j == ib || j == ic) {
          continue;
        }
        const auto& p = poly[j];
        if (cross(a, b, p) >= 0.0 && cross(b, c, p) >= 0.0 && cross(c, a, p) >= 0.0) {
          empty = false;
          break;
        }
      }
      if (empty) {
        out.push_back({ia, ib, ic});
        idx.erase(idx.begin() + static_cast<long>(i));
        break;
      }
    }
  }
  if (idx.size() != 3) {
    throw std::invalid_argument("prismMesh: the polygon is not simple (ear clipping failed)");
  }
  out.push_back({idx[0], idx[1], idx[2]});
  return out;
}

}  // namespace

Mesh3 prismMesh(const std::vector<Eigen::Vector2d>& polygon_ccw, double z0, double z1) {
  const std::vector<Eigen::Vector2d> poly = withoutCollinear(polygon_ccw);
  double twice_area = 0.0;
  for (std::size_t i = 0; i < poly.size(); ++i) {
    const auto& a = poly[i];
    const auto& b = poly[(i + 1) % poly.size()];
    twice_area += a.x() * b.y() - a.y() * b.x();
  }
  if (poly.size() < 3 || !(twice_area > 0.0) || !(z1 > z0)) {
    throw std::invalid_argument(
        "prismMesh: needs a counter-clockwise polygon of positive area and z1 > z0");
  }
  const int n = static_cast<int>(poly.size());
  Mesh3 m;
  for (double z : {z0, z1}) {
    for (const auto& p : poly) {
      m.vertices.emplace_back(p.x(), p.y(), z);
    }
  }
  for (int i = 0; i < n; ++i) {
    const int a0 = i, b0 = (i + 1) % n, a1 = i + n, b1 = (i + 1) % n + n;
    m.triangles.push_back({a0, b0, b1});
    m.triangles.push_back({a0, b1, a1});
  }
  for (const auto& t : earClip(poly)) {
    m.triangles.push_back({t[0] + n, t[1] + n, t[2] + n});  // top, normal +z
    m.triangles.push_back({t[0], t[2], t[1]});              // bottom, normal -z
  }
  return m;
}

CollisionWorld3 extrudedWorld(const steering::SteeringProblem& problem, double half_depth_m,
                              double tolerance_m) {
  const steering::ContinuousWorkspace planar(problem);
  const Mesh3 box =
      boxMesh(Vector3(problem.workspace_min.x(), problem.workspace_min.y(), -half_depth_m),
              Vector3(problem.workspace_max.x(), problem.workspace_max.y(), half_depth_m));
  std::vector<ObstacleMesh3> obstacles;
  for (std::size_t i = 0; i < planar.expandedObstacles().size(); ++i) {
    std::vector<Eigen::Vector2d> poly;
    for (const auto& p : planar.expandedObstacles()[i].vertices()) {
      poly.emplace_back(p.x(), p.y());
    }
    obstacles.push_back(ObstacleMesh3{problem.obstacles[i].name,
                                      prismMesh(poly, -half_depth_m, half_depth_m), 0.0});
  }
  return CollisionWorld3(box, std::move(obstacles), tolerance_m);
}

PlanarConsistency planarConsistency(const steering::SteeringProblem& problem,
                                    const steering::PolicyTable& table,
                                    const steering::TipPose& start, std::int64_t trials,
                                    std::uint64_t seed, int max_steps) {
  PlanarConsistency out;
  out.start = start;
  out.predicted_ps = table.lookup(start).probability_of_success;
  const steering::ContinuousWorkspace planar(problem);
  steering::TrialOptions planar_options;
  planar_options.max_steps = max_steps;
  out.planar_mc = steering::runMonteCarlo(planar, start, steering::tablePolicy(table), trials, seed,
                                          2, planar_options);
  // The 3-D world: 10 cm deep slab (the needle never leaves z = 0 under in-plane noise).
  constexpr double kHalfDepth_m = 0.05;
  constexpr double kTolerance_m = 1e-5;  // the planar check's chord tolerance
  const CollisionWorld3 world = extrudedWorld(problem, kHalfDepth_m, kTolerance_m);
  const steering::SteeringParams& sp = problem.params;
  NeedleParams3 needle;
  needle.kappa_max_per_m = 1.0 / sp.radius_m;
  needle.duty_cycle_length_m = 2.0 * kPi * sp.radius_m / sp.orientations;  // never spins
  NoiseParams3 noise;
  noise.sigma_insert_rad = sp.sigma_insert_rad;
  noise.sigma_spin_rad = sp.sigma_flip_rad;
  noise.in_plane_only = true;
  const double delta = 2.0 * kPi * sp.radius_m / sp.orientations;
  out.trials_3d = trials;
  for (std::int64_t i = 0; i < trials; ++i) {
    NoisyNeedle3 world_needle(needle, noise, seed + static_cast<std::uint64_t>(i));
    const double side = start.bevel == steering::Bevel::kLeft ? 1.0 : -1.0;
    TipPose3 tip =
        makeTipPose(Vector3(start.p_SceneTip.x(), start.p_SceneTip.y(), 0.0),
                    Vector3(std::cos(start.theta_rad), std::sin(start.theta_rad), 0.0),
                    side * Vector3(-std::sin(start.theta_rad), std::cos(start.theta_rad), 0.0));
    for (int step = 0; step < max_steps; ++step) {
      // The 2-D pose of the 3-D tip: bevel left when d points to the tangent's left in x-y.
      steering::TipPose pose;
      pose.p_SceneTip = geometry::Point2(tip.p_SceneTip.x(), tip.p_SceneTip.y());
      pose.theta_rad = std::atan2(tip.tangent().y(), tip.tangent().x());
      const Vector3 left(-tip.tangent().y(), tip.tangent().x(), 0.0);
      pose.bevel = tip.bevel().dot(left) > 0.0 ? steering::Bevel::kLeft : steering::Bevel::kRight;
      if (planar.inTarget(pose.p_SceneTip)) {
        ++out.successes_3d;
        break;
      }
      const steering::ControlLookup look = table.lookup(pose);
      const bool flip = look && look.control == steering::Control::kFlip;
      const StepRecord rec =
          world_needle.step(tip, Control3{flip ? kPi : 0.0, needle.kappa_max_per_m, delta});
      if (!world.checkPolyline(rec.path).free()) {
        break;
      }
      tip = rec.pose;
    }
  }
  return out;
}

}  // namespace needle_guidance::steering_3d
