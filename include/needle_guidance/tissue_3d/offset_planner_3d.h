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
//
// Corotational tissue (scene key `tissue.model: corotational`): a corotational insertion costs
// 10-30 times a linear one, so the plan starts in the linear model of the same mesh (built once
// by the planner), which gives the lateral position, the hole and the track's drift; then one
// corotational insertion along that needle line, by long moves, stops where the tip's tissue
// point reaches the target's x (located within its move), releases the seed and retracts: the
// depth and its verification at once, its events settled to a tenth of the tolerance. Only
// when that seed misses by more than half the tolerance is the needle moved by the miss
// (another hole when the template's holes are fixed) and inserted again.
#pragma once

#include <memory>
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
  /// The planner's own estimate; < 0 undefined (corotational tissue: one insertion predicts and
  /// verifies at once).
  double predicted_error_m = -1.0;
  double verified_error_m = -1.0;  ///< |seed - target| by the independent simulation; < 0 undefined
  Vector3 verified_seed_m = Vector3::Zero();
  double unplanned_error_m = -1.0;  ///< aiming straight at the target; < 0 undefined
  double plan_cpu_s = 0.0;  ///< planning and verification; the unplanned run is not included
  int simulations = 0;      ///< insertions the plan and its verification used
  /// Corotational tissue: insertions in the linear model that gave the plan its start (they are
  /// not in `simulations`, which counts the corotational ones); 0 for linear tissue.
  int linear_simulations = 0;
  /// CPU of the insertions in the scene's tissue model [s] (the rest of plan_cpu_s is the
  /// linear start, the column solves along new needle lines and the planner's own work).
  double simulation_cpu_s = 0.0;
  /// Corotational tissue: the needle moves of its corotational insertions (insertion, depth
  /// trials and retraction; each a located, corotationally converged move); 0 for linear tissue.
  int corotational_moves = 0;
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
  /// Corotational tissue: a verified seed within this fraction of the tolerance ends the plan;
  /// above it the needle is moved by the miss and inserted again (at most
  /// max_corotational_insertions in all). The margin covers the corotational answer's
  /// dependence on the simulation step (a few um per halving), so the seed stays within the
  /// tolerance in a simulation of another step (the closed loop's).
  double corotational_accept_fraction = 0.5;
  int max_corotational_insertions = 3;
  /// Corotational tissue: the planner's insertions move the needle by this multiple of the
  /// scene's step (needle.step), the last move ending at the stop. The events within a move
  /// (puncture, track points, stick to slip) are located on the warp where they happen, so the seed
  /// does not depend on the move length (docs/tissue_3d.md, "Longer moves, measured"); a move's
  /// cost is mostly its events, which longer moves do not remove, so beyond a few millimetres a
  /// longer move saves little.
  double corotational_step_scale = 8.0;
  /// Corotational tissue: the planner's insertions settle the warp at each located event to this
  /// fraction of the tolerance (fem::EmbeddedNeedleParams::event_warp_tolerance_m: 10 um at the
  /// 0.1 mm tolerance, four times the simulation's 2.5 um). A seed moves by about a tenth of
  /// the event tolerance, by up to two thirds on a soft block whose surface the tip crushes
  /// (docs/tissue_3d.md, "Settled to the accuracy the seed needs"): far inside the acceptance's
  /// margin. The seed's own release state is settled as tightly as in the simulation. In (0,
  /// corotational_accept_fraction].
  double corotational_event_tolerance_fraction = 0.1;
};

