// Rigid-needle offset planning in 3-D (dissertation ch. 4 in 3-D): the needle's lateral
// position (y, z) on the stage, or a template hole, and its depth, so that the seed lands on its
// target once the tissue has deformed and relaxed. Each candidate is judged by simulating the
// insertion (NeedleInsertion3); the plan is then verified by an independent full simulation
// (a fresh insertion at the scene's step, seed release and complete retraction). On a template
// the best hole is searched: the seed's lateral offset from its hole, measured at the nearest
// hole, predicts where every hole's seed lands, and the few holes predicted to land closer are
// verified. Refusals are physical, with their figures: target outside the tissue, in a fixed
// (bone) region, needle line through a fixed region, or out of the robot's reach (no hole
// within the tolerance: the nearest hole and its verified miss).
#pragma once

#include <string>
#include <vector>

#include "needle_guidance/tissue_3d/needle_insertion_3d.h"

namespace needle_guidance::tissue_3d {

struct PlanResult3 {
  std::string target;
  bool placed = false;  ///< verified within tolerance
  std::string refusal;  ///< the reason when not placed ("" if placed)
  /// Not placed for a physical reason (outside the tissue, in or behind bone, out of the
  /// robot's reach, no template hole close enough): the target is not reachable.
  bool unreachable = false;
  Eigen::Vector2d lateral_m = Eigen::Vector2d::Zero();  ///< planned (y, z)
  double tip_x_m = 0.0;                                 ///< planned depth (tip x at release)
  double predicted_error_m = -1.0;                      ///< planner's own estimate; < 0 undefined
  double verified_error_m = -1.0;  ///< |seed - target| by the independent simulation; < 0 undefined
  Vector3 verified_seed_m = Vector3::Zero();
  double unplanned_error_m = -1.0;  ///< aiming straight at the target; < 0 undefined
  double plan_cpu_s = 0.0;  ///< planning and verification; the unplanned run is not included
  int simulations = 0;      ///< insertions the plan and its verification used
  /// Template: the plan's hole (row along y, column along z); (-1, -1) on a stage.
  Eigen::Vector2i hole = Eigen::Vector2i(-1, -1);
  /// Template: the nearest hole to the target and its verified error (< 0 undefined).
  Eigen::Vector2i nearest_hole = Eigen::Vector2i(-1, -1);
  double nearest_hole_error_m = -1.0;
  int holes_verified = 0;  ///< template holes verified by a full simulation
};

struct PlannerOptions3 {
  double tolerance_m = 1e-4;  ///< a seed within this of its target is placed
  double converge_m = 5e-6;   ///< planner iterations stop below this predicted error
  int max_iterations = 8;
  bool unplanned = true;  ///< also simulate the unplanned insertion
};

class OffsetPlanner3 {
public:
  OffsetPlanner3(const TissueScene3d& scene, TissueModel3& model, PlannerOptions3 options = {});
  PlanResult3 plan(const Target3& target);
  /// Seed position after an insertion to tip x at lateral, seed release and full retraction,
  /// with moves of the scene's step (step_scale x the step). Throws std::runtime_error when the
  /// simulation refuses.
  Vector3 simulateImplant(const Eigen::Vector2d& lateral, double tip_x, double step_scale = 1.0);

private:
  /// Tip's tissue point against tip x, from one insertion to max_x (recorded after each step),
  /// stopped once the tip's tissue point has passed x = stop_x.
  struct Trajectory {
    std::vector<double> s;
    std::vector<Vector3> tip;
  };
  /// A verified candidate: lateral position, depth and the seed of its full simulation.
  struct Attempt {
    Eigen::Vector2d lateral = Eigen::Vector2d::Zero();
    double tip_x = 0.0;
    Vector3 seed = Vector3::Zero();
    double error = -1.0;  ///< |seed - goal|; < 0 never simulated
  };
  Trajectory insertAlong(const Eigen::Vector2d& lateral, double max_x, double stop_x);
  std::string physicalRefusal(const Target3& target) const;
  /// The fixed region the needle line at lateral crosses before tip x, with where ("" if none).
  std::string fixedRegionOnLine(const Eigen::Vector2d& lateral, double tip_x) const;
  /// Depth (and, on a stage, lateral position) from the simulated tip trajectory; false with
  /// r.refusal set when the robot cannot reach.
  bool predict(const Vector3& goal, Eigen::Vector2d& lateral, double& tip_x, PlanResult3& r);
  /// Full simulations from (lateral, tip_x), corrected by the measured miss (the lateral too if
  /// move_lateral); the best one.
  Attempt verify(const Vector3& goal, Eigen::Vector2d lateral, double tip_x, bool move_lateral,
                 PlanResult3& r);
  /// Template: from the verified nearest hole, the hole whose verified seed lands closest.
  Attempt bestHole(const Vector3& goal, const Attempt& nearest, PlanResult3& r);

  const TissueScene3d& scene_;
  TissueModel3& model_;
  PlannerOptions3 options_;
  RegionLocator3 regions_;
};

}  // namespace needle_guidance::tissue_3d
