// Obstacle shapes and the open workspace shared by the steering tests
// (test/core/steering_*_test.cpp).
#pragma once

#include <string>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance::steering::test_shapes {

/// The axis-aligned rectangle [x0, x1] x [y0, y1], counter-clockwise [m].
inline geometry::Polygon rect(double x0, double y0, double x1, double y1) {
  return geometry::Polygon({{x0, y0}, {x1, y0}, {x1, y1}, {x0, y1}});
}

/// A named obstacle with its clearance [m].
inline scene::Obstacle obstacle(const std::string& name, const geometry::Polygon& p,
                                double clearance_m) {
  scene::Obstacle o;
  o.name = name;
  o.polygon = p;
  o.clearance_m = clearance_m;
  return o;
}

/// 10 x 10 cm, no obstacles, r = 5 cm, N_c = 40 (delta = 7.85 mm) and a target of radius 5 mm
/// at (target_x_m, 50 mm): figure 5.1's parameters.
inline SteeringProblem openProblem(double spacing_m = 1e-3, double sigma_i_rad = 0.0,
                                   double sigma_r_rad = 0.0, double target_x_m = 0.085) {
  SteeringProblem p;
  p.workspace_min = Point2(0.0, 0.0);
  p.workspace_max = Point2(0.1, 0.1);
  p.target.name = "target";
  p.target.position = Point2(target_x_m, 0.05);
  p.target.radius_m = 0.005;
  p.params.grid_spacing_m = spacing_m;
  p.params.orientations = 40;
  p.params.radius_m = 0.05;
  p.params.sigma_insert_rad = sigma_i_rad;
  p.params.sigma_flip_rad = sigma_r_rad;
  return p;
}

/// The entry line x = 0 of openProblem's workspace, every height [m].
inline StartOptions entryLine() {
  StartOptions s;
  s.start_x_m = 0.0;
  s.min_height_m = 0.0;
  s.max_height_m = 0.1;
  return s;
}

/// The dissertation's 5.4.2 discretisation of a scene's problem (Delta 1 mm, s = 1, rounded
/// transitions), whatever model the scene file chooses: the tests of 5.4.2 run on it.
inline SteeringProblem dissertation(SteeringProblem p) {
  p.params.grid_spacing_m = 1e-3;
  p.params.orientation_subdivision = 1;
  p.params.transition_model = TransitionModel::kRounded;
  return p;
}

}  // namespace needle_guidance::steering::test_shapes
