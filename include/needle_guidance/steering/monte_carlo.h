// Monte Carlo truth check of the steering MDP: the continuous needle (exact arcs,
// continuous normal deflections, continuous_workspace.h) follows a policy with the tip imaged
// after every insertion distance delta (5.3); the empirical success rate with a 95 % Wilson
// interval is compared with the P_s the discretised MDP predicts. Plain C++; no ROS.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance::steering {

/// How a trial ended.
enum class TrialOutcome {
  kReachedTarget,  ///< the imaged tip (after a step) lies in the target disc
  kHitObstacle,    ///< an arc touched an expanded obstacle
  kLeftWorkspace,  ///< an arc left the workspace
  kStepLimit,      ///< max_steps insertions without reaching the target
};
/// "reached_target" | "hit_obstacle" | "left_workspace" | "step_limit".
std::string toString(TrialOutcome outcome);

/// A policy: the control to apply at the imaged tip pose (before step `step`, from 0).
using SteeringPolicy = std::function<Control(const TipPose& pose, int step)>;

/// The closed-loop policy of a solved table: lookup(pose).control (insert where the look-up
/// fails, e.g. off the grid). The table must outlive the returned function.
SteeringPolicy tablePolicy(const PolicyTable& table);
/// An open-loop policy: controls[step], then kInsert once the sequence is exhausted.
SteeringPolicy openLoopPolicy(std::vector<Control> controls);

struct TrialOptions {
  int max_steps = 200;       ///< insertions before kStepLimit, >= 1
  bool record_path = false;  ///< keep every imaged pose (start included) in Trial::path
  /// 0: continuous deflections (the truth). > 0: every beta is rounded to the nearest multiple
  /// of this step [rad] — an ablation that isolates the MDP's orientation quantisation (with
  /// alpha = 2 pi / N_c, what remains of the gap is the position rounding of 5.4.2).
  double deflection_step_rad = 0.0;
  /// runMonteCarlo runs trials first_trial .. first_trial + trials - 1 (trial i with seed
  /// (seed, i)), so a run of n trials can be continued by another from first_trial = n; >= 0.
  std::int64_t first_trial = 0;
};

/// One simulated insertion.
struct Trial {
  TrialOutcome outcome = TrialOutcome::kStepLimit;
  int steps = 0;                  ///< insertions made (the failing one included)
  int flips = 0;                  ///< direction changes made
  TipPose end;                    ///< last pose (at the contact point on failure)
  std::vector<TipPose> path;      ///< imaged poses, when TrialOptions::record_path
  std::vector<Control> controls;  ///< controls applied, when TrialOptions::record_path
  bool success() const { return outcome == TrialOutcome::kReachedTarget; }
};

/// Simulates one trial from `start`: at each step the policy picks u, beta ~ N(0, sigma_i)
/// (u = insert) or N(0, sigma_r) (u = flip) is drawn from `rng`, and the exact arc of
/// advanceTip of length delta = 2 pi r / N_c is traced. A start outside the workspace or in an
/// obstacle fails at once (steps = 0); a start in the target succeeds at once.
Trial simulateTrial(const ContinuousWorkspace& world, const TipPose& start,
                    const SteeringPolicy& policy, std::uint64_t seed,
                    const TrialOptions& options = {});

/// Binomial 95 % (or other z) Wilson score interval of successes / trials; [0, 1] for 0 trials.
struct Interval {
  double low = 0.0;
  double high = 1.0;
  bool contains(double p) const { return p >= low && p <= high; }
};
Interval wilsonInterval(std::int64_t successes, std::int64_t trials, double z = 1.959963984540054);

/// The difference of two success rates measured on the same trials (paired: trial i of both
/// arms used the same seed, i.e. common random numbers), with its 95 % interval.
struct PairedDifference {
  std::int64_t trials = 0;
  std::int64_t both = 0;         ///< a and b succeeded
  std::int64_t only_a = 0;       ///< a succeeded, b failed
  std::int64_t only_b = 0;       ///< b succeeded, a failed
  double difference = 0.0;       ///< rate(a) - rate(b)
  Interval interval{-1.0, 1.0};  ///< Newcombe's hybrid score interval for paired proportions
  bool excludesZero() const { return interval.low > 0.0 || interval.high < 0.0; }
};

/// rate(a) - rate(b) of paired outcomes (a[i], b[i]: trial i of each arm), with the interval of
/// Newcombe (1998, method 10: the two Wilson intervals combined with the phi correlation of the
/// pairs). Throws std::invalid_argument for outcome vectors of different or zero length.
PairedDifference pairedDifference(const std::vector<bool>& a, const std::vector<bool>& b,
                                  double z = 1.959963984540054);

/// Aggregate of many trials from one start.
struct MonteCarloResult {
  std::int64_t trials = 0;
  std::int64_t successes = 0;
  std::int64_t hit_obstacle = 0;
  std::int64_t left_workspace = 0;
  std::int64_t step_limit = 0;
  double mean_steps = 0.0;
  double mean_flips = 0.0;
  double seconds = 0.0;  ///< wall time [s]
  double rate() const { return trials > 0 ? double(successes) / double(trials) : 0.0; }
  Interval interval() const { return wilsonInterval(successes, trials); }
};

/// Runs `trials` independent trials from `start`; trial i (from options.first_trial on) uses seed
/// (seed, i), so the result does not depend on `threads` (>= 1). The policy must be safe to call
/// from several threads. Throws std::invalid_argument for trials < 1, threads < 1, max_steps < 1
/// or first_trial < 0.
MonteCarloResult runMonteCarlo(const ContinuousWorkspace& world, const TipPose& start,
                               const SteeringPolicy& policy, std::int64_t trials,
                               std::uint64_t seed, int threads = 2,
                               const TrialOptions& options = {});

/// Two runs from one start as one (counts added, mean steps and flips weighted by trials,
/// seconds added), e.g. a run continued with TrialOptions::first_trial.
MonteCarloResult combined(const MonteCarloResult& a, const MonteCarloResult& b);

/// Aggregate of sampling the discretised MDP itself (DiscreteChain).
struct ChainResult {
  std::int64_t trials = 0;
  std::int64_t successes = 0;
  std::int64_t failed_arcs = 0;  ///< the true arc from the grid point failed (5.4.2)
  /// The true arc was clear but its rounded end point is an obstacle cell: a failure that only
  /// the position rounding makes (e.g. end points rounded onto an expanded edge on a grid line).
  std::int64_t rounded_into_obstacle = 0;
  std::int64_t step_limit = 0;
  double rate() const { return trials > 0 ? double(successes) / double(trials) : 0.0; }
  Interval interval() const { return wilsonInterval(successes, trials); }
};

/// Samples the Markov chain the solver optimised: from the grid state nearest `start`, the
/// table's control, a discrete deflection drawn with the model's probabilities (beta ~ N(0,
/// sigma) drawn as simulateTrial draws it, rounded to the alpha grid, tails folded), the
/// stencil's successor. Its success rate estimates the table's P_s at that state with no modelling
/// error at all, so it separates solver error from discretisation error in the truth check. With
/// kInterpolated the draw is scaled to the model's sigma' (binSigma) and the corner of a split
/// transition is drawn by its share from a second stream, so the deflections stay coupled. Trial i
/// uses seed (seed, i). Throws std::invalid_argument for trials < 1 or max_steps < 1, a start
/// off the grid, or a table solved for another model (hash).
ChainResult runDiscreteChain(const SteeringModel& model, const PolicyTable& table,
                             const TipPose& start, std::int64_t trials, std::uint64_t seed,
                             int max_steps = 200);

}  // namespace needle_guidance::steering
