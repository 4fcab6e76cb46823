#include "needle_guidance/steering/continuous_workspace.h"

namespace needle_guidance::steering {

needle_model::PlanarWorkspace planarWorkspace(const SteeringProblem& problem) {
  needle_model::PlanarWorkspace w;
  w.workspace_min = problem.workspace_min;
  w.workspace_max = problem.workspace_max;
  w.obstacles = problem.obstacles;
  w.target = problem.target;
  w.radius_m = problem.params.radius_m;
  return w;
}

}  // namespace needle_guidance::steering
