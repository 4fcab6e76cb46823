// Obstacle shapes shared by the steering tests (test/core/steering_*_test.cpp).
#pragma once

#include <string>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/scene/scene.h"

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

}  // namespace needle_guidance::steering::test_shapes
