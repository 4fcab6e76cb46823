// The start state the procedure uses, chosen so that its predicted P_s can be trusted (not in
// the dissertation; 5.5 takes the maximiser of the table's P_s over the entry line, figure 5.7).
// That maximum over thousands of states lands where the discretised MDP is most optimistic,
// often next to a workspace edge or an obstacle where the grid's rounding is worst. So the
// highest-ranked, mutually distinct start states are screened by a Monte Carlo of the continuous
// needle (monte_carlo.h) following the table's policy; the start with the highest lower bound
// among those whose prediction the screen confirms is chosen, and verified once more with fresh
// seeds. Plain C++; no ROS.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/policy_table.h"

namespace needle_guidance::steering {

struct StartVerificationOptions {
  /// Distinct start states screened (the best by predicted P_s, see separation_*), >= 1.
  int candidates = 8;
  /// Two screened starts of the same bevel differ by more than separation_m in height or more
  /// than separation_rad in angle, so the screen does not spend itself on neighbours of one
  /// optimistic state [m], [rad], >= 0.
  double separation_m = 2e-3;
  double separation_rad = 0.16;
  std::int64_t screen_trials = 1000;  ///< Monte Carlo trials per screened start, >= 1
  /// Fresh trials at a chosen start, >= 0; 0 = from the tolerance and the start's P_s:
  /// n = max(16,000, 1 / tolerance^2) x 4 v, v the larger of p (1 - p) of the prediction and of
  /// the screen's rate (at P_s 0.5: 40,000 at 0.005, 16,000 at 0.01; at most 100,000; at least
  /// screen_trials), so the verification's binomial standard error is at most half the
  /// tolerance at its own P_s.
  std::int64_t verify_trials = 0;
  /// The gap |predicted - Monte Carlo| a confirmed prediction may have (the scene's
  /// ps_tolerance), >= 0. The screen allows the binomial noise on top (z below); the
  /// verification does not: its own gap must be within the tolerance.
  double tolerance = 0.01;
  double z = 1.959963984540054;  ///< of the intervals (95 %), > 0
  std::uint64_t seed = 23;       ///< screen: (seed, i); verification: (seed + 1, i)
  int threads = 2;               ///< Monte Carlo threads, >= 1
  int max_steps = 200;           ///< insertions per trial, >= 1
};

/// One screened start state.
struct ScreenedStart {
  StartCandidate candidate;
  MonteCarloResult screen;
  /// |predicted - screen rate| <= tolerance + z * binomial standard error of the prediction.
  bool confirmed = false;
  /// The rank key: the screen's Wilson lower bound, capped by the prediction.
  double score = 0.0;
};

/// The start state chosen and its verification.
struct VerifiedStart {
  bool found = false;
  StartCandidate start;                 ///< the start used: pose, state, predicted P_s
  MonteCarloResult verification;        ///< verify_trials fresh trials from it
  bool confirmed = false;               ///< |predicted - verified rate| <= tolerance
  std::vector<ScreenedStart> screened;  ///< in the order screened (best prediction first)
  int rank_by_prediction = 0;           ///< 0 = the table's own best start (bestStart)
  double tolerance = 0.0;
  double seconds = 0.0;  ///< wall time [s]
  std::string message;   ///< why nothing was found, else empty

  explicit operator bool() const { return found; }
  double predicted() const { return start.probability_of_success; }
  /// predicted - verified rate.
  double gap() const { return predicted() - verification.rate(); }
  /// "y = 43.0 mm, theta = 18.0 deg, bevel left: predicted P_s 0.344, verified 0.341
  /// [0.332, 0.350] (10000 trials), confirmed within 0.01; 2nd of 8 screened".
  std::string toString() const;
};

/// The distinct best start states (entry line, `start`) by predicted P_s, at most `count`, each
/// separated from every better one of its bevel (options.separation_*). Empty when no start has P_s
/// > 0.
std::vector<StartCandidate> distinctBestStarts(const PolicyTable& table, const StartOptions& start,
                                               const StartVerificationOptions& options);

/// Screens distinctBestStarts by Monte Carlo of the continuous needle under the table's policy,
/// takes the screen-confirmed one with the highest score (none confirmed: the highest score) and
/// verifies it with fresh seeds; if its verified gap exceeds the tolerance, the next is verified,
/// up to five. The start is the first verified within the tolerance, else the verified one
/// with the smallest gap (confirmed = false). found = false (with the reason) when no start
/// has P_s > 0. Throws std::invalid_argument naming a bad option.
VerifiedStart verifyBestStart(const ContinuousWorkspace& world, const PolicyTable& table,
                              const StartOptions& start,
                              const StartVerificationOptions& options = {});

/// The tolerance a start's prediction is verified to when the scene states none
/// (ps_tolerance 0): the loader's default ps_tolerance.
constexpr double kDefaultVerificationTolerance = 0.01;
/// The problem's ps_tolerance, or kDefaultVerificationTolerance when it is 0.
inline double verificationTolerance(const SteeringProblem& problem) {
  return problem.ps_tolerance > 0.0 ? problem.ps_tolerance : kDefaultVerificationTolerance;
}

/// True if `predicted` agrees with a Monte Carlo of `trials` trials at `rate`: |predicted - rate|
/// <= tolerance + z * sqrt(predicted (1 - predicted) / trials).
bool predictionConfirmed(double predicted, double rate, std::int64_t trials, double tolerance,
                         double z = 1.959963984540054);

}  // namespace needle_guidance::steering
