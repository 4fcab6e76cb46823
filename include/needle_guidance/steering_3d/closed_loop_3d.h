// One simulated 3-D steerable-needle insertion: the noisy needle of needle_3d.h is
// the world, the tip is imaged after every step (step_length_m of insertion, 5.3's delta) and,
// depending on the strategy, the planner replans from it, the plan runs open loop, or a straight
// needle is pushed. Success means the outcome: the tip ends inside the target ball and the path
// never touched an expanded obstacle or left the tissue. Plain C++; no ROS (the bench, the tests
// and a node call the same function).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "needle_guidance/needle_model/biplane_3d.h"
#include "needle_guidance/steering_3d/planner_3d.h"

namespace needle_guidance::steering_3d {

enum class Strategy3 {
  kReplanUncertainty,  ///< replan every step, choose by estimated P(success) (ours)
  kReplanFirstFound,   ///< replan every step, first feasible plan (Patil-style baseline)
  kOpenLoop,           ///< plan once from the entry (by P(success)), execute blind
  kStraight,           ///< a straight needle aimed at the target (no steering, no correction)
};
/// "replan_uncertainty" | "replan_first_found" | "open_loop" | "straight".
std::string toString(Strategy3 strategy);

struct TrialOptions3 {
  int max_steps = 200;       ///< steps before giving up, >= 1
  bool record_path = false;  ///< keep the tip path in TrialResult3::path
  /// Replanning strategies replan from the tip imaged by these two views (BiplaneObserver3,
  /// seeded from the trial's seed) instead of the true tip; after a dropped or gated pair, from
  /// the previous estimate advanced by the executed control.
  bool biplane = false;
  needle_model::BiplaneImaging3 imaging;
};

/// How one trial ended.
struct TrialResult3 {
  bool success = false;
  needle_model::Contact3 contact =
      needle_model::Contact3::kFree;  ///< what the path touched (kFree if nothing)
  std::string obstacle;               ///< for kObstacle
  PlanCode no_plan = PlanCode::kOk;   ///< the first plan's failure, if any
  std::string message;                ///< a one-line reason for a failure
  double target_error_m = 0.0;        ///< final tip to target centre [m] (inf without a start)
  int steps = 0;
  double initial_plan_s = 0.0;       ///< the first plan's wall time [s]
  std::vector<double> replan_s;      ///< each replan's wall time [s]
  std::vector<double> replan_cpu_s;  ///< each replan's CPU time (its thread's) [s]
  /// Each replan's answer: Plan3::approach of the plan taken (-1 a tree's plan), -2 no plan.
  std::vector<int> replan_approach;
  double predicted_p_success = 0.0;         ///< the first plan's estimate (Plan3::p_success)
  double predicted_p_success_lqg_mp = 0.0;  ///< the first plan's LQG-MP-style estimate
  int views_fused = 0;                      ///< biplane: tip estimates fused from both views
  int views_dropped = 0;                    ///< biplane: pairs with a view that found no tip
  int views_gated = 0;                      ///< biplane: pairs refused by the gate
  double estimate_error_m_max = 0.0;        ///< biplane: largest estimate-to-true-tip distance [m]
  std::vector<needle_model::Vector3> path;  ///< tip positions, when record_path
};

/// The tip after `control` from `previous`, without noise (the duty cycle's effective curvature):
/// the estimate when a biplane pair is dropped or gated.
needle_model::TipPose3 predictTip3(const needle_model::TipPose3& previous,
                                   const needle_model::Control3& control,
                                   const needle_model::NeedleParams3& needle);

/// Counts a biplane pair in `r` (fused, gated, else dropped) and returns the estimate: the fused
/// tip, or `predicted` when the pair was not fused; tracks its largest distance to `truth`.
needle_model::TipPose3 acceptBiplane(
    const Result<needle_model::TipPose3, needle_model::BiplaneStatus>& seen,
    const needle_model::TipPose3& predicted, const needle_model::TipPose3& truth, TrialResult3& r);

/// Planner seed of the k-th planning call in a trial seeded `seed` (splitmix64 of both).
std::uint64_t callSeed(std::uint64_t seed, std::uint64_t k);

/// One executed step of a trial (also the ROS procedure's world): moves `tip` by `control`
/// through the noisy needle, counts the step, appends the path when options.record_path and
/// checks it; false (result's contact, obstacle and message set) if it touched something.
bool executeStep3(needle_model::NoisyNeedle3& needle, const needle_model::CollisionWorld3& world,
                  const needle_model::Control3& control, needle_model::TipPose3& tip,
                  TrialResult3& result, const TrialOptions3& options);
/// Sets target_error_m and success (no contact and the tip in the target ball) from the final
/// tip; a failure gets a message if it has none.
void finishTrial3(const needle_model::Scene3d& scene, const needle_model::TipPose3& tip,
                  TrialResult3& result);

/// Runs one insertion in `scene` with noise `noise` (the world's; the planner assumes the same)
/// from the planner's entry; `seed` seeds both the world and the planner.
TrialResult3 runTrial3(const needle_model::Scene3d& scene,
                       const needle_model::CollisionWorld3& world, Strategy3 strategy,
                       const needle_model::NoiseParams3& noise, const PlannerParams3& planner,
                       std::uint64_t seed, const TrialOptions3& options = {});

}  // namespace needle_guidance::steering_3d