class OffsetPlanner3 {
public:
  /// model: the scene's tissue. In corotational tissue the linear start runs in the tissue's
  /// linear model while its reference is the linear stiffness; after a re-warp the planner
  /// assembles and factors a linear model of the same mesh once (setupCpuSeconds). Throws
  /// std::invalid_argument for options out of range.
  OffsetPlanner3(const TissueScene3d& scene, TissueModel3& model, PlannerOptions3 options = {});
  ~OffsetPlanner3();
  PlanResult3 plan(const Target3& target);
  /// Seed position after an insertion to tip x at lateral, seed release and full retraction,
  /// with moves of the scene's step (step_scale x the step). Throws std::runtime_error when the
  /// simulation refuses.
  Vector3 simulateImplant(const Eigen::Vector2d& lateral, double tip_x, double step_scale = 1.0);
  /// CPU spent on a separate linear model of corotational tissue [s] (0 while none was needed).
  double setupCpuSeconds() const { return setup_cpu_s_; }

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
  Trajectory insertAlong(TissueModel3& model, const Eigen::Vector2d& lateral, double max_x,
                         double stop_x);
  std::string physicalRefusal(const Target3& target) const;
  /// The fixed region the needle line at lateral crosses before tip x, with where ("" if none).
  std::string fixedRegionOnLine(const Eigen::Vector2d& lateral, double tip_x) const;
  /// Depth (and, on a stage, lateral position) from the tip trajectories simulated in model
  /// (`simulations` counts them, at most max_iterations; the lateral position is corrected
  /// after the last); false with r.refusal set when the robot cannot reach.
  bool predict(TissueModel3& model, const Vector3& goal, Eigen::Vector2d& lateral, double& tip_x,
               PlanResult3& r, int& simulations, int max_iterations);
  /// Full simulations from (lateral, tip_x), corrected by the measured miss (the lateral too if
  /// move_lateral); the best one.
  Attempt verify(const Vector3& goal, Eigen::Vector2d lateral, double tip_x, bool move_lateral,
                 PlanResult3& r);
  /// Template: from the verified nearest hole, the hole whose verified seed lands closest.
  Attempt bestHole(const Vector3& goal, const Attempt& nearest, PlanResult3& r);
  /// Corotational tissue on a stage with a followed track: the lateral position corrected by
  /// the drift of one insertion in the linear model (linear: the scene's tissue, seen as
  /// linear, or a linear model of its mesh), stopped where the tip's tissue point reaches the
  /// goal's x; lateral itself where the linear model does not reach the goal.
  Eigen::Vector2d linearStart(TissueModel3& linear, const Vector3& goal,
                              const Eigen::Vector2d& lateral, PlanResult3& r);
  /// Corotational tissue: the plan from the linear start (class comment); false with r.refusal
  /// set when the robot cannot reach.
  bool planCorotational(const Vector3& goal, Eigen::Vector2d lateral, Attempt& plan,
                        PlanResult3& r);
  /// Corotational tissue: insertions (insertToGoal) from lateral until the seed lands within
  /// the acceptance, the needle moved by the miss (another hole on a template) in between; the
  /// best in plan. step_scale becomes 1 when an insertion is refused at longer moves. False
  /// with r.refusal set when the robot cannot reach.
  bool insertUntilPlaced(const Vector3& goal, Eigen::Vector2d lateral, double& step_scale,
                         Attempt& plan, PlanResult3& r);
  /// Corotational tissue: one insertion at lateral by moves of step_scale x the scene's step,
  /// stopped where the tip's tissue point reaches the goal's x (located within its move), seed
  /// release and retraction (the verification); error < 0 with r.refusal set when the deepest
  /// tip position is short of it. Throws std::runtime_error when the simulation refuses.
  Attempt insertToGoal(const Vector3& goal, const Eigen::Vector2d& lateral, double step_scale,
                       PlanResult3& r);

  const TissueScene3d& scene_;
  TissueModel3& model_;
  PlannerOptions3 options_;
  RegionLocator3 regions_;
  /// Corotational tissue on a stage with a followed track: the plan starts from a linear
  /// insertion (planCorotational).
  bool linear_start_ = false;
  /// The linear model of the same mesh, built once the scene's tissue has been re-warped.
  std::unique_ptr<TissueModel3> linear_;
  double setup_in_plan_cpu_s_ = 0.0;  ///< set-up CPU spent inside the current plan()
  double setup_cpu_s_ = 0.0;
};

}  // namespace needle_guidance::tissue_3d
