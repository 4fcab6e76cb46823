// A steering policy that learns the needle's deflection noise from the tip poses it sees:
// NoiseEstimator accumulates the deflection of every observed step; when the
// estimate's interval (at a level that bounds the false re-solves of a whole run, see
// AdaptationOptions) no longer contains the sigma the current table assumed, the MDP is solved
// again for the estimate on a background thread while the old table keeps answering; the new
// table is swapped in at the next poll(). Tables are cached by model hash. Not in the
// dissertation (5.3 takes sigma_i, sigma_r as known). Plain C++; no ROS.
#pragma once

#include <cstdint>
#include <future>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "needle_guidance/steering/model_selection.h"
#include "needle_guidance/steering/noise_estimator.h"

namespace needle_guidance::steering {

struct AdaptationOptions {
  bool adapt = true;  ///< false: the starting table is never replaced (the fixed-sigma policy)
  /// Deflections of a control needed before its interval may trigger a re-solve (>= 2).
  int min_samples = 10;
  /// The re-solve test's bound on the probability that a run ever re-solves while the sigmas in
  /// use are the true ones, over both controls and every check of the run, in (0, 1). The
  /// interval is checked after every deflection of a control, at sample count n >= min_samples
  /// with the level false_resolve_rate / 2 * min_samples / (n (n + 1)) (the /2 for the two
  /// controls; the levels of all n sum to false_resolve_rate / 2: a union bound over time).
  double false_resolve_rate = 0.05;
  double confidence = 0.95;  ///< of the reported intervals (trajectory()), (0, 1)
  /// A re-solve assumes the estimate rounded to sigma_0 (1 + sigma_step)^k, sigma_0 the problem's
  /// sigma: a re-solve that would not change the rounded sigmas is skipped, and the table cache
  /// can hit. >= 0 (0: no rounding).
  double sigma_step = 0.05;
  int max_cached = 3;  ///< tables kept besides the one in use (each holds its model), >= 0
  /// A stopped step (observeStopped) teaches only if its chord is at least this fraction of the
  /// step length delta: a short chord turns tip-tracking error into a large angle error.
  double min_stopped_chord = 0.1;
  SolverOptions solver;  ///< for each re-solve
  int threads = 2;       ///< model building
  /// Re-solved tables are loaded from / saved to <table_dir>/<scene_name>_<hash>.table (so that
  /// another process, e.g. the procedure's report, can load the table that answered); "" = none.
  std::string table_dir;
  std::string scene_name;
};

/// One point of the sigma trajectory, recorded after each observed step.
struct SigmaSample {
  std::int64_t step = 0;  ///< steps observed so far
  SigmaEstimate insert;   ///< sigma_i
  SigmaEstimate flip;     ///< sigma_r
};

/// One re-solve.
struct Resolve {
  std::int64_t requested_at_step = 0;
  Control trigger = Control::kInsert;  ///< whose interval excluded the sigma in use
  std::int64_t swapped_at_step = -1;   ///< -1 while it runs
  double sigma_insert_rad = 0.0;       ///< assumed by the new table
  double sigma_flip_rad = 0.0;
  double seconds = 0.0;  ///< build + solve (0 when the cache had it)
  bool cached = false;
};

/// One whole step of delta seen in a running needle's tips, for AdaptivePolicy::observe.
struct ObservedStep {
  TipPose before;
  TipPose after;
  Control control = Control::kInsert;  ///< kFlip when the bevel changed at the step's start
};

/// Pairs the tips of a running needle, as a robot or tracker publishes them (mid-motion, at rest,
/// before and after a flip, at any rate), into whole steps. A step goes from the first tip at rest
/// at a step boundary (k delta of inserted length) to the first at the next ((k + 1) delta); its
/// control is whether the bevel changed between them, so a step drawn after a flip counts as a
/// flip even when the policy's answer to the post-flip tip was "insert". Tips between boundaries
/// (mid-motion, or stopped at a contact) are skipped; the first step of a needle is not paired (in
/// the tips a new entry with another bevel looks like a flip); a step either end of which no one
/// vouched for (ground truth or a confident image) is not paired.
class StepPairing {
public:
  /// @param[in] delta_m the step length of the model [m], > 0
  explicit StepPairing(double delta_m);
  /// The step this tip completes, if any.
  std::optional<ObservedStep> add(double inserted_length_m, const TipPose& pose, bool vouched);

private:
  double delta_m_;
  bool anchored_ = false;  ///< a boundary tip is known
  bool vouched_ = false;   ///< ... and vouched for
  TipPose anchor_;
  double anchor_steps_ = 0.0;  ///< its inserted length in steps
};

class AdaptivePolicy {
public:
  /// Starts from `initial` (the problem's sigmas; its params fix the grid of every re-solve).
  /// @param[in] problem the problem the initial table was solved for
  AdaptivePolicy(SteeringProblem problem, std::shared_ptr<const PolicySource> initial,
                 AdaptationOptions options);
  ~AdaptivePolicy();
  AdaptivePolicy(const AdaptivePolicy&) = delete;
  AdaptivePolicy& operator=(const AdaptivePolicy&) = delete;

