// Rapid 3-D steerable-needle planning under uncertainty: an RRT over the needle's
// constant-curvature arcs (any curvature in [0, kappa_max] through duty-cycled spinning, the
// spin-rate gap excluded) with the reachability-aware metric of Patil et al. (T-RO 2014: the
// arc length to a sample the needle can reach with one arc, infinite otherwise), run from the
// entry region or from the current tip under a time budget. Among the plans found within the
// budget the planner chooses by the probability of success estimated with a short seeded Monte
// Carlo of the noisy closed loop (monteCarloSuccess: the same noise draws for every candidate),
// by default, or with an LQG-MP-style propagation of the closed loop's deviation covariance
// (van den Berg, Abbeel and Goldberg, IJRR 2011); the bench checks both against Monte Carlo of
// the real replanning loop.
//
// OMPL is not used here: its geometric planners need a symmetric interpolation between states
// and its control planners propagate random controls; the reachability steer of Patil 2014 is
// neither, so the tree, the metric and the steer are our own (about 300 lines), on the
// collision world's AABB trees. Plain C++; no ROS.
#pragma once

#include <chrono>
#include <cstdint>
#include <deque>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/needle_model/collision_3d.h"
#include "needle_guidance/needle_model/needle_3d.h"
#include "needle_guidance/needle_model/scene_3d.h"
#include "needle_guidance/status.h"

namespace needle_guidance::steering_3d {

/// Why there is no plan.
enum class PlanCode {
  kOk = 0,
  kStartOutsideTissue,  ///< the tip (or every entry sample) is outside the tissue
  kStartInObstacle,     ///< the tip lies within an expanded obstacle
  kTargetOutsideTissue,
  kTargetInObstacle,    ///< the target's centre lies within an expanded obstacle
  kNoPathWithinBudget,  ///< the tree found no feasible path within the time and node budget
};
/// "ok" | "start_outside_tissue" | ... (snake case of the enumerator).
std::string toString(PlanCode code);
using PlanStatus = Status<PlanCode, PlanCode::kOk>;

/// How the planner chooses among the plans it found.
enum class PlanChoice {
  kFirstFound,             ///< the first feasible plan (the Patil-style replanning baseline)
  kMaxSuccessProbability,  ///< the plan with the highest estimated P(success) (ours)
};

/// How kMaxSuccessProbability estimates P(success).
enum class SuccessEstimate {
  /// monteCarloSuccess: rollouts of the noisy needle under a cheap model of the replanning loop,
  /// with common random numbers across the candidates; ties go to the earlier-found plan.
  kMonteCarlo,
  kLqgMp,  ///< successProbability (LQG-MP-style covariance propagation; pessimistic)
};

struct PlannerParams3 {
  double time_budget_s = 0.03;       ///< wall-clock budget of a replan [s], > 0
  double entry_time_budget_s = 1.0;  ///< budget of the plan from the entry region [s], > 0
  int max_plans = 8;       ///< kMaxSuccessProbability: plans to choose among (one per tree), >= 1
  int max_nodes = 20000;   ///< tree size limit, >= 1
  double goal_bias = 0.2;  ///< probability of sampling the target centre, [0, 1]
  double max_edge_length_m = 0.01;  ///< longest tree edge [m], > 0
  /// Bevel rotations smaller than this are dropped (the arc is then traced in the current bevel
  /// plane): a rotation costs sigma_spin instead of sigma_insert (needle_3d.h) [rad].
  double rotation_snap_rad = 0.1;
  int entry_samples = 24;  ///< entry poses sampled as roots by planFromEntry, >= 1
  /// Plans keep this much beyond the obstacles' clearance: duty cycling bends once per cycle
  /// and drifts by its residual heading (needle_3d.h), so executed arcs stray from the ideal
  /// ones by ~0.1 mm over a plan even without noise [m], >= 0.
  double safety_margin_m = 3e-4;
  PlanChoice choice = PlanChoice::kMaxSuccessProbability;
  SuccessEstimate estimate = SuccessEstimate::kMonteCarlo;
  int rollouts = 24;        ///< kMonteCarlo: rollouts per candidate of a replan, >= 1
  int entry_rollouts = 96;  ///< kMonteCarlo: rollouts per candidate of the plan from the entry
  /// kMonteCarlo: the rollouts of a replan end by time_budget_s + estimate_budget_s after its
  /// start (the first found always gets one; candidates not reached by then drop out) [s], > 0
  double estimate_budget_s = 0.012;
  double entry_estimate_budget_s = 0.3;  ///< the same for the plan from the entry [s], > 0
};

/// A plan: controls from `start`; the last one ends at the target centre.
struct Plan3 {
  needle_model::TipPose3 start;
  std::vector<needle_model::Control3> controls;
  double length_m = 0.0;
  /// The chooser's estimate of P(success) (PlannerParams3::estimate); for kFirstFound, the
  /// LQG-MP-style one.
  double p_success = 0.0;
  double p_success_lqg_mp = 0.0;  ///< successProbability's estimate
  /// Which turn-then-straight approach the aware choice took (planner_3d.cpp's candidates; 0 is
  /// the baseline's single arc), -1 for a plan from the tree.
  int approach = -1;
  /// Positions every <= 1 mm along the plan, start and end included [m].
  std::vector<needle_model::Vector3> points() const;
};

/// A plan's controls as the queue a loop executes step by step (nextStep).
std::deque<needle_model::Control3> controlQueue(const Plan3& plan);
/// Takes the next step, at most step_length_m, off the front of `queue` (a control's bevel
/// rotation goes with its first step); pops the control when the step ends it.
needle_model::Control3 nextStep(std::deque<needle_model::Control3>& queue, double step_length_m);

/// What a planning call did.
struct PlanReport {
  int nodes = 0;
  int plans_found = 0;
  double seconds = 0.0;
  double closest_approach_m = 0.0;  ///< tree's closest node to the target centre [m]
};

/// The LQG-MP-style estimate of a plan's probability of success under the closed loop that
/// replans after every step_length_m: per lateral axis, the deviation e and heading error h
/// follow e' = e + L (h + beta) + L^2 c / 2, h' = h + beta + L c with beta ~ N(0, sigma) at each
/// step (sigma_spin on steps that rotate the bevel) and the replanned correction c the arc that
/// rejoins the plan two steps ahead, c = -2 (e + 2L h) / (2L)^2. With s_k^2 the per-axis variance
/// after step k, m_k the plan's clearance margin over step k, q_k the probability that the
/// correction exceeds the curvature the plan leaves unused (kappa_max - kappa_k; one-sided
/// normal tail of c) and r the target radius,
///   P = prod_k (1 - exp(-m_k^2 / (2 s_k^2))) (1 - q_k) * (1 - exp(-r^2 / (2 s_end^2))),
/// (the 2-D isotropic normal's tail beyond m; 1-D with in-plane noise). Margins are to the
/// expanded obstacles only: the tissue boundary is where the needle enters. Zero-sigma plans
/// score 1.
double successProbability(const Plan3& plan, const needle_model::CollisionWorld3& world,
                          const needle_model::Target3& target,
                          const needle_model::NoiseParams3& noise, double step_length_m,
                          double kappa_max_per_m);

/// Monte Carlo estimate of a plan's probability of success under the replanning loop, for
/// choosing among candidates: `rollouts` runs of the noisy needle (NoisyNeedle3 seeded
/// callSeed-style from `seed` and the rollout's index, so every candidate meets the same draws)
/// that execute the plan's first step, then at every step follow the single arc into the target
/// when one is free (what a replan finds first) and otherwise steer towards the plan two steps
/// ahead. A rollout succeeds when it ends in the target ball without touching an expanded
/// obstacle (with the planner's safety margin) or leaving the tissue. Returns the successes.
int monteCarloSuccesses(const Plan3& plan, const needle_model::Scene3d& scene,
                        const needle_model::CollisionWorld3& world,
                        const needle_model::NoiseParams3& noise, const PlannerParams3& params,
                        int rollouts, std::uint64_t seed);

/// The planner of one scene. The world must outlive it.
class Planner3 {
public:
  Planner3(const needle_model::Scene3d& scene, const needle_model::CollisionWorld3& world,
           PlannerParams3 params, needle_model::NoiseParams3 noise);

