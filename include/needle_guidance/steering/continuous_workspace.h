// The continuous steerable-needle world of a steering problem (dissertation 5.3), without the
// discretisation of 5.4.2: the needle model's PlanarWorld of the problem's workspace, obstacles,
// target and radius of curvature. Shared by the Monte Carlo truth check (monte_carlo.h) and the
// shortest-path baseline. Plain C++; no ROS.
#pragma once

#include "needle_guidance/needle_model/planar_world.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance::steering {

using needle_model::ArcOutcome;
using needle_model::ArcTrace;

/// The needle model's workspace of a problem: its rectangle, obstacles, target and
/// r = params.radius_m.
needle_model::PlanarWorkspace planarWorkspace(const SteeringProblem& problem);

/// The PlanarWorld of a steering problem, which it keeps.
class ContinuousWorkspace : public needle_model::PlanarWorld {
public:
  /// Throws std::invalid_argument as PlanarWorld does.
  explicit ContinuousWorkspace(const SteeringProblem& problem, double chord_tolerance_m = 1e-5)
      : PlanarWorld(planarWorkspace(problem), chord_tolerance_m), problem_(problem) {}

  const SteeringProblem& problem() const { return problem_; }

private:
  SteeringProblem problem_;
};

}  // namespace needle_guidance::steering
