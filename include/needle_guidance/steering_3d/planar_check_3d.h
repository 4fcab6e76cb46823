// The 3-D model's planar special case against dissertation ch. 5: a planar steering
// workspace extruded along z into meshes (its expanded obstacles as prisms, the rectangle as a
// box), the 3-D needle restricted to the 5.3 model (full curvature, spins only 180-degree
// flips, deflection only in the plane), driven by the solved MDP's policy looked up from the
// 3-D tip. Its Monte Carlo success rate should agree with the MDP's predicted P_s and with the
// planar Monte Carlo (src/steering) of the same policy within the 95 % interval. Plain C++.
#pragma once

#include <cstdint>
#include <vector>

#include "needle_guidance/needle_model/collision_3d.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance::steering_3d {

/// A closed prism: the counter-clockwise polygon (x, y) [m] between z0 < z1 [m], caps by ear
/// clipping. Collinear vertices are dropped. Throws std::invalid_argument for a polygon without
/// positive area (or clockwise) or z1 <= z0.
needle_model::Mesh3 prismMesh(const std::vector<Eigen::Vector2d>& polygon_ccw, double z0,
                              double z1);

/// The collision world of a planar problem extruded over z in [-half_depth, half_depth]: the
/// workspace box as tissue and the expanded obstacles (as ContinuousWorkspace expands them) as
/// prisms with zero clearance.
needle_model::CollisionWorld3 extrudedWorld(const steering::SteeringProblem& problem,
                                            double half_depth_m, double tolerance_m);

/// One comparison.
struct PlanarConsistency {
  steering::TipPose start;
  double predicted_ps = 0.0;             ///< the table's P_s at the start state
  steering::MonteCarloResult planar_mc;  ///< src/steering's continuous Monte Carlo
  std::int64_t trials_3d = 0;
  std::int64_t successes_3d = 0;
  steering::Interval interval3d() const {
    return steering::wilsonInterval(successes_3d, trials_3d);
  }
  double rate3d() const { return trials_3d > 0 ? double(successes_3d) / trials_3d : 0.0; }
  /// The 3-D interval holds both the predicted P_s and the planar Monte Carlo rate.
  bool withinCi() const {
    return interval3d().contains(predicted_ps) && interval3d().contains(planar_mc.rate());
  }
};

/// Runs `trials` 3-D trials (seeds seed + i) and `trials` planar ones from `start` under the
/// solved `table` of `problem`; a 3-D trial succeeds when the tip, imaged after each insertion
/// of delta = 2 pi r / N_c, lies in the target disc (5.3), and fails on touching an expanded
/// obstacle or leaving the workspace, or after max_steps.
PlanarConsistency planarConsistency(const steering::SteeringProblem& problem,
                                    const steering::PolicyTable& table,
                                    const steering::TipPose& start, std::int64_t trials,
                                    std::uint64_t seed, int max_steps = 200);

}  // namespace needle_guidance::steering_3d