  /// Plans from the entry region (roots: entry_samples poses on the disc, tangents in the cone,
  /// bevels at random) within the budget. Seeded.
  Result<Plan3, PlanStatus> planFromEntry(std::uint64_t seed, PlanReport* report = nullptr) const;
  /// Replans from the current tip pose within the budget. Seeded.
  Result<Plan3, PlanStatus> planFromTip(const needle_model::TipPose3& tip, std::uint64_t seed,
                                        PlanReport* report = nullptr) const;

  const PlannerParams3& params() const { return params_; }
  const needle_model::NoiseParams3& noise() const { return noise_; }

private:
  Result<Plan3, PlanStatus> plan(const std::vector<needle_model::TipPose3>& roots,
                                 std::uint64_t seed, double budget_s, int rollouts,
                                 double estimate_budget_s, PlanReport* report) const;
  /// Index of the plan to keep; sets each plan's estimates. Plans whose first rollout would
  /// start after `deadline` are dropped.
  std::size_t choose(std::vector<Plan3>& plans, int rollouts,
                     std::chrono::steady_clock::time_point deadline, std::uint64_t seed) const;
  PlanStatus checkTarget() const;
  /// The aware replan when a direct approach is free: the turn-then-straight candidates
  /// (planner_3d.cpp) that keep the clearance, each scored by `rollouts` rollouts of the
  /// replanning loop that keeps it (common random numbers; whole rounds until `deadline`); the
  /// most successes wins, ties to the earlier candidate (without noise: to the smaller final
  /// error). Nothing if none is free.
  std::optional<Plan3> planApproach(const needle_model::TipPose3& tip, int rollouts,
                                    std::chrono::steady_clock::time_point deadline,
                                    std::uint64_t seed, PlanReport& rep) const;

  const needle_model::Scene3d& scene_;
  const needle_model::CollisionWorld3& world_;
  PlannerParams3 params_;
  needle_model::NoiseParams3 noise_;
};

}  // namespace needle_guidance::steering_3d