  /// The control and P_s of the table in use (never blocks on a solve).
  ControlLookup lookup(const TipPose& pose) const;
  /// The table in use and its model (shared: stays valid after a swap).
  std::shared_ptr<const PolicySource> current() const;
  /// Adds the deflection of one observed whole step (length delta) and starts a re-solve if the
  /// sigma in use left the test's interval (AdaptationOptions::false_resolve_rate; when adapting
  /// and no solve is running). Throws std::invalid_argument for a non-finite pose (the estimate
  /// is unchanged).
  void observe(const TipPose& before, const TipPose& after, Control control);
  /// The same for a step that stopped early (contact with an obstacle or the workspace edge) at
  /// `stopped`: its deflection comes from the chord (NoiseEstimator::deflectionOfStoppedStep).
  /// Returns false when the chord is too short to teach (nothing recorded).
  bool observeStopped(const TipPose& before, const TipPose& stopped, Control control);
  /// Swaps in a finished re-solve; true if the table changed.
  bool poll();
  /// Waits for a running re-solve and swaps it in; true if the table changed.
  bool waitAndSwap();
  bool solving() const;

  const NoiseEstimator& estimator() const { return estimator_; }
  const std::vector<SigmaSample>& trajectory() const { return trajectory_; }
  const std::vector<Resolve>& resolves() const { return resolves_; }
  /// The sigmas the table in use assumes [rad].
  double assumedSigma(Control control) const;
  /// The confidence level of the re-solve test after n deflections of a control (>= min_samples).
  double testConfidence(std::int64_t n) const;

private:
  /// Records the trajectory point and runs the re-solve test for `control`.
  void afterSample(Control control);
  /// sigma rounded to the problem's sigma_0 (1 + sigma_step)^k.
  double rounded(Control control, double sigma_rad) const;
  void startResolve(Control trigger, double sigma_insert_rad, double sigma_flip_rad);
  bool swapIn();

  SteeringProblem problem_;        ///< its params.sigma_* are those of current_
  double sigma0_[2] = {0.0, 0.0};  ///< the initial table's sigma_i, sigma_r [rad]
  AdaptationOptions options_;
  NoiseEstimator estimator_;
  mutable std::mutex mutex_;  ///< guards current_
  std::shared_ptr<const PolicySource> current_;
  std::future<std::shared_ptr<const PolicySource>> pending_;
  SteeringProblem pending_problem_;
  /// Tables by model hash, most recently used last (at most max_cached + 1).
  std::vector<std::pair<std::uint64_t, std::shared_ptr<const PolicySource>>> cache_;
  std::vector<SigmaSample> trajectory_;
  std::vector<Resolve> resolves_;
  std::int64_t steps_ = 0;
};

/// The noise a trial's table assumed (SteeringControl.sigma_insert_rad / sigma_flip_rad of the
/// trial's first answer) [rad].
struct TrialNoise {
  double sigma_insert_rad = 0.0;
  double sigma_flip_rad = 0.0;
};

/// One table a run's trials used, with the trials (indices into the run's list) that used it.
struct TableUsed {
  TrialNoise noise;
  std::vector<int> trials;
  std::shared_ptr<const PolicySource> policy;  ///< its model and table
};

/// The tables behind a run whose policy may have re-solved (the procedure's report predicts P_s
/// and runs its Monte Carlo per table): one entry per distinct noise, in order of first use, each
/// solveOrLoad(withNoise(chosen, noise), scene_name, table_dir, options) — loaded when
/// steering_policy saved it after the re-solve (AdaptationOptions::table_dir), else solved.
/// `chosen` is the problem of the model the scene's tolerance chose (PolicySource::model->
/// problem()). A failed solve comes back as its status; nothing is kept.
Result<std::vector<TableUsed>> tablesUsed(const SteeringProblem& chosen,
                                          const std::vector<TrialNoise>& trials,
                                          const std::string& scene_name,
                                          const std::string& table_dir,
                                          const SelectionOptions& options);

}  // namespace needle_guidance::steering
