// The start state chosen so that its prediction can be trusted (see start_verification.h).
#include "needle_guidance/steering/start_verification.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "needle_guidance/format.h"

namespace needle_guidance::steering {
namespace {

constexpr double kPi = 3.14159265358979323846;
/// Fewest fresh trials of a verification's first look (verify_trials 0).
constexpr std::int64_t kMinVerifyTrials = 16000;
/// Growth of a verification's trials from its first look to its second.
constexpr std::int64_t kLookGrowth = 2;
/// Looks of a verification at most: the first, twice its trials, then the cap (the number
/// kVerificationConfirmZ covers).
constexpr int kMaxLooks = 3;

void checkOptions(const StartVerificationOptions& o) {
  const std::pair<bool, std::pair<const char*, double>> checks[] = {
      {o.candidates >= 1, {"candidates (>= 1)", o.candidates}},
      {o.separation_m >= 0.0, {"separation_m (>= 0)", o.separation_m}},
      {o.separation_rad >= 0.0, {"separation_rad (>= 0)", o.separation_rad}},
      {o.screen_trials >= 1, {"screen_trials (>= 1)", double(o.screen_trials)}},
      {o.verify_trials >= 0, {"verify_trials (>= 0)", double(o.verify_trials)}},
      {o.max_verify_trials >= 1, {"max_verify_trials (>= 1)", double(o.max_verify_trials)}},
      {o.tolerance >= 0.0 && o.tolerance < 1.0, {"tolerance [0, 1)", o.tolerance}},
      {o.z > 0.0 && std::isfinite(o.z), {"z (> 0)", o.z}},
      {o.confirm_z > 0.0 && std::isfinite(o.confirm_z), {"confirm_z (> 0)", o.confirm_z}},
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

/// Fresh trials of a verification's first look (verify_trials 0): those that give the standard
/// error of max(16,000, 1 / tolerance^2) trials at P_s 0.5, at the larger binomial variance of
/// the candidate's prediction and of its screen's rate; never fewer than the screen ran, never
/// more than max_verify_trials.
std::int64_t firstLookTrials(const StartVerificationOptions& o, const ScreenedStart& s) {
  if (o.verify_trials > 0) {
    return std::min(o.verify_trials, o.max_verify_trials);
  }
  const double at_half = std::max(double(kMinVerifyTrials),
                                  std::ceil(1.0 / std::max(o.tolerance * o.tolerance, 1e-5)));
  const double p = std::clamp<double>(s.candidate.probability_of_success, 0.0, 1.0);
  const double r = s.screen.rate();
  const double variance = std::max(p * (1.0 - p), r * (1.0 - r));
  const auto n = std::max<std::int64_t>(
      o.screen_trials, static_cast<std::int64_t>(std::ceil(at_half * 4.0 * variance)));
  return std::min(n, o.max_verify_trials);
}

std::string ordinal(int n) {
  const int last = n % 10;
  const bool teen = n % 100 >= 11 && n % 100 <= 13;
  const char* suffix = teen ? "th" : last == 1 ? "st" : last == 2 ? "nd" : last == 3 ? "rd" : "th";
  return std::to_string(n) + suffix;
}

/// The binomial standard error of a Monte Carlo's rate at that rate (NaN without trials).
double rateStandardError(const MonteCarloResult& mc) {
  if (mc.trials < 1) {
    return std::numeric_limits<double>::quiet_NaN();
  }
  const double r = mc.rate();
  return std::sqrt(r * (1.0 - r) / double(mc.trials));
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

StagedVerification verifyInLooks(double predicted, std::int64_t first,
                                 const StartVerificationOptions& o, const TrialSampler& sample) {
  StagedVerification out;
  out.mc = sample(0, first);
  for (out.looks = 1;; ++out.looks) {
    out.confirmed = verificationConfirms(predicted, out.mc, o.tolerance, o.confirm_z);
    const std::int64_t cap =
        verificationCap(out.mc.rate(), o.tolerance, o.z, first, o.max_verify_trials);
    if (out.confirmed || out.mc.trials >= cap || out.looks == kMaxLooks) {
      return out;
    }
    const std::int64_t next =
        out.looks + 1 == kMaxLooks ? cap : std::min(out.mc.trials * kLookGrowth, cap);
    out.mc = combined(out.mc, sample(out.mc.trials, next - out.mc.trials));  // the same run
  }
}

bool verificationConfirms(double predicted, const MonteCarloResult& mc, double tolerance,
                          double z) {
  if (mc.trials < 1 || !std::isfinite(predicted) || !std::isfinite(tolerance)) {
    return false;
  }
  return std::abs(predicted - mc.rate()) + z * rateStandardError(mc) <= tolerance;
}

std::int64_t verificationCap(double rate, double tolerance, double z, std::int64_t first,
                             std::int64_t max_trials) {
  const double half = 0.5 * tolerance;
  const double r = std::clamp(rate, 0.0, 1.0);
  const double needed = half > 0.0 ? std::ceil(z * z * r * (1.0 - r) / (half * half))
                                   : double(std::numeric_limits<std::int64_t>::max());
  const double capped = std::min(needed, double(max_trials));
  return std::max(first, static_cast<std::int64_t>(capped));
}

double VerifiedStart::standardError() const {
  return rateStandardError(verification);
}

std::string VerifiedStart::toString() const {
  if (!found) {
    return message;
  }
  std::ostringstream out;
  const Interval ci = verification.interval();
  const double bound = std::abs(gap()) + z * standardError();
  const std::string rule = "|gap| " + formatNumber(std::abs(gap()), 3) + " + " +
                           formatNumber(z, 3) + " x SE " + formatNumber(standardError(), 2) +
                           " = " + formatNumber(bound, 3) + (confirmed ? " <= " : " > ") +
                           formatNumber(tolerance, 3);
  const std::string interval =
      "[" + formatNumber(ci.low, 3) + ", " + formatNumber(ci.high, 3) + "]";
  out << "y = " << formatNumber(start.pose.p_SceneTip.y() * 1e3, 4)
      << " mm, theta = " << formatNumber(start.pose.theta_rad * 180.0 / kPi, 3) << " deg, bevel "
      << steering::toString(start.pose.bevel) << ": P_s " << formatNumber(reported(), 4);
  if (confirmed) {
    out << " (the model's prediction, confirmed: verified " << formatNumber(verification.rate(), 4)
        << " " << interval << " over " << verification.trials << " trials, " << rule << ")";
  } else {
    out << " " << interval << " (the verified rate over " << verification.trials
        << " trials; the model's " << formatNumber(predicted(), 4) << " NOT confirmed within "
        << formatNumber(tolerance, 3) << ": " << rule << ")";
  }
  out << "; " << ordinal(rank_by_prediction + 1) << " of " << screened.size() << " screened";
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
  out.z = options.confirm_z;
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
  // The screen's choice: the confirmed one with the highest score (ties: the better prediction,
  // screened first); none confirmed: the highest score.
  std::size_t chosen = 0;
  for (std::size_t i = 1; i < out.screened.size(); ++i) {
    const ScreenedStart& a = out.screened[i];
    const ScreenedStart& b = out.screened[chosen];
    if (a.confirmed != b.confirmed ? a.confirmed : a.score > b.score) {
      chosen = i;
    }
  }
  const ScreenedStart& screened = out.screened[chosen];
  out.found = true;
  out.start = screened.candidate;
  out.rank_by_prediction = static_cast<int>(chosen);
  const std::int64_t first = firstLookTrials(options, screened);
  const TrialSampler sample = [&](std::int64_t first_trial, std::int64_t trials) {
    TrialOptions continued = trial;
    continued.first_trial = first_trial;
    return runMonteCarlo(world, out.start.pose, policy, trials, options.seed + 1, options.threads,
                         continued);
  };
  const StagedVerification v = verifyInLooks(out.predicted(), first, options, sample);
  out.verification = v.mc;
  out.confirmed = v.confirmed;
  out.looks = v.looks;
  out.first_look_trials = first;
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return out;
}

}  // namespace needle_guidance::steering
