// The start state the procedure uses, chosen so that its predicted P_s can be trusted (not in
// the dissertation; 5.5 takes the maximiser of the table's P_s over the entry line, figure 5.7).
// That maximum over thousands of states lands where the discretised MDP is most optimistic,
// often next to a workspace edge or an obstacle where the grid's rounding is worst. So the
// highest-ranked, mutually distinct start states are screened by a Monte Carlo of the continuous
// needle (monte_carlo.h) following the table's policy; the start with the highest lower bound
// among those whose prediction the screen confirms is chosen and verified with fresh seeds by a
// staged Monte Carlo. The P_s reported for it is the table's prediction when the verification
// confirms it beyond its own noise, and the verified rate otherwise. Plain C++; no ROS.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/policy_table.h"

namespace needle_guidance::steering {

/// z of the verification's confirmation: the one-sided 2.5 % / 3 quantile, so that over the at
/// most 3 looks the default first look gives (verify_trials 0), a prediction off by the
/// tolerance is confirmed in at most 2.5 % of verifications (Bonferroni).
constexpr double kVerificationConfirmZ = 2.3939797998185104;

struct StartVerificationOptions {
  /// Distinct start states screened (the best by predicted P_s, see separation_*), >= 1.
  int candidates = 8;
  /// Two screened starts of the same bevel differ by more than separation_m in height or more
  /// than separation_rad in angle, so the screen does not spend itself on neighbours of one
  /// optimistic state [m], [rad], >= 0.
  double separation_m = 2e-3;
  double separation_rad = 0.16;
  std::int64_t screen_trials = 1000;  ///< Monte Carlo trials per screened start, >= 1
  /// Fresh trials of the verification's first look, >= 0; 0 = from the tolerance and the
  /// start's P_s: n0 = max(16,000, 1 / tolerance^2) x 4 v, v the larger of p (1 - p) of the
  /// prediction and of the screen's rate (at P_s 0.5: 16,000 at 0.01, 40,000 at 0.005; at least
  /// screen_trials, at most max_verify_trials).
  std::int64_t verify_trials = 0;
  /// The most trials of a verification, >= 1. A verification that is not confirmed goes on in
  /// looks of twice the trials (the same seeds continued) until z SE <= tolerance / 2 at its own
  /// rate r (n >= z^2 r (1 - r) / (tolerance / 2)^2: 38,415 at r = 0.5, tolerance 0.01) or until
  /// these trials.
  std::int64_t max_verify_trials = 100000;
  /// The gap |P_s reported - true P_s| the procedure answers for (the scene's ps_tolerance), >= 0.
  /// The screen confirms when |predicted - rate| <= tolerance + z SE; the verification only when
  /// |predicted - rate| + confirm_z SE <= tolerance.
  double tolerance = 0.01;
  /// Of the screen's intervals (95 %) and of the verification's cap (z SE <= tolerance / 2), > 0.
  double z = 1.959963984540054;
  /// Of the verification's confirmation |predicted - rate| + confirm_z SE <= tolerance, > 0.
  double confirm_z = kVerificationConfirmZ;
  std::uint64_t seed = 23;  ///< screen: (seed, i); verification: (seed + 1, i)
  int threads = 2;          ///< Monte Carlo threads, >= 1
  int max_steps = 200;      ///< insertions per trial, >= 1
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
  StartCandidate start;           ///< the start used: pose, state, predicted P_s
  MonteCarloResult verification;  ///< its fresh trials, every look together
  /// |predicted - verified rate| + confirm_z SE <= tolerance (SE the binomial standard error at
  /// the verified rate): the reported P_s is the prediction. Otherwise it is the verified rate.
  bool confirmed = false;
  int looks = 0;  ///< looks of the staged verification (1 = stopped at the first)
  std::int64_t first_look_trials = 0;   ///< trials of its first look
  std::vector<ScreenedStart> screened;  ///< in the order screened (best prediction first)
  int rank_by_prediction = 0;           ///< 0 = the table's own best start (bestStart)
  double tolerance = 0.0;
  double z = kVerificationConfirmZ;  ///< of the verification's confirmation
  double seconds = 0.0;              ///< wall time [s]
  std::string message;               ///< why nothing was found, else empty

