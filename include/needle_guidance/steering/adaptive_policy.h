// A steering policy that learns the needle's deflection noise from the tip poses it sees
// (issue 21): NoiseEstimator accumulates the deflection of every observed step; when the
// estimate's interval no longer contains the sigma the current table assumed, the MDP is solved
// again for the estimate on a background thread while the old table keeps answering; the new
// table is swapped in at the next poll(). Tables are cached by model hash. Not in the
// dissertation (5.3 takes sigma_i, sigma_r as known). Plain C++; no ROS.
#pragma once

#include <cstdint>
#include <future>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "needle_guidance/steering/model_selection.h"
#include "needle_guidance/steering/noise_estimator.h"

namespace needle_guidance::steering {

struct AdaptationOptions {
  bool adapt = true;  ///< false: the starting table is never replaced (the fixed-sigma policy)
  /// Deflections of a control needed before its interval may trigger a re-solve (>= 2).
  int min_samples = 10;
  double confidence = 0.95;  ///< of the intervals, (0, 1)
  SolverOptions solver;      ///< for each re-solve
  int threads = 2;           ///< model building
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
  std::int64_t swapped_at_step = -1;  ///< -1 while it runs
  double sigma_insert_rad = 0.0;      ///< assumed by the new table
  double sigma_flip_rad = 0.0;
  double seconds = 0.0;  ///< build + solve (0 when the cache had it)
  bool cached = false;
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
  /// Adds the deflection of one observed step and starts a re-solve if the estimate left the
  /// interval (when adapting and no solve is running). Throws std::invalid_argument for a
  /// non-finite pose (the estimate is unchanged).
  void observe(const TipPose& before, const TipPose& after, Control control);
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

private:
  void startResolve();
  bool swapIn();

  SteeringProblem problem_;  ///< its params.sigma_* are those of current_
  AdaptationOptions options_;
  NoiseEstimator estimator_;
  mutable std::mutex mutex_;  ///< guards current_
  std::shared_ptr<const PolicySource> current_;
  std::future<std::shared_ptr<const PolicySource>> pending_;
  SteeringProblem pending_problem_;
  std::map<std::uint64_t, std::shared_ptr<const PolicySource>> cache_;  ///< by model hash
  std::vector<SigmaSample> trajectory_;
  std::vector<Resolve> resolves_;
  std::int64_t steps_ = 0;
};

}  // namespace needle_guidance::steering
