// The start state chosen so that its prediction can be trusted (see start_verification.h).
#include "needle_guidance/steering/start_verification.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "needle_guidance/format.h"

namespace needle_guidance::steering {
namespace {

constexpr double kPi = 3.14159265358979323846;
/// Candidates verified with fresh seeds at most, in score order.
constexpr int kMaxVerified = 5;
/// Fewest fresh trials of a verification (verify_trials 0).
constexpr std::int64_t kMinVerifyTrials = 16000;

void checkOptions(const StartVerificationOptions& o) {
  const std::pair<bool, std::pair<const char*, double>> checks[] = {
      {o.candidates >= 1, {"candidates (>= 1)", o.candidates}},
      {o.separation_m >= 0.0, {"separation_m (>= 0)", o.separation_m}},
      {o.separation_rad >= 0.0, {"separation_rad (>= 0)", o.separation_rad}},
      {o.screen_trials >= 1, {"screen_trials (>= 1)", double(o.screen_trials)}},
      {o.verify_trials >= 0, {"verify_trials (>= 0)", double(o.verify_trials)}},
      {o.tolerance >= 0.0 && o.tolerance < 1.0, {"tolerance [0, 1)", o.tolerance}},
      {o.z > 0.0 && std::isfinite(o.z), {"z (> 0)", o.z}},
      {o.threads >= 1, {"threads (>= 1)", o.threads}},
      {o.max_steps >= 1, {"max_steps (>= 1)", o.max_steps}},
  };
  for (const auto& [ok, what] : checks) {
    if (!ok) {  // NaN fails every comparison above
      throw std::invalid_argument("verifyBestStart: " + std::string(what.first) +
                                  " out of range: " + formatNumber(what.second));
    }
  }
}

/// The smallest angle between two orientations [rad].
double angleBetween(double a, double b) {
  const double d = std::fmod(std::abs(a - b), 2.0 * kPi);
  return std::min(d, 2.0 * kPi - d);
}

/// Fresh trials of a verification (verify_trials 0): those that give the standard error of
/// max(16,000, 1 / tolerance^2) trials at P_s 0.5, at the larger binomial variance of the
/// candidate's prediction and of its screen's rate; never fewer than the screen ran.
std::int64_t verificationTrials(const StartVerificationOptions& o, const ScreenedStart& s) {
  const double at_half = std::max(double(kMinVerifyTrials),
                                  std::ceil(1.0 / std::max(o.tolerance * o.tolerance, 1e-5)));
  const double p = std::clamp<double>(s.candidate.probability_of_success, 0.0, 1.0);
  const double r = s.screen.rate();
  const double variance = std::max(p * (1.0 - p), r * (1.0 - r));
  return std::max<std::int64_t>(o.screen_trials,
                                static_cast<std::int64_t>(std::ceil(at_half * 4.0 * variance)));
}

std::string ordinal(int n) {
  const int last = n % 10;
  const bool teen = n % 100 >= 11 && n % 100 <= 13;
  const char* suffix = teen ? "th" : last == 1 ? "st" : last == 2 ? "nd" : last == 3 ? "rd" : "th";
  return std::to_string(n) + suffix;
}

}  // namespace

bool predictionConfirmed(double predicted, double rate, std::int64_t trials, double tolerance,
                         double z) {
  if (trials < 1 || !std::isfinite(predicted) || !std::isfinite(rate)) {
    return false;
  }
  const double p = std::clamp(predicted, 0.0, 1.0);
  const double noise = z * std::sqrt(p * (1.0 - p) / double(trials));
  return std::abs(predicted - rate) <= tolerance + noise;
}

std::string VerifiedStart::toString() const {
  if (!found) {
    return message;
  }
  std::ostringstream out;
  const Interval ci = verification.interval();
  out << "y = " << formatNumber(start.pose.p_SceneTip.y() * 1e3, 4)
      << " mm, theta = " << formatNumber(start.pose.theta_rad * 180.0 / kPi, 3) << " deg, bevel "
      << steering::toString(start.pose.bevel) << ": predicted P_s " << formatNumber(predicted(), 3)
      << ", verified " << formatNumber(verification.rate(), 3) << " [" << formatNumber(ci.low, 3)
      << ", " << formatNumber(ci.high, 3) << "] (" << verification.trials << " trials), "
      << (confirmed ? "confirmed within " : "NOT confirmed within ") << formatNumber(tolerance, 3)
      << "; " << ordinal(rank_by_prediction + 1) << " of " << screened.size() << " screened";
  return out.str();
}

std::vector<StartCandidate> distinctBestStarts(const PolicyTable& table, const StartOptions& start,
                                               const StartVerificationOptions& options) {
  std::vector<StartCandidate> all = table.startCandidates(start);
  std::stable_sort(all.begin(), all.end(), [](const StartCandidate& a, const StartCandidate& b) {
    return a.probability_of_success > b.probability_of_success;
  });
  std::vector<StartCandidate> out;
  if (all.empty() || !(all.front().probability_of_success > 0.0f)) {
    return out;
  }
  for (const StartCandidate& c : all) {
    if (static_cast<int>(out.size()) >= options.candidates || c.probability_of_success <= 0.0f) {
      break;
    }
    const bool near = std::any_of(out.begin(), out.end(), [&](const StartCandidate& kept) {
      return kept.pose.bevel == c.pose.bevel &&
             std::abs(kept.pose.p_SceneTip.y() - c.pose.p_SceneTip.y()) <= options.separation_m &&
             angleBetween(kept.pose.theta_rad, c.pose.theta_rad) <= options.separation_rad;
    });
    if (!near) {
      out.push_back(c);
    }
  }
  return out;
}

VerifiedStart verifyBestStart(const ContinuousWorkspace& world, const PolicyTable& table,
                              const StartOptions& start, const StartVerificationOptions& options) {
  checkOptions(options);
  const auto t0 = std::chrono::steady_clock::now();
  VerifiedStart out;
  out.tolerance = options.tolerance;
  const std::vector<StartCandidate> candidates = distinctBestStarts(table, start, options);
  if (candidates.empty()) {
    const BestStart best = table.bestStart(start);
    out.message =
        best.message.empty() ? "verifyBestStart: no start state with P_s > 0" : best.message;
    return out;
  }
  const SteeringPolicy policy = tablePolicy(table);
  TrialOptions trial;
  trial.max_steps = options.max_steps;
  for (const StartCandidate& c : candidates) {
    ScreenedStart s;
    s.candidate = c;
    s.screen = runMonteCarlo(world, c.pose, policy, options.screen_trials, options.seed,
                             options.threads, trial);
    s.confirmed = predictionConfirmed(c.probability_of_success, s.screen.rate(), s.screen.trials,
                                      options.tolerance, options.z);
    s.score = std::min<double>(c.probability_of_success,
                               wilsonInterval(s.screen.successes, s.screen.trials, options.z).low);
    out.screened.push_back(s);
  }
  // Confirmed candidates first, each group by score (ties: the better prediction, screened first).
  std::vector<int> order(out.screened.size());
  for (std::size_t i = 0; i < order.size(); ++i) {
    order[i] = static_cast<int>(i);
  }
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) {
    const ScreenedStart& sa = out.screened[static_cast<std::size_t>(a)];
    const ScreenedStart& sb = out.screened[static_cast<std::size_t>(b)];
    if (sa.confirmed != sb.confirmed) {
      return sa.confirmed;
    }
    return sa.score > sb.score;
  });
  double best_gap = 1.0;
  const int tries = std::min<int>(kMaxVerified, static_cast<int>(order.size()));
  for (int i = 0; i < tries; ++i) {
    const int index = order[static_cast<std::size_t>(i)];
    const ScreenedStart& screened = out.screened[static_cast<std::size_t>(index)];
    const StartCandidate& c = screened.candidate;
    const std::int64_t verify_trials =
        options.verify_trials > 0 ? options.verify_trials : verificationTrials(options, screened);
    const MonteCarloResult mc = runMonteCarlo(world, c.pose, policy, verify_trials,
                                              options.seed + 1, options.threads, trial);
    // Strict: the verified gap itself within the tolerance (no allowance for the noise).
    const bool confirmed =
        predictionConfirmed(c.probability_of_success, mc.rate(), mc.trials, options.tolerance, 0.0);
    const double gap = std::abs(c.probability_of_success - mc.rate());
    if (confirmed || !out.found || gap < best_gap) {
      out.found = true;
      out.start = c;
      out.verification = mc;
      out.confirmed = confirmed;
      out.rank_by_prediction = index;
      best_gap = gap;
    }
    if (confirmed) {
      break;
    }
  }
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return out;
}

}  // namespace needle_guidance::steering