  explicit operator bool() const { return found; }
  double predicted() const { return start.probability_of_success; }
  /// The P_s the procedure reports for this start: the prediction when confirmed, else the
  /// verified Monte Carlo rate (whose interval is verification.interval()).
  double reported() const { return confirmed ? predicted() : verification.rate(); }
  /// predicted - verified rate.
  double gap() const { return predicted() - verification.rate(); }
  /// The verification's binomial standard error at its own rate, sqrt(r (1 - r) / n).
  double standardError() const;
  /// Confirmed: "y = 43.0 mm, theta = 18.0 deg, bevel left: P_s 0.645 (the model's prediction,
  /// confirmed: verified 0.643 [0.636, 0.650] over 16000 trials, |gap| 0.0021 + 2.39 x SE 0.0038
  /// = 0.011 <= 0.015); 1st of 8 screened". Not confirmed: "...: P_s 0.631 [0.626, 0.636] (the
  /// verified rate over 38415 trials; the model's 0.645 NOT confirmed within 0.01: |gap| 0.014 +
  /// 2.39 x SE 0.0025 = 0.02 > 0.01); ...".
  std::string toString() const;
};

/// The distinct best start states (entry line, `start`) by predicted P_s, at most `count`, each
/// separated from every better one of its bevel (options.separation_*). Empty when no start has P_s
/// > 0.
std::vector<StartCandidate> distinctBestStarts(const PolicyTable& table, const StartOptions& start,
                                               const StartVerificationOptions& options);

/// Screens distinctBestStarts by Monte Carlo of the continuous needle under the table's policy,
/// takes the screen-confirmed one with the highest score (none confirmed: the highest score) and
/// verifies that one with fresh seeds (seed + 1) in looks: the first of verify_trials trials,
/// each next one continuing the same trials to twice as many, capped where z SE <= tolerance / 2
/// at the verified rate and at max_verify_trials. It stops at the first look that confirms the
/// prediction (verificationConfirms with confirm_z) or at the cap. found = false (with the reason)
/// when no start has P_s > 0. Throws std::invalid_argument naming a bad option.
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

/// The verification's rule: |predicted - rate| + z sqrt(rate (1 - rate) / trials) <= tolerance.
/// False for no trials or a non-finite value.
bool verificationConfirms(double predicted, const MonteCarloResult& mc, double tolerance,
                          double z = kVerificationConfirmZ);

/// `trials` more trials of one seeded run from one start, trials first_trial .. first_trial +
/// trials - 1 (runMonteCarlo with TrialOptions::first_trial).
using TrialSampler = std::function<MonteCarloResult(std::int64_t first_trial, std::int64_t trials)>;

/// A staged verification: its trials (every look together), the decision and the looks taken.
struct StagedVerification {
  MonteCarloResult mc;
  bool confirmed = false;
  int looks = 0;
};

/// The staged verification of `predicted` (verifyBestStart): one run of `sample` looked at after
/// `first` trials, after twice as many, and at the cap (verificationCap with options.z at the
/// rate of the look before), stopping at the first look that confirms the prediction
/// (verificationConfirms with options.confirm_z) or reaches the cap: at most 3 looks.
StagedVerification verifyInLooks(double predicted, std::int64_t first,
                                 const StartVerificationOptions& options,
                                 const TrialSampler& sample);

/// The trials at which a verification at `rate` stops unconfirmed: z^2 rate (1 - rate) /
/// (tolerance / 2)^2 rounded up, within [first, max_trials].
std::int64_t verificationCap(double rate, double tolerance, double z, std::int64_t first,
                             std::int64_t max_trials);

/// True if `predicted` agrees with a Monte Carlo of `trials` trials at `rate`: |predicted - rate|
/// <= tolerance + z * sqrt(predicted (1 - predicted) / trials).
bool predictionConfirmed(double predicted, double rate, std::int64_t trials, double tolerance,
                         double z = 1.959963984540054);

}  // namespace needle_guidance::steering
