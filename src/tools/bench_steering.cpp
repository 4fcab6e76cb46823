// Benchmark of the steerable-needle MDP planner (dissertation 5.4.2-5.5): build and
// solve time, sweeps and peak memory against the number of states on the steering_workspace
// scene at Delta = 4, 2, 1 mm (1 mm = the dissertation's 800,000-state problem) and 0.5 mm as
// the finer reference; 1 vs 2 threads; epsilon against the value error (speed against error);
// P_s at a fixed start pose against the grid spacing; O(1) control look-up time; table file
// size and save/load time; the start-state surface of figure 5.7.
// Usage: bench_steering --out DIR [--quick] [--scene SPEC]
//        bench_steering --truth-only --out DIR [--scene SPEC]... (the truth check where the start
//        is chosen, per scene: chosen start, 10 best starts, starts near every boundary, and the
//        procedure's closed loop on the robot's simulated needle at the chosen start)

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <memory>
#include <optional>
#include <random>
#include <sstream>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "needle_guidance/cpu_time.h"
#include "needle_guidance/math.h"
#include "needle_guidance/procedures/guided_trial.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/process_usage.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/adaptive_policy.h"
#include "needle_guidance/steering/exact_pose_prediction.h"
#include "needle_guidance/steering/model_selection.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/shortest_path.h"
#include "needle_guidance/steering/start_verification.h"
#include "needle_guidance/steering/steering_model.h"
#include "needle_guidance/steering/value_iteration.h"

namespace ng = needle_guidance;
using needle_guidance::processCpuSeconds;
using needle_guidance::report::peakMb;
namespace st = ng::steering;

namespace {

using needle_guidance::kPi;
constexpr double kMmPerM = 1e3;
constexpr double kDegPerRad = 180.0 / kPi;
/// Look-ups timed for lookup_us.
constexpr int kLookups = 1000000;
/// Seed of the random look-up poses.
constexpr unsigned kLookupSeed = 5;
/// The grid spacing of the dissertation's 800,000-state problem [m].
constexpr double kSpacing800k_m = 1e-3;
/// Solves per grid whose median time is reported.
constexpr int kSolveRepeats = 3;
/// Solves of the scene's chosen model: solve_s_default is the fastest (on a shared machine the
/// others are slowed by other processes; their median is solve_s_default_median).
constexpr int kDefaultSolveRepeats = 5;
/// Monte Carlo trials per start state (>= 10,000).
constexpr std::int64_t kMonteCarloTrials = 10000;
/// Seed of the Monte Carlo trials (trial i of every start uses the stream (seed, i)).
constexpr std::uint64_t kMonteCarloSeed = 11;
/// Start states whose predicted and simulated P_s are both below this are left out of the
/// truth check: they agree trivially.
constexpr double kTrivialPs = 0.01;

/// The mean |gap| binomial noise alone gives at a start of P_s `predicted` over `trials`
/// (sqrt(2 / pi) times the standard error; a table value a rounding past 1 counts as 1).
double noiseFloor(double predicted, std::int64_t trials) {
  const double p = std::clamp(predicted, 0.0, 1.0);
  return std::sqrt(2.0 / kPi * p * (1.0 - p) / double(trials));
}

/// Heights of the truth check's start states on the entry line [mm].
const std::vector<double> kTruthHeights_mm = {5.0, 10.0, 15.0, 30.0, 54.0, 60.0, 80.0};

double secondsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

struct Solved {
  double spacing_m = 0.0;
  int subdivision = 1;  ///< orientation_subdivision s
  st::TransitionModel transition = st::TransitionModel::kRounded;
  std::int64_t states = 0;
  double build_s = 0.0;
  st::SolveStats stats;    ///< of the last solve, seconds = the median over the repeats
  double fastest_s = 0.0;  ///< the fastest of the repeats [s]
  double peak_mb = 0.0;
  int transitions = 0;
  std::unique_ptr<const st::SteeringModel> model;
  std::unique_ptr<const st::PolicyTable> table;
  st::BestStart best;
};

/// Builds and solves at one grid spacing and orientation subdivision; the solve time is the
/// median of `repeats` solves (the first also pays for page faults).
Solved solveAt(const st::SteeringProblem& base, double spacing_m, int threads, double epsilon,
               const st::StartOptions& start, int subdivision = 1, int repeats = kSolveRepeats,
               st::TransitionModel transition = st::TransitionModel::kRounded) {
  st::SteeringProblem problem = base;
  problem.params.grid_spacing_m = spacing_m;
  problem.params.orientation_subdivision = subdivision;
  problem.params.transition_model = transition;
  Solved out;
  out.transition = transition;
  out.spacing_m = spacing_m;
  out.subdivision = subdivision;
  const auto t0 = std::chrono::steady_clock::now();
  out.model = std::make_unique<const st::SteeringModel>(problem, threads);
  const st::SteeringModel& model = *out.model;
  out.build_s = secondsSince(t0);
  out.states = model.numStates();
  out.transitions = model.maxTransitions();
  st::SolverOptions options;
  options.threads = threads;
  options.epsilon = epsilon;
  std::vector<double> seconds;
  for (int i = 0; i < repeats; ++i) {
    out.table = std::make_unique<const st::PolicyTable>(
        st::solveValueIteration(model, options, &out.stats));
    seconds.push_back(out.stats.seconds);
  }
  std::sort(seconds.begin(), seconds.end());
  out.stats.seconds = seconds[seconds.size() / 2];
  out.fastest_s = seconds.front();
  out.peak_mb = peakMb();
  out.best = out.table->bestStart(start);
  return out;
}

/// The truth check at one (Delta, s) after another: per start state, the table's
/// predicted P_s against (a) the continuous needle (exact arcs, continuous deflections), (b)
/// the same needle with deflections rounded to the model's orientation step and (c) the MDP's
/// own Markov chain, all with the same seeds, so that
///   predicted - chain      = solver error (should be noise only),
///   chain - rounded        = position rounding of 5.4.2 (and the grid-aligned obstacle edges),
///   rounded - continuous   = deflection quantisation (alpha / s).
class TruthCheck {
public:
  struct Summary {
    double spacing_mm = 0.0;
    int subdivision = 1;
    std::int64_t states = 0;
    double total_s = 0.0;
    int starts = 0;
    double within = 0.0;        ///< fraction of starts whose predicted P_s is in the MC CI
    double mean_abs_gap = 0.0;  ///< mean |predicted - MC|
    double noise_floor = 0.0;   ///< mean E|MC - p| from binomial noise alone
  };

  TruthCheck(const st::ContinuousWorkspace& world, std::vector<st::TipPose> starts)
      : world_(world),
        starts_(std::move(starts)),
        per_start_({"grid_spacing_mm", "subdivision", "y_mm", "theta_deg", "bevel", "predicted_ps",
                    "mc_ps", "ci_low", "ci_high", "within_ci", "gap", "chain_ps", "chain_within_ci",
                    "rounded_deflection_ps", "rounded_into_obstacle", "transition_model"},
                   6),
        summary_({"grid_spacing_mm", "subdivision", "states", "total_s", "starts",
                  "within_ci_fraction", "mean_abs_gap", "max_abs_gap", "mean_gap", "noise_floor",
                  "solver_gap", "chain_within_ci_fraction", "position_rounding_gap",
                  "deflection_gap", "rounded_into_obstacle", "transition_model"},
                 6) {}

  Summary check(const Solved& r) {
    const st::SteeringPolicy policy = st::tablePolicy(*r.table);
    st::TrialOptions rounded;
    rounded.deflection_step_rad = r.model->grid().alphaRad();
    Summary sum;
    sum.spacing_mm = r.spacing_m * kMmPerM;
    sum.subdivision = r.subdivision;
    sum.states = r.states;
    sum.total_s = r.build_s + r.stats.seconds;
    double max_gap = 0.0, signed_gap = 0.0, solver = 0.0, position = 0.0, deflection = 0.0;
    double into_obstacle = 0.0, chain_within = 0.0;
    for (const auto& pose : starts_) {
      const double predicted = r.table->lookup(pose).probability_of_success;
      const st::MonteCarloResult mc =
          st::runMonteCarlo(world_, pose, policy, kMonteCarloTrials, kMonteCarloSeed, 2);
      seconds_ += mc.seconds;
      trials_ += mc.trials;
      if (predicted < kTrivialPs && mc.rate() < kTrivialPs) {
        continue;
      }
      const st::MonteCarloResult mc_rounded =
          st::runMonteCarlo(world_, pose, policy, kMonteCarloTrials, kMonteCarloSeed, 2, rounded);
      const st::ChainResult chain =
          st::runDiscreteChain(*r.model, *r.table, pose, kMonteCarloTrials, kMonteCarloSeed);
      const st::Interval ci = mc.interval();
      const double gap = predicted - mc.rate();
      const double into = double(chain.rounded_into_obstacle) / double(chain.trials);
      ++sum.starts;
      sum.within += ci.contains(predicted) ? 1.0 : 0.0;
      sum.mean_abs_gap += std::abs(gap);
      sum.noise_floor += noiseFloor(predicted, mc.trials);
      max_gap = std::max(max_gap, std::abs(gap));
      signed_gap += gap;
      solver += std::abs(predicted - chain.rate());
      chain_within += chain.interval().contains(predicted) ? 1.0 : 0.0;
      position += std::abs(chain.rate() - mc_rounded.rate());
      deflection += std::abs(mc_rounded.rate() - mc.rate());
      into_obstacle += into;
      per_start_.addRow({sum.spacing_mm, double(r.subdivision), pose.p_SceneTip.y() * kMmPerM,
                         pose.theta_rad * kDegPerRad, st::toString(pose.bevel), predicted,
                         mc.rate(), ci.low, ci.high, ci.contains(predicted) ? 1.0 : 0.0, gap,
                         chain.rate(), chain.interval().contains(predicted) ? 1.0 : 0.0,
                         mc_rounded.rate(), into, st::toString(r.transition)});
    }
    const double n = std::max(1, sum.starts);
    sum.within = sum.starts > 0 ? sum.within / n : 1.0;
    sum.mean_abs_gap /= n;
    sum.noise_floor /= n;
    summary_.addRow({sum.spacing_mm, double(r.subdivision), double(r.states), sum.total_s,
                     double(sum.starts), sum.within, sum.mean_abs_gap, max_gap, signed_gap / n,
                     sum.noise_floor, solver / n, chain_within / n, position / n, deflection / n,
                     into_obstacle / n, st::toString(r.transition)});
    summaries_.push_back(sum);
    std::cout << "truth check, " << st::toString(r.transition) << ", Delta " << sum.spacing_mm
              << " mm, s = " << r.subdivision << ", " << sum.total_s
              << " s: " << sum.within * sum.starts << " of " << sum.starts
              << " start states within the 95 % interval, mean |gap| " << sum.mean_abs_gap
              << " (noise floor " << sum.noise_floor << "; solver " << solver / n
              << ", position rounding " << position / n << ", deflection quantisation "
              << deflection / n << ")\n"
              << std::flush;
    return sum;
  }

  double withinFraction(double spacing_m, int subdivision) const {
    for (const Summary& s : summaries_) {
      if (std::abs(s.spacing_mm - spacing_m * kMmPerM) < 1e-9 && s.subdivision == subdivision) {
        return s.within;
      }
    }
    throw std::runtime_error("truth check: no run at that spacing and subdivision");
  }
  /// The model whose predictions fall in the interval most often (then: smaller mean gap).
  Summary best() const {
    Summary b = summaries_.front();
    for (const Summary& s : summaries_) {
      if (s.within > b.within || (s.within == b.within && s.mean_abs_gap < b.mean_abs_gap)) {
        b = s;
      }
    }
    return b;
  }
  /// The summary of the last check.
  Summary last() const { return summaries_.back(); }
  double seconds() const { return seconds_; }
  std::int64_t trials() const { return trials_; }
  std::string summaryText() const { return summary_.toText(); }
  /// Writes PREFIXtruth_check.csv and PREFIXtruth_gap.csv.
  void writeCsv(const std::string& prefix) const {
    per_start_.writeCsv(prefix + "truth_check.csv");
    summary_.writeCsv(prefix + "truth_gap.csv");
  }

private:
  const st::ContinuousWorkspace& world_;
  std::vector<st::TipPose> starts_;
  ng::report::Table per_start_;
  ng::report::Table summary_;
  std::vector<Summary> summaries_;
  double seconds_ = 0.0;
  std::int64_t trials_ = 0;
};

// ---- the model chosen by ps_tolerance, checked against Monte Carlo ----

/// The truth check's start states on a scene's entry line: heights at the given fractions of
/// the start range, angles -18, 0, 18 degrees, both bevels.
std::vector<st::TipPose> entryStarts(const st::SteeringProblem& problem,
                                     const st::StartOptions& start,
                                     const std::vector<double>& y_mm) {
  std::vector<double> heights_m;
  for (double y : y_mm) {
    heights_m.push_back(y / kMmPerM);
  }
  return st::entryLineStarts(problem, start, heights_m);
}

/// The scene's model as steering_policy chooses it (ps_tolerance), solved once more for a median
/// time, and every rung of the ladder checked against Monte Carlo: its own error estimate beside
/// the measured mean gap (selection.csv).
struct Selection {
  st::SteeringProblem chosen;  ///< ps_tolerance 0, the chosen grid
  double estimated_error = NAN;
  double selection_s = 0.0;  ///< every rung built and solved [s]
  int rungs = 0;
};

Selection selectModel(const std::string& scene_name, const st::SteeringProblem& problem,
                      const st::StartOptions& start, TruthCheck* truth, ng::report::Table& table) {
  st::SelectionOptions options;
  options.start = start;
  ng::Result<st::PolicySource> r = st::solveOrLoad(problem, "", "", options);
  if (!r) {
    throw std::runtime_error(r.status().toString());
  }
  Selection out;
  out.chosen = r.value().model->problem();
  out.chosen.ps_tolerance = 0.0;
  out.estimated_error = r.value().estimated_error;
  out.selection_s = r.value().seconds;
  out.rungs = static_cast<int>(r.value().ladder.size());
  std::cout << "ps_tolerance " << problem.ps_tolerance << " on " << scene_name << ": "
            << r.value().description() << "\n"
            << std::flush;
  for (const st::ModelRung& rung : r.value().ladder) {
    double within = NAN, gap = NAN;
    if (truth != nullptr) {
      const TruthCheck::Summary sum = truth->check(
          solveAt(problem, rung.grid_spacing_m, 2, 1e-3, start,
                  problem.params.orientation_subdivision, 1, problem.params.transition_model));
      within = sum.within;
      gap = sum.mean_abs_gap;
    }
    table.addRow({scene_name, rung.grid_spacing_m * kMmPerM, double(rung.states), rung.build_s,
                  rung.solve_s, rung.estimated_error, gap, within,
                  rung.grid_spacing_m == out.chosen.params.grid_spacing_m ? 1.0 : 0.0});
  }
  return out;
}

// ---- adaptation experiment ----

/// Closed-loop trials per arm and world sigma (>= 300). The arms are paired (trial i
/// of every arm uses the seed kAdaptSeed + i), so their difference is measured trial by trial;
/// at 2x sigma knowing sigma is worth about 0.01-0.02 of P_s on these scenes, which 20,000 pairs
/// resolve (paired standard error ~0.003) and 300 do not; the arms' own Wilson intervals (half
/// width ~0.0042 at P_s 0.35) are apart at a 0.01 difference only from about 35,000 trials.
constexpr int kAdaptTrials = 50000;
/// Seed of trial i of every arm: kAdaptSeed + i (the arms see the same deflection streams).
constexpr std::uint64_t kAdaptSeed = 2100;
/// Trials after which sigma_estimate_error_pct is read.
constexpr int kEstimateAfterTrials = 10;
/// sigma_trajectory.csv: every trial up to this one, then every kTrajectoryEvery-th.
constexpr int kTrajectoryDense = 100;
constexpr int kTrajectoryEvery = 100;
/// False re-solves at 1x: adaptive runs, each of kFalseRunTrials trials from its own seeds.
constexpr int kFalseRuns = 200;
constexpr int kFalseRunTrials = 300;
constexpr std::uint64_t kFalseSeed = 210000;

struct Arm {
  std::string scene;
  std::string arm;     ///< fixed | adaptive | oracle
  double scale = 1.0;  ///< world sigma / scene sigma
  std::int64_t successes = 0;
  std::int64_t trials = 0;
  std::vector<bool> outcomes;  ///< per trial, for the paired differences
  st::Interval ci;
  int resolves = 0;
  double resolve_s = 0.0;          ///< summed re-solve time [s]
  double sigma_i_error_pct = NAN;  ///< |sigma_i estimate - truth| / truth after 10 trials
  double sigma_r_error_pct = NAN;
  st::SigmaEstimate final_insert;  ///< after every trial (the estimator's bias shows here)
  double true_sigma_i = 0.0;
};

std::shared_ptr<const st::PolicySource> solvedFor(const st::SteeringProblem& p) {
  st::SteeringProblem fixed = p;
  fixed.ps_tolerance = 0.0;
  ng::Result<st::PolicySource> r = st::solveOrLoad(fixed, "", "", st::SelectionOptions{});
  if (!r) {
    throw std::runtime_error(r.status().toString());
  }
  return std::make_shared<const st::PolicySource>(std::move(r.value()));
}

/// One closed-loop trial of the table in use from its best start; the adaptive policy observes
/// every step, the one that stopped at a contact included (by its chord).
st::Trial adaptiveTrial(const st::ContinuousWorkspace& world, st::AdaptivePolicy& policy,
                        const st::StartOptions& start, std::uint64_t seed) {
  const std::shared_ptr<const st::PolicySource> table = policy.current();
  const st::BestStart best = table->table->bestStart(start);
  const st::SteeringPolicy control = [&table](const st::TipPose& pose, int) {
    return table->table->lookup(pose).control;
  };
  st::TrialOptions trial_options;
  trial_options.record_path = true;
  const st::Trial t = st::simulateTrial(world, best.best.pose, control, seed, trial_options);
  const bool stopped =
      t.outcome == st::TrialOutcome::kHitObstacle || t.outcome == st::TrialOutcome::kLeftWorkspace;
  const std::size_t whole = t.controls.size() - (stopped && !t.controls.empty() ? 1 : 0);
  for (std::size_t j = 0; j < whole; ++j) {
    policy.observe(t.path[j], t.path[j + 1], t.controls[j]);
  }
  if (whole < t.controls.size()) {
    policy.observeStopped(t.path[whole], t.path[whole + 1], t.controls[whole]);
  }
  return t;
}

/// One arm: kAdaptTrials trials in a world whose sigmas are `scale` times the problem's, each
/// from the best start of the table in use; the adaptive arm observes every step of a trial and
/// swaps a re-solved table in before the next trial.
Arm runArm(const std::string& scene_name, const st::SteeringProblem& problem,
           const st::StartOptions& start, double scale, const std::string& arm_name,
           const std::shared_ptr<const st::PolicySource>& assumed,
           const std::shared_ptr<const st::PolicySource>& oracle, ng::report::Table& trajectory) {
  st::SteeringProblem truth = problem;
  truth.params.sigma_insert_rad *= scale;
  truth.params.sigma_flip_rad *= scale;
  const st::ContinuousWorkspace world(truth);
  st::AdaptationOptions options;
  options.adapt = arm_name == "adaptive";
  st::AdaptivePolicy policy(arm_name == "oracle" ? truth : problem,
                            arm_name == "oracle" ? oracle : assumed, options);
  Arm out;
  out.scene = scene_name;
  out.arm = arm_name;
  out.scale = scale;
  out.true_sigma_i = truth.params.sigma_insert_rad;
  for (int i = 0; i < kAdaptTrials; ++i) {
    const st::Trial t = adaptiveTrial(world, policy, start, kAdaptSeed + std::uint64_t(i));
    out.successes += t.success() ? 1 : 0;
    out.outcomes.push_back(t.success());
    ++out.trials;
    policy.waitAndSwap();
    const st::SigmaEstimate ei = policy.estimator().estimate(st::Control::kInsert);
    const st::SigmaEstimate er = policy.estimator().estimate(st::Control::kFlip);
    if (i + 1 == kEstimateAfterTrials) {
      out.sigma_i_error_pct = 100.0 * std::abs(ei.sigma_rad / truth.params.sigma_insert_rad - 1.0);
      out.sigma_r_error_pct =
          er.samples > 0 ? 100.0 * std::abs(er.sigma_rad / truth.params.sigma_flip_rad - 1.0) : NAN;
    }
    if (arm_name == "adaptive" && (i < kTrajectoryDense || (i + 1) % kTrajectoryEvery == 0)) {
      trajectory.addRow({scene_name, scale, double(i + 1), ei.sigma_rad * kDegPerRad,
                         ei.low_rad * kDegPerRad, ei.high_rad * kDegPerRad,
                         er.sigma_rad * kDegPerRad,
                         policy.assumedSigma(st::Control::kInsert) * kDegPerRad,
                         policy.assumedSigma(st::Control::kFlip) * kDegPerRad,
                         truth.params.sigma_insert_rad * kDegPerRad});
    }
  }
  out.final_insert = policy.estimator().estimate(st::Control::kInsert);
  out.ci = st::wilsonInterval(out.successes, out.trials);
  out.resolves = static_cast<int>(policy.resolves().size());
  for (const st::Resolve& r : policy.resolves()) {
    out.resolve_s += r.seconds;
  }
  std::cout << "adaptation, " << scene_name << ", world sigma " << scale << "x, " << arm_name
            << ": " << out.successes << " / " << out.trials << " [" << out.ci.low << ", "
            << out.ci.high << "], " << out.resolves << " re-solves (" << out.resolve_s
            << " s), sigma_i error after " << kEstimateAfterTrials << " trials "
            << out.sigma_i_error_pct << " %, after all " << out.final_insert.sigma_rad * kDegPerRad
            << " deg [" << out.final_insert.low_rad * kDegPerRad << ", "
            << out.final_insert.high_rad * kDegPerRad << "] (truth "
            << out.true_sigma_i * kDegPerRad << ")\n"
            << std::flush;
  return out;
}

/// Fixed-sigma, adaptive and oracle arms at world sigma 0.5x, 1x and 2x the scene's.
std::vector<Arm> adaptationExperiment(const std::string& scene_name, const st::PolicySource& chosen,
                                      const st::StartOptions& start, ng::report::Table& arms,
                                      ng::report::Table& trajectory) {
  const st::SteeringProblem problem = chosen.model->problem();
  const auto assumed = solvedFor(problem);
  std::vector<Arm> out;
  for (double scale : {0.5, 1.0, 2.0}) {
    st::SteeringProblem truth = problem;
    truth.params.sigma_insert_rad *= scale;
    truth.params.sigma_flip_rad *= scale;
    const auto oracle = scale == 1.0 ? assumed : solvedFor(truth);
    for (const char* arm : {"fixed", "adaptive", "oracle"}) {
      out.push_back(runArm(scene_name, problem, start, scale, arm, assumed, oracle, trajectory));
      const Arm& a = out.back();
      arms.addRow({a.scene, a.arm, a.scale, double(a.successes), double(a.trials),
                   double(a.successes) / double(a.trials), a.ci.low, a.ci.high, double(a.resolves),
                   a.resolve_s, a.sigma_i_error_pct, a.sigma_r_error_pct});
    }
  }
  return out;
}

const Arm& findArm(const std::vector<Arm>& arms, const std::string& name, double scale) {
  for (const Arm& a : arms) {
    if (a.arm == name && a.scale == scale) {
      return a;
    }
  }
  throw std::runtime_error("no arm " + name);
}

std::string jsonInterval(const st::Interval& i) {
  return "[" + ng::report::jsonNumber(i.low) + ", " + ng::report::jsonNumber(i.high) + "]";
}

/// The paired differences of one world sigma: success_diff_A_B_<level><suffix> and _ci.
std::string pairedJson(const std::vector<Arm>& arms, double scale, const std::string& level,
                       const std::string& suffix, ng::report::Table& paired) {
  std::ostringstream j;
  const std::pair<const char*, const char*> pairs[] = {
      {"adaptive", "fixed"}, {"oracle", "fixed"}, {"adaptive", "oracle"}};
  for (const auto& [a, b] : pairs) {
    const Arm& arm_a = findArm(arms, a, scale);
    const st::PairedDifference d =
        st::pairedDifference(arm_a.outcomes, findArm(arms, b, scale).outcomes);
    const std::string key = std::string("success_diff_") + a + "_" + b + "_" + level + suffix;
    j << ",\n  \"" << key << "\": " << ng::report::jsonNumber(d.difference) << ",\n  \"" << key
      << "_ci\": " << jsonInterval(d.interval);
    paired.addRow({arm_a.scene, std::string(a) + " - " + b, scale, d.difference, d.interval.low,
                   d.interval.high, double(d.only_a), double(d.only_b), double(d.trials)});
    std::cout << "paired, " << arm_a.scene << ", " << level << ": " << a << " - " << b << " = "
              << d.difference << " [" << d.interval.low << ", " << d.interval.high << "] ("
              << d.only_a << " vs " << d.only_b << " discordant of " << d.trials << ")\n";
  }
  return j.str();
}

/// The adaptation keys of one scene (suffix "" or "_heldout").
std::string adaptationJson(const std::vector<Arm>& arms, const std::string& suffix,
                           ng::report::Table& paired) {
  std::ostringstream j;
  for (double scale : {0.5, 1.0, 2.0}) {
    const std::string level = scale == 0.5 ? "0.5x" : scale == 1.0 ? "1x" : "2x";
    for (const char* arm : {"adaptive", "fixed", "oracle"}) {
      const Arm& a = findArm(arms, arm, scale);
      j << ",\n  \"success_" << arm << "_" << level << suffix
        << "\": " << ng::report::jsonNumber(double(a.successes) / double(a.trials))
        << ",\n  \"success_" << arm << "_" << level << suffix << "_ci\": " << jsonInterval(a.ci);
    }
    j << pairedJson(arms, scale, level, suffix, paired);
  }
  const Arm& adaptive2 = findArm(arms, "adaptive", 2.0);
  const Arm& fixed2 = findArm(arms, "fixed", 2.0);
  const Arm& oracle2 = findArm(arms, "oracle", 2.0);
  const double rate = double(adaptive2.successes) / double(adaptive2.trials);
  const st::PairedDifference vs_fixed = st::pairedDifference(adaptive2.outcomes, fixed2.outcomes);
  const st::PairedDifference vs_oracle = st::pairedDifference(adaptive2.outcomes, oracle2.outcomes);
  const st::SigmaEstimate& fin = adaptive2.final_insert;
  j << ",\n  \"adaptation_trials_per_arm" << suffix << "\": " << adaptive2.trials
    << ",\n  \"adaptive_beats_fixed_2x" << suffix
    << "\": " << (adaptive2.ci.low > fixed2.ci.high ? "true" : "false")
    << ",\n  \"adaptive_beats_fixed_2x_paired" << suffix
    << "\": " << (vs_fixed.interval.low > 0.0 ? "true" : "false")
    << ",\n  \"adaptive_within_oracle_ci_2x" << suffix
    << "\": " << (oracle2.ci.contains(rate) ? "true" : "false")
    << ",\n  \"adaptive_matches_oracle_2x_paired" << suffix
    << "\": " << (vs_oracle.excludesZero() ? "false" : "true") << ",\n  \"resolves_adaptive_2x"
    << suffix << "\": " << adaptive2.resolves << ",\n  \"resolve_s_adaptive_2x" << suffix
    << "\": " << ng::report::jsonNumber(adaptive2.resolve_s) << ",\n  \"sigma_estimate_error_pct"
    << suffix << "\": " << ng::report::jsonNumber(adaptive2.sigma_i_error_pct)
    << ",\n  \"sigma_flip_estimate_error_pct" << suffix
    << "\": " << ng::report::jsonNumber(adaptive2.sigma_r_error_pct)
    << ",\n  \"sigma_final_error_pct_2x" << suffix
    << "\": " << ng::report::jsonNumber(100.0 * (fin.sigma_rad / adaptive2.true_sigma_i - 1.0))
    << ",\n  \"sigma_final_covers_truth_2x" << suffix
    << "\": " << (fin.contains(adaptive2.true_sigma_i) ? "true" : "false");
  return j.str();
}

/// The false re-solve rate at 1x: kFalseRuns adaptive runs of kFalseRunTrials trials each (own
/// seeds) in a world whose sigma is the scene's; a run counts once it asks for any re-solve.
std::string falseResolveJson(const std::string& scene_name, const st::PolicySource& chosen,
                             const st::StartOptions& start, const std::string& suffix) {
  const st::SteeringProblem problem = chosen.model->problem();
  const auto assumed = solvedFor(problem);
  const st::ContinuousWorkspace world(problem);
  std::int64_t runs_with_resolve = 0, steps = 0;
  for (int run = 0; run < kFalseRuns; ++run) {
    st::AdaptivePolicy policy(problem, assumed, st::AdaptationOptions{});
    for (int i = 0; i < kFalseRunTrials && policy.resolves().empty(); ++i) {
      adaptiveTrial(world, policy, start,
                    kFalseSeed + std::uint64_t(run) * kFalseRunTrials + std::uint64_t(i));
    }
    runs_with_resolve += policy.resolves().empty() ? 0 : 1;
    steps += static_cast<std::int64_t>(policy.trajectory().size());
  }
  const st::Interval ci = st::wilsonInterval(runs_with_resolve, kFalseRuns);
  std::cout << "false re-solves at 1x, " << scene_name << ": " << runs_with_resolve << " of "
            << kFalseRuns << " runs of " << kFalseRunTrials << " trials (" << steps
            << " steps observed)\n";
  std::ostringstream j;
  j << ",\n  \"false_resolve_rate_1x" << suffix
    << "\": " << ng::report::jsonNumber(double(runs_with_resolve) / kFalseRuns)
    << ",\n  \"false_resolve_rate_1x" << suffix << "_ci\": " << jsonInterval(ci)
    << ",\n  \"false_resolve_runs_1x" << suffix << "\": " << kFalseRuns
    << ",\n  \"false_resolve_run_trials_1x" << suffix << "\": " << kFalseRunTrials;
  return j.str();
}

/// The adaptation experiment on the scene and, with its own selection and truth check, on the
/// held-out workspace steering_heldout; writes adaptation.csv, adaptation_paired.csv and
/// sigma_trajectory.csv and returns the JSON keys.
std::string adaptationAndHeldOut(const std::string& scene_name, const Selection& selected,
                                 const st::StartOptions& start, ng::report::Table& selection_table,
                                 const std::string& out_dir) {
  ng::report::Table arms(
      {"scene", "arm", "world_sigma_scale", "successes", "trials", "success", "ci_low", "ci_high",
       "resolves", "resolve_s", "sigma_i_error_pct_10", "sigma_r_error_pct_10"},
      6);
  ng::report::Table paired({"scene", "pair", "world_sigma_scale", "difference", "ci_low", "ci_high",
                            "only_first", "only_second", "trials"},
                           6);
  ng::report::Table trajectory(
      {"scene", "world_sigma_scale", "trial", "sigma_i_deg", "sigma_i_low_deg", "sigma_i_high_deg",
       "sigma_r_deg", "assumed_sigma_i_deg", "assumed_sigma_r_deg", "true_sigma_i_deg"},
      6);
  const auto chosen = solvedFor(selected.chosen);
  const std::vector<Arm> main_arms =
      adaptationExperiment(scene_name, *chosen, start, arms, trajectory);
  std::ostringstream keys;
  keys << adaptationJson(main_arms, "", paired) << falseResolveJson(scene_name, *chosen, start, "");
  // Held out: selection, truth check of the chosen model and the same experiment.
  const ng::scene::Scene held = ng::scene::loadSceneSpec("steering_heldout");
  const st::SteeringProblem held_problem = st::problemFromScene(held);
  const st::StartOptions held_start = st::startOptionsFromScene(held);
  const st::ContinuousWorkspace held_world(held_problem);
  TruthCheck held_truth(held_world,
                        entryStarts(held_problem, held_start, {8.0, 16.0, 25.0, 40.0, 55.0, 70.0}));
  const Selection held_selected =
      selectModel(held.name, held_problem, held_start, &held_truth, selection_table);
  held_truth.writeCsv(out_dir + "/heldout_");
  const TruthCheck::Summary held_default = held_truth.last();
  const auto held_chosen = solvedFor(held_selected.chosen);
  const std::vector<Arm> held_arms =
      adaptationExperiment(held.name, *held_chosen, held_start, arms, trajectory);
  keys << adaptationJson(held_arms, "_heldout", paired)
       << falseResolveJson(held.name, *held_chosen, held_start, "_heldout")
       << ",\n  \"mc_within_ci_fraction_default_heldout\": "
       << ng::report::jsonNumber(held_default.within)
       << ",\n  \"ps_mean_abs_gap_default_heldout\": "
       << ng::report::jsonNumber(held_default.mean_abs_gap)
       << ",\n  \"estimated_error_default_heldout\": "
       << ng::report::jsonNumber(held_selected.estimated_error)
       << ",\n  \"grid_spacing_mm_default_heldout\": "
       << ng::report::jsonNumber(held_selected.chosen.params.grid_spacing_m * kMmPerM);
  arms.writeCsv(out_dir + "/adaptation.csv");
  paired.writeCsv(out_dir + "/adaptation_paired.csv");
  trajectory.writeCsv(out_dir + "/sigma_trajectory.csv");
  std::cout << arms.toText() << paired.toText();
  return keys.str();
}

/// Epsilon against the P_s error of the dissertation's 800k model (speed against error):
/// epsilon.csv. Returns the model (its hash names the table file).
std::unique_ptr<st::SteeringModel> epsilonSweep(const st::SteeringProblem& problem,
                                                const st::StartOptions& start, bool quick,
                                                const std::string& out_dir) {
  st::SteeringProblem p800k = problem;  // the dissertation's model, as run800k was solved
  p800k.params.grid_spacing_m = kSpacing800k_m;
  p800k.params.orientation_subdivision = 1;
  p800k.params.transition_model = st::TransitionModel::kRounded;
  auto model800k = std::make_unique<st::SteeringModel>(p800k, 2);
  const double reference_epsilon = quick ? 1e-6 : 1e-7;
  st::SolverOptions tight;
  tight.epsilon = reference_epsilon;
  const st::PolicyTable reference = st::solveValueIteration(*model800k, tight);
  const std::vector<double> epsilons = quick ? std::vector<double>{1e-2, 1e-3, 1e-4}
                                             : std::vector<double>{1e-2, 1e-3, 1e-4, 1e-5, 1e-6};
  ng::report::Table eps_table(
      {"epsilon", "sweeps", "solve_s", "max_value_error", "best_ps", "policy_agreement"}, 6);
  for (double eps : epsilons) {
    st::SolverOptions o;
    o.epsilon = eps;
    st::SolveStats s;
    const st::PolicyTable t = st::solveValueIteration(*model800k, o, &s);
    double max_err = 0.0;
    std::int64_t same = 0, free_states = 0;
    for (std::int64_t i = 0; i < t.grid().numStates(); ++i) {
      max_err = std::max(max_err, double(std::abs(t.value(i) - reference.value(i))));
      if (t.cell(i / (2 * t.grid().nc)) == st::Cell::kFree && reference.value(i) > 0.0f) {
        ++free_states;
        same += t.control(i) == reference.control(i) ? 1 : 0;
      }
    }
    eps_table.addRow({eps, double(s.sweeps), s.seconds, std::max(1e-9, max_err),
                      double(t.bestStart(start).best.probability_of_success),
                      free_states > 0 ? double(same) / double(free_states) : 1.0});
  }
  eps_table.writeCsv(out_dir + "/epsilon.csv");
  std::cout << eps_table.toText();

  return model800k;
}

/// Mean O(1) look-up time over random continuous poses [us].
double lookupMicroseconds(const st::PolicyTable& table, const st::SteeringProblem& problem) {
  std::mt19937 rng(kLookupSeed);
  std::uniform_real_distribution<double> ux(problem.workspace_min.x(), problem.workspace_max.x());
  std::uniform_real_distribution<double> uy(problem.workspace_min.y(), problem.workspace_max.y());
  std::uniform_real_distribution<double> ut(-kPi, kPi);
  std::vector<st::TipPose> poses(kLookups);
  for (auto& pose : poses) {
    pose.p_SceneTip = st::Point2(ux(rng), uy(rng));
    pose.theta_rad = ut(rng);
    pose.bevel = rng() % 2 ? st::Bevel::kRight : st::Bevel::kLeft;
  }
  double checksum = 0.0;
  int flips = 0;
  const auto tl = std::chrono::steady_clock::now();
  for (const auto& pose : poses) {
    const st::ControlLookup l = table.lookup(pose);
    checksum += l.probability_of_success;
    flips += l.control == st::Control::kFlip ? 1 : 0;
  }
  const double lookup_us = secondsSince(tl) / kLookups * 1e6;
  std::cout << "lookup: " << lookup_us << " us (checksum " << checksum << ", flips " << flips
            << ")\n";

  return lookup_us;
}

struct TableFile {
  double save_s = 0.0;
  double load_s = 0.0;
  double mb = 0.0;
};

/// Saves, loads and measures the table file (then removes it: a report holds figures).
TableFile tableFile(const st::PolicyTable& table, std::uint64_t hash, const std::string& out_dir) {
  const std::string table_path = out_dir + "/steering_800k.table";
  const auto ts = std::chrono::steady_clock::now();
  table.save(table_path);
  const double save_s = secondsSince(ts);
  st::LoadStatus load_status;
  const auto tload = std::chrono::steady_clock::now();
  const auto loaded = st::PolicyTable::load(table_path, hash, load_status);
  const double load_s = secondsSince(tload);
  if (!loaded)
    throw std::runtime_error(load_status.toString());
  std::FILE* f = std::fopen(table_path.c_str(), "rb");
  double table_mb = 0.0;
  if (f != nullptr) {
    std::fseek(f, 0, SEEK_END);
    table_mb = static_cast<double>(std::ftell(f)) / (1024.0 * 1024.0);
    std::fclose(f);
  }
  std::remove(table_path.c_str());  // a report folder holds figures, not 4 MB binaries

  return {save_s, load_s, table_mb};
}

/// The start surface of figure 5.7 (start_surface.csv) and its slices (start_slices.csv).
void startSurface(const st::PolicyTable& table, const st::StartOptions& start, st::Bevel bevel,
                  const std::string& out_dir) {
  ng::report::Table surface({"bevel", "y_mm", "theta_deg", "ps"}, 6);
  ng::report::Table slices({"theta", "y_mm", "ps"}, 6);
  const std::vector<int> slice_deg = {-45, -18, 0, 18, 45};
  for (const auto& c : table.startCandidates(start)) {
    const double theta_deg = c.pose.theta_rad * kDegPerRad;
    surface.addRow({st::toString(c.pose.bevel), c.pose.p_SceneTip.y() * kMmPerM, theta_deg,
                    double(c.probability_of_success)});
    for (int d : slice_deg) {
      if (c.pose.bevel == bevel && std::abs(theta_deg - d) < 1e-6) {
        slices.addRow({std::to_string(d) + " deg", c.pose.p_SceneTip.y() * kMmPerM,
                       double(c.probability_of_success)});
      }
    }
  }
  surface.writeCsv(out_dir + "/start_surface.csv");
  slices.writeCsv(out_dir + "/start_slices.csv");
}

struct Scaling {
  std::vector<Solved> runs;  ///< Delta 4, 2, 1 mm (and 0.5, 0.25 mm unless quick), 2 threads
  Solved single;             ///< 1 mm, one thread
  Solved r25;                ///< 1 mm, r = 2.5 cm
  ng::report::Table scaling{{"grid_spacing_mm", "states", "transitions_max", "build_s", "solve_s",
                             "total_s", "sweeps", "converged", "peak_mb", "best_ps", "threads"},
                            6};
};

/// The dissertation's model at several grid spacings: states against time and memory
/// (steering.csv).
Scaling scalingRuns(const st::SteeringProblem& problem, const st::StartOptions& start, bool quick,
                    const std::string& out_dir) {
  Scaling out;
  std::vector<Solved>& runs = out.runs;
  ng::report::Table& scaling = out.scaling;
  const auto record = [&scaling](const Solved& r, int threads) {
    scaling.addRow({r.spacing_m * kMmPerM, double(r.states), double(r.transitions), r.build_s,
                    r.stats.seconds, r.build_s + r.stats.seconds, double(r.stats.sweeps),
                    r.stats.converged ? 1.0 : 0.0, r.peak_mb,
                    double(r.best.best.probability_of_success), double(threads)});
    std::cout << "Delta " << r.spacing_m * kMmPerM << " mm, " << threads
              << " thread(s): " << r.states << " states, build " << r.build_s << " s, solve "
              << r.stats.seconds << " s (" << r.stats.sweeps << " sweeps), peak " << r.peak_mb
              << " MB, " << r.best.toString() << "\n"
              << std::flush;
  };
  // ---- states vs time and memory (increasing size, so ru_maxrss belongs to the last solve) ----
  // 0.5 mm (3.2 M states) is the finer reference for the P_s error; it runs after the one-
  // thread 800k solve so that ru_maxrss of that solve is still its own.
  const std::vector<double> spacings_m = {4e-3, 2e-3, kSpacing800k_m};
  for (double spacing : spacings_m) {
    runs.push_back(solveAt(problem, spacing, 2, 1e-3, start));
    record(runs.back(), 2);
  }

  // ---- the dissertation's other 800,000-state problems (5.5: r = 2.5 cm, delta = 0.393 cm) ----
  st::SteeringProblem r25 = problem;
  r25.params.radius_m = 0.025;
  Solved& solved_r25 = out.r25 = solveAt(r25, kSpacing800k_m, 2, 1e-3, start);
  std::cout << "r = 25 mm: " << solved_r25.states << " states, build " << solved_r25.build_s
            << " s, solve " << solved_r25.stats.seconds << " s (" << solved_r25.stats.sweeps
            << " sweeps), " << solved_r25.best.toString() << "\n"
            << std::flush;

  // ---- one thread at 800k ----
  Solved& single = out.single = solveAt(problem, kSpacing800k_m, 1, 1e-3, start);
  record(single, 1);
  for (double fine_m : quick ? std::vector<double>{} : std::vector<double>{0.5e-3, 0.25e-3}) {
    runs.push_back(solveAt(problem, fine_m, 2, 1e-3, start));
    record(runs.back(), 2);
  }
  scaling.writeCsv(out_dir + "/steering.csv");
  return out;
}

/// The 800k solve's convergence (convergence.csv) and P_s at its best start against the grid
/// spacing (resolution.csv); returns P_s there on the finest grid.
double convergenceAndResolution(const std::vector<Solved>& runs, const Solved& run800k,
                                const std::string& out_dir) {
  ng::report::Table convergence({"sweep", "max_change"}, 6);
  for (std::size_t i = 0; i < run800k.stats.max_change_per_sweep.size(); ++i) {
    convergence.addRow({double(i + 1), std::max(1e-12, run800k.stats.max_change_per_sweep[i])});
  }
  convergence.writeCsv(out_dir + "/convergence.csv");

  // ---- P_s at one start pose (the 1 mm best start) against the grid spacing ----
  const st::TipPose reference_start = run800k.best.best.pose;
  const Solved& finest = runs.back();
  const double ps_finest = finest.table->lookup(reference_start).probability_of_success;
  ng::report::Table resolution(
      {"grid_spacing_mm", "states", "total_s", "ps_reference_start", "ps_error_vs_finest"}, 6);
  for (const auto& r : runs) {
    const double ps = r.table->lookup(reference_start).probability_of_success;
    resolution.addRow({r.spacing_m * kMmPerM, double(r.states), r.build_s + r.stats.seconds, ps,
                       std::abs(ps - ps_finest)});
  }
  resolution.writeCsv(out_dir + "/resolution.csv");
  std::cout << resolution.toText();
  return ps_finest;
}

struct Baseline {
  st::ShortestPath sp;
  st::MonteCarloResult sp_open, sp_closed;
};

/// The shortest-path baselines against the MDP from the same start (baseline.csv).
Baseline shortestPathBaseline(const st::ContinuousWorkspace& world,
                              const st::SteeringProblem& problem, const st::TipPose& start_pose,
                              const st::MonteCarloResult& mdp_mc, const std::string& out_dir) {
  Baseline out;
  // Open loop: the planned controls replayed under the same uncertainty. Closed loop: the
  // shortest path re-planned after every imaged step, as a steps-to-go table on the same grid.
  st::ShortestPathOptions sp_options;
  sp_options.max_iterations = 100000;  // with the seed: the same plan in every run
  sp_options.time_limit_s = 30.0;
  out.sp = st::planShortestPath(world, start_pose, sp_options);
  std::cout << "shortest path: " << out.sp.toString() << "\n" << std::flush;
  st::SteeringProblem sp_problem = problem;
  sp_problem.params.grid_spacing_m = kSpacing800k_m;
  const st::ShortestPathTable sp_table = st::ShortestPathTable::fromProblem(sp_problem, 2);
  ng::report::Table baseline({"policy", "ps", "ci_low", "ci_high", "mean_steps", "mean_flips"}, 6);
  auto addBaseline = [&](const std::string& name, const st::MonteCarloResult& r) {
    baseline.addRow(
        {name, r.rate(), r.interval().low, r.interval().high, r.mean_steps, r.mean_flips});
  };
  addBaseline("mdp", mdp_mc);
  if (out.sp.found) {
    out.sp_open = st::runMonteCarlo(world, start_pose, st::openLoopPolicy(out.sp.controls),
                                    kMonteCarloTrials, kMonteCarloSeed, 2);
    addBaseline("shortest_path_open_loop", out.sp_open);
  }
  out.sp_closed = st::runMonteCarlo(world, start_pose, st::shortestPathPolicy(sp_table),
                                    kMonteCarloTrials, kMonteCarloSeed, 2);
  addBaseline("shortest_path_closed_loop", out.sp_closed);
  baseline.writeCsv(out_dir + "/baseline.csv");
  std::cout << baseline.toText();
  return out;
}

/// plot.json: the figures scripts/plot_bench.py draws from the CSVs.
void writePlotJson(const std::string& out_dir) {
  ng::report::writeTextFile(
      out_dir + "/plot.json",
      R"json([{"csv": "steering.csv", "x": "states", "y": "total_s", "group": "threads", "logx": true, "logy": true,
  "annotate": "grid_spacing_mm", "title": "MDP build + solve time vs number of states (group: threads)", "png": "solve_time.png"},
 {"csv": "steering.csv", "x": "states", "y": "peak_mb", "group": "threads", "logx": true, "annotate": "grid_spacing_mm",
  "title": "Peak resident memory vs number of states", "png": "memory.png"},
 {"csv": "convergence.csv", "x": "sweep", "y": "max_change", "logy": true,
  "title": "Gauss-Seidel value iteration, 800k states: max change per sweep", "png": "convergence.png"},
 {"csv": "epsilon.csv", "x": "solve_s", "y": "max_value_error", "logy": true, "annotate": "epsilon",
  "title": "Convergence threshold: solve time vs max P_s error (800k states)", "png": "epsilon.png"},
 {"csv": "resolution.csv", "x": "total_s", "y": "ps_error_vs_finest", "logx": true, "annotate": "grid_spacing_mm",
  "points": true, "title": "Grid spacing: time vs P_s error at the 1 mm best start (vs finest grid)", "png": "resolution.png"},
 {"csv": "truth_gap.csv", "x": "grid_spacing_mm", "y": "mean_abs_gap", "group": "subdivision", "logx": true, "annotate": "within_ci_fraction",
  "title": "Truth check by Delta and s (label: fraction in 95 % CI)", "png": "truth_gap.png"},
 {"csv": "truth_gap.csv", "x": "total_s", "y": "mean_abs_gap", "group": "subdivision", "logx": true, "annotate": "grid_spacing_mm",
  "title": "Speed against error by s (label: Delta mm)", "png": "truth_tradeoff.png"},
 {"csv": "truth_check.csv", "x": "predicted_ps", "y": "mc_ps", "group": "grid_spacing_mm", "filter": {"subdivision": "1"}, "points": true,
  "title": "Predicted P_s vs Monte Carlo, 10,000 trials per start (s = 1)", "png": "truth_check.png"},
 {"csv": "baseline.csv", "x": "mean_steps", "y": "ps", "group": "policy", "points": true,
  "title": "P_s from the best start (Monte Carlo, 10,000 trials): MDP vs shortest path", "png": "baseline.png"},
 {"csv": "selection.csv", "x": "estimated_error", "y": "mc_mean_abs_gap", "group": "scene", "points": true, "annotate": "grid_spacing_mm",
  "title": "ps_tolerance ladder: the solver's error estimate vs the Monte Carlo gap (label: Delta mm)", "png": "selection.png"},
 {"csv": "adaptation.csv", "x": "world_sigma_scale", "y": "success", "group": "arm", "points": true,
  "title": "50,000 paired closed-loop trials per arm (both scenes)", "png": "adaptation.png"},
 {"csv": "adaptation_paired.csv", "x": "world_sigma_scale", "y": "difference", "group": "pair", "points": true,
  "title": "Paired success differences, common random numbers (both scenes)", "png": "adaptation_paired.png"},
 {"csv": "sigma_trajectory.csv", "x": "trial", "y": "sigma_i_deg", "group": "world_sigma_scale",
  "title": "Adaptive arm: learned sigma_i after each trial", "png": "sigma_trajectory.png"},
 {"csv": "truth_decision.csv", "x": "predicted_ps", "y": "mc_ps", "group": "group", "points": true,
  "title": "Predicted P_s vs Monte Carlo where the start is chosen (scene and held out)", "png": "truth_decision.png"},
 {"csv": "start_slices.csv", "x": "y_mm", "y": "ps", "group": "theta",
  "title": "P_s of start states on the entry line (figure 5.7 slices, best bevel)", "png": "start_surface.png"}])json");
}

/// The truth check of every grid of `runs`, of the scene's chosen model (`default_out`), of the
/// interpolated model at s = 3 and (unless quick) of finer models; writes its CSVs.
TruthCheck truthChecks(const st::ContinuousWorkspace& world, const st::SteeringProblem& problem,
                       const st::StartOptions& start, const std::vector<Solved>& runs,
                       const Solved& run800k, const Solved& scene_model, bool quick,
                       const std::string& out_dir, TruthCheck::Summary& default_out) {
  // ---- truth check: predicted P_s against the continuous needle (Monte Carlo) ----
  // Start states: a fixed set on the entry line (heights x angles x bevels) plus the 1 mm best
  // start; the policy of each grid drives the continuous needle (exact arcs, continuous
  // deflections) from the same start states, at every grid spacing and, finer than 5.4.2,
  // with the orientation subdivided s = 2 and 4 times.
  std::vector<st::TipPose> mc_starts = entryStarts(problem, start, kTruthHeights_mm);
  mc_starts.push_back(run800k.best.best.pose);
  TruthCheck truth(world, mc_starts);
  for (const auto& r : runs) {
    truth.check(r);
  }
  default_out = truth.check(scene_model);
  for (const auto& [spacing, subdivision] :
       std::vector<std::pair<double, int>>{{1e-3, 3}, {0.7e-3, 3}, {0.5e-3, 3}}) {
    truth.check(solveAt(problem, spacing, 2, 1e-3, start, subdivision, 1,
                        st::TransitionModel::kInterpolated));
  }
  if (!quick) {
    // Finer models, solved once each and dropped after their check (memory).
    const std::vector<std::pair<double, int>> finer = {{0.125e-3, 1}, {1e-3, 2},     {0.5e-3, 2},
                                                       {0.25e-3, 2},  {0.125e-3, 2}, {1e-3, 4},
                                                       {0.5e-3, 4},   {0.25e-3, 4}};
    for (const auto& [spacing, subdivision] : finer) {
      truth.check(solveAt(problem, spacing, 2, 1e-3, start, subdivision, 1));
    }
  }
  truth.writeCsv(out_dir + "/");
  return truth;
}

/// The keys of the scene's chosen model: its truth check, solve time and selection.
std::string defaultModelJson(const Solved& scene_model, const TruthCheck::Summary& truth_default,
                             const st::SteeringProblem& problem, const Selection& selected) {
  std::ostringstream json;
  json << ",\n  \"transition_model_default\": \"" << st::toString(scene_model.transition) << "\""
       << ",\n  \"grid_spacing_mm_default\": "
       << ng::report::jsonNumber(scene_model.spacing_m * kMmPerM)
       << ",\n  \"subdivision_default\": " << scene_model.subdivision
       << ",\n  \"states_default\": " << scene_model.states
       << ",\n  \"mc_within_ci_fraction_default\": " << ng::report::jsonNumber(truth_default.within)
       << ",\n  \"ps_mean_abs_gap_default\": " << ng::report::jsonNumber(truth_default.mean_abs_gap)
       << ",\n  \"noise_floor_default\": " << ng::report::jsonNumber(truth_default.noise_floor)
       << ",\n  \"solve_s_default\": " << ng::report::jsonNumber(scene_model.fastest_s)
       << ",\n  \"solve_s_default_median\": " << ng::report::jsonNumber(scene_model.stats.seconds)
       << ",\n  \"solve_repeats_default\": " << kDefaultSolveRepeats
       << ",\n  \"build_s_default\": " << ng::report::jsonNumber(scene_model.build_s)
       << ",\n  \"peak_mb_default\": " << ng::report::jsonNumber(scene_model.peak_mb)
       << ",\n  \"ps_tolerance_default\": " << ng::report::jsonNumber(problem.ps_tolerance)
       << ",\n  \"estimated_error_default\": " << ng::report::jsonNumber(selected.estimated_error)
       << ",\n  \"selection_s_default\": " << ng::report::jsonNumber(selected.selection_s)
       << ",\n  \"selection_models_default\": " << selected.rungs;
  return json.str();
}

/// One line each: the scene's chosen model and the scene's needle.
void printSceneModel(const std::string& scene_name, const st::SteeringProblem& problem,
                     const Solved& scene_model) {
  std::cout << "scene model (" << st::toString(scene_model.transition) << ", Delta "
            << scene_model.spacing_m * kMmPerM << " mm, s = " << scene_model.subdivision
            << "): " << scene_model.states << " states, build " << scene_model.build_s
            << " s, solve " << scene_model.stats.seconds << " s (median; fastest "
            << scene_model.fastest_s << " s), peak " << scene_model.peak_mb << " MB\n"
            << "bench_steering: scene " << scene_name
            << ", r = " << problem.params.radius_m * kMmPerM
            << " mm, N_c = " << problem.params.orientations
            << ", sigma_i = " << problem.params.sigma_insert_rad * kDegPerRad
            << " deg, sigma_r = " << problem.params.sigma_flip_rad * kDegPerRad << " deg\n"
            << std::flush;
}

/// The 1 mm (800k) run of `runs`; throws std::runtime_error without one.
const Solved& the800k(const std::vector<Solved>& runs) {
  for (const auto& r : runs) {
    if (std::abs(r.spacing_m - kSpacing800k_m) < 1e-12) {
      return r;
    }
  }
  throw std::runtime_error("no 1 mm run");
}

/// selection.csv's columns: one row per rung of each scene's ps_tolerance ladder.
ng::report::Table selectionTable() {
  return ng::report::Table(
      {"scene", "grid_spacing_mm", "states", "build_s", "solve_s", "estimated_error",
       "mc_mean_abs_gap", "mc_within_ci_fraction", "chosen"},
      6);
}

// ---- the truth check where the decision is made: the chosen start, the 10 best starts and
// starts near every workspace edge and obstacle, each against the continuous needle ----

/// Monte Carlo trials at the chosen start: its gap is the headline, measured against a
/// tolerance of 0.005 - 0.01, so its binomial noise (mean |noise| <= 0.0013) must be well below.
constexpr std::int64_t kChosenStartTrials = 10 * kMonteCarloTrials;
/// Monte Carlo trials per entry-line and near-boundary start (ps_mean_abs_gap_entry,
/// ps_mean_abs_gap_boundary; noise floor <= 0.002, well below a tolerance of 0.005).
constexpr std::int64_t kEntryTrials = 4 * kMonteCarloTrials;
/// Best starts by prediction in the truth check.
constexpr int kTopStarts = 10;
/// Heights of the entry-line starts as fractions of the start range.
const std::vector<double> kEntryFractions = {0.08, 0.2, 0.35, 0.5, 0.65, 0.8, 0.92};

/// A start state of the truth check and the group it belongs to.
struct TruthStart {
  std::string group;  ///< entry | chosen | table_best | top10 | edge | obstacle
  st::TipPose pose;
};

/// The entry-line starts at `fractions` of the start range (within the workspace).
std::vector<double> entryHeights_mm(const st::SteeringProblem& problem,
                                    const st::StartOptions& start,
                                    const std::vector<double>& fractions) {
  const auto [lo, hi] = st::startRange(problem, start);
  std::vector<double> out;
  for (double f : fractions) {
    out.push_back((lo + f * (hi - lo)) * kMmPerM);
  }
  return out;
}

/// Closed-loop trials at the chosen start: the procedure's trial loop (runGuidedTrial) on the
/// robot's simulated needle, ground-truth feedback, with steerable_procedure's deflection streams
/// (~seed 1: trial k uses kTrialSeedStride + k), so its first kLaunchTrials are the trials of
/// `steerable_needle.launch trials:=30`.
constexpr int kClosedLoopTrials = 3000;
constexpr int kLaunchTrials = 30;

struct ClosedLoop {
  std::int64_t trials = 0;
  std::int64_t successes = 0;
  int launch_successes = 0;  ///< of the first kLaunchTrials
  double rate() const { return trials > 0 ? double(successes) / double(trials) : NAN; }
};

ClosedLoop closedLoop(const ng::scene::Scene& scene, const st::SteeringProblem& problem,
                      const st::PolicyTable& table, const st::TipPose& start) {
  ng::robot::SteerableNeedleConfig config;  // as insertion_robot configures it from the scene
  config.start_x_m = scene.steering->start_x_m;
  config.min_height_m = scene.needle.min_height_m;
  config.max_height_m = scene.needle.max_height_m;
  config.sigma_insert_rad = problem.params.sigma_insert_rad;
  config.sigma_flip_rad = problem.params.sigma_flip_rad;
  const ng::robot::EntryPose entry{start.p_SceneTip.y(), start.theta_rad, start.bevel};
  ng::robot::SteerableNeedle needle(st::planarWorkspace(problem), config, entry);
  const double delta_m = 2.0 * kPi * problem.params.radius_m / problem.params.orientations;
  ClosedLoop out;
  std::uint64_t frame_index = 0;
  for (int k = 0; k < kClosedLoopTrials; ++k) {
    const ng::procedures::GuidedTrial trial = ng::procedures::runGuidedTrial(
        needle, entry, delta_m, ng::procedures::SteerableSettings::kTrialSeedStride + k, table,
        nullptr, nullptr, frame_index);
    const bool success = trial.outcome == st::TrialOutcome::kReachedTarget;
    out.successes += success ? 1 : 0;
    out.launch_successes += success && k < kLaunchTrials ? 1 : 0;
    ++out.trials;
  }
  return out;
}

/// The truth check of one scene where its start is chosen: per start its prediction against the
/// continuous needle (same seeds for every start), grouped; rows go to `rows`.
struct DecisionTruth {
  std::string scene;
  double ps_tolerance = 0.0;
  std::string model;  ///< the chosen model's description
  double estimated_error = NAN;
  st::ModelCheck check;               ///< the chosen model's Monte Carlo check in the selection
  double selection_s = 0.0;           ///< the whole ladder [s]
  int selection_models = 0;           ///< models solved by the ladder
  double selection_check_s = 0.0;     ///< of selection_s, the Monte Carlo checks of its rungs [s]
  std::vector<st::ModelRung> ladder;  ///< every rung the selection solved
  double solve_s = 0.0;               ///< the chosen model's solve, fastest of kSolveRepeats [s]
  double verify_s = 0.0;              ///< screening and verifying the start [s]
  st::VerifiedStart chosen;
  st::MonteCarloResult chosen_mc;   ///< kChosenStartTrials at the chosen start
  double gap_table_best = NAN;      ///< |gap| at the table's own best start (5.5's choice)
  double mean_abs_gap_entry = 0.0;  ///< the entry-line starts (ps_mean_abs_gap_default)
  double within_entry = 0.0;
  double noise_floor_entry = 0.0;  ///< mean |gap| binomial noise alone gives there
  double solve_cpu_s = 0.0;        ///< CPU time of the chosen model's fastest solve [s]
  double verify_cpu_s = 0.0;       ///< CPU time of screening and verifying the start [s]
  double mean_abs_gap_top = 0.0, max_abs_gap_top = 0.0;
  double mean_abs_gap_boundary = 0.0, max_abs_gap_boundary = 0.0;
  double noise_floor_boundary = 0.0;  ///< mean |gap| binomial noise alone gives there
  int entry_starts = 0, top_starts = 0, boundary_starts = 0;
  double mc_s = 0.0;
  ClosedLoop closed_loop;  ///< the procedure's closed loop at the chosen start
};

/// Prediction (from the pose itself; the table's rounded look-up beside it in the rows) against
/// Monte Carlo for each start of `starts`; returns the mean |gap| of the
/// non-trivial ones and their count, the largest in max_gap, the fraction inside the interval
/// in within.
double scoreStarts(const st::ContinuousWorkspace& world, const st::PolicyTable& table,
                   const st::ExactPosePrediction& prediction, const std::vector<TruthStart>& starts,
                   std::int64_t trials, const std::string& scene, ng::report::Table& rows,
                   int& count, double& max_gap, double& within, double& noise_floor) {
  const st::SteeringPolicy policy = prediction.policy();
  double sum = 0.0;
  count = 0;
  max_gap = 0.0;
  within = 0.0;
  noise_floor = 0.0;
  for (const TruthStart& s : starts) {
    const double predicted = prediction.predict(s.pose).probability_of_success;
    const st::MonteCarloResult mc =
        st::runMonteCarlo(world, s.pose, policy, trials, kMonteCarloSeed, 2);
    const st::Interval ci = mc.interval();
    rows.addRow({scene, s.group, s.pose.p_SceneTip.x() * kMmPerM, s.pose.p_SceneTip.y() * kMmPerM,
                 s.pose.theta_rad * kDegPerRad, st::toString(s.pose.bevel), predicted, mc.rate(),
                 ci.low, ci.high, ci.contains(predicted) ? 1.0 : 0.0, predicted - mc.rate(),
                 double(mc.trials), double(table.lookup(s.pose).probability_of_success)});
    if (predicted < kTrivialPs && mc.rate() < kTrivialPs) {
      continue;
    }
    ++count;
    noise_floor += noiseFloor(predicted, trials);
    sum += std::abs(predicted - mc.rate());
    max_gap = std::max(max_gap, std::abs(predicted - mc.rate()));
    within += ci.contains(predicted) ? 1.0 : 0.0;
  }
  within = count > 0 ? within / count : NAN;
  noise_floor = count > 0 ? noise_floor / count : NAN;
  return count > 0 ? sum / count : NAN;
}

/// The rungs of the selection's ladder (selection_ladder.csv): what each group of the model check
/// measured against the rung's own estimate, and which rung was chosen.
ng::report::Table ladderRows() {
  return ng::report::Table(
      {"scene", "rung", "transition_model", "grid_mm", "subdivision", "states", "coarsened",
       "estimated_error", "check_gap_entry", "check_gap_top", "check_gap_boundary", "check_trials",
       "check_passed", "check_s", "chosen"},
      6);
}

void addLadderRows(const DecisionTruth& d, ng::report::Table& rows) {
  for (std::size_t i = 0; i < d.ladder.size(); ++i) {
    const st::ModelRung& r = d.ladder[i];
    const bool run = r.check.run;
    rows.addRow({d.scene, double(i), st::toString(r.transition_model), r.grid_spacing_m * kMmPerM,
                 double(r.orientation_subdivision), double(r.states), r.coarsened ? 1.0 : 0.0,
                 r.estimated_error, run ? r.check.gap_entry : NAN, run ? r.check.gap_top : NAN,
                 run ? r.check.gap_boundary : NAN, double(r.check.trials_per_start),
                 run ? (r.check.passed ? 1.0 : 0.0) : NAN, run ? r.check.seconds : 0.0,
                 r.chosen ? 1.0 : 0.0});
  }
}

/// The per-start rows of decisionTruth (truth_decision.csv).
ng::report::Table decisionRows() {
  return ng::report::Table(
      {"scene", "group", "x_mm", "y_mm", "theta_deg", "bevel", "predicted_ps", "mc_ps", "ci_low",
       "ci_high", "within_ci", "gap", "trials", "rounded_ps"},
      6);
}

/// The scene's model as ps_tolerance chooses it, its start screened and verified
/// (verifyBestStart, as steering_policy does), then every truth start scored.
DecisionTruth decisionTruth(const ng::scene::Scene& scene, ng::report::Table& rows) {
  const st::SteeringProblem problem = st::problemFromScene(scene);
  const st::StartOptions start = st::startOptionsFromScene(scene);
  const st::ContinuousWorkspace world(problem);
  DecisionTruth out;
  out.scene = scene.name;
  out.ps_tolerance = problem.ps_tolerance;
  st::SelectionOptions selection;
  selection.start = start;
  ng::Result<st::PolicySource> source = st::solveOrLoad(problem, "", "", selection);
  if (!source) {
    throw std::runtime_error(scene.name + ": " + source.status().toString());
  }
  out.model = source.value().description();
  out.estimated_error = source.value().estimated_error;
  out.check = source.value().check;
  out.selection_s = source.value().seconds;
  out.ladder = source.value().ladder;
  out.selection_models = int(out.ladder.size());
  for (const st::ModelRung& rung : source.value().ladder) {
    out.selection_check_s += rung.check.run ? rung.check.seconds : 0.0;
  }
  const st::SteeringProblem chosen = source.value().model->problem();
  const Solved solved =
      solveAt(chosen, chosen.params.grid_spacing_m, 2, 1e-3, start,
              chosen.params.orientation_subdivision, kSolveRepeats, chosen.params.transition_model);
  out.solve_s = solved.fastest_s;
  const st::PolicyTable& table = *solved.table;
  st::SolverOptions solver;  // once more for its CPU time (both threads' together)
  double c0 = processCpuSeconds();
  st::solveValueIteration(*solved.model, solver);
  out.solve_cpu_s = processCpuSeconds() - c0;
  st::StartVerificationOptions verify;
  verify.tolerance = st::verificationTolerance(problem);
  c0 = processCpuSeconds();
  out.chosen = st::verifyBestStart(world, table, start, verify);
  out.verify_cpu_s = processCpuSeconds() - c0;
  out.verify_s = out.chosen.seconds;
  if (!out.chosen) {
    throw std::runtime_error(scene.name + ": " + out.chosen.message);
  }
  std::cout << scene.name << ": " << out.model << "\n  start " << out.chosen.toString() << " in "
            << out.verify_s << " s (" << out.verify_cpu_s << " s CPU, " << out.chosen.looks
            << " looks)\n";
  for (std::size_t i = 0; i < out.chosen.screened.size(); ++i) {
    const st::ScreenedStart& s = out.chosen.screened[i];
    std::cout << "    screened rank " << i << ": predicted " << s.candidate.probability_of_success
              << ", screen " << s.screen.rate() << " (" << s.screen.trials << " trials)"
              << (s.confirmed ? ", confirmed" : "") << ", score " << s.score << "\n";
  }
  std::cout << std::flush;
  const auto t0 = std::chrono::steady_clock::now();
  out.chosen_mc = st::runMonteCarlo(world, out.chosen.start.pose, st::tablePolicy(table),
                                    kChosenStartTrials, kMonteCarloSeed, 2);
  rows.addRow({scene.name, "chosen", out.chosen.start.pose.p_SceneTip.x() * kMmPerM,
               out.chosen.start.pose.p_SceneTip.y() * kMmPerM,
               out.chosen.start.pose.theta_rad * kDegPerRad,
               st::toString(out.chosen.start.pose.bevel), out.chosen.predicted(),
               out.chosen_mc.rate(), out.chosen_mc.interval().low, out.chosen_mc.interval().high,
               out.chosen_mc.interval().contains(out.chosen.predicted()) ? 1.0 : 0.0,
               out.chosen.predicted() - out.chosen_mc.rate(), double(out.chosen_mc.trials),
               double(table.lookup(out.chosen.start.pose).probability_of_success)});
  std::vector<TruthStart> entry, top, boundary;
  for (const st::TipPose& p :
       entryStarts(problem, start, entryHeights_mm(problem, start, kEntryFractions))) {
    entry.push_back({"entry", p});
  }
  std::vector<st::StartCandidate> all = table.startCandidates(start);
  std::stable_sort(all.begin(), all.end(), [](const auto& a, const auto& b) {
    return a.probability_of_success > b.probability_of_success;
  });
  for (std::size_t i = 0; i < all.size() && i < std::size_t(kTopStarts); ++i) {
    top.push_back({i == 0 ? "table_best" : "top10", all[i].pose});
  }
  for (const st::NearBoundaryStart& b : st::nearBoundaryStarts(start, table, world)) {
    boundary.push_back({b.group, b.pose});
  }
  // Every start is predicted from its own pose (a grid state's pose gives the table's value).
  const st::ExactPosePrediction prediction(*solved.model, table);
  int n = 0;
  double max_gap = 0.0, within = 0.0, noise = 0.0;
  out.mean_abs_gap_entry = scoreStarts(world, table, prediction, entry, kEntryTrials, scene.name,
                                       rows, n, max_gap, within, noise);
  out.entry_starts = n;
  out.within_entry = within;
  out.noise_floor_entry = noise;
  out.mean_abs_gap_top = scoreStarts(world, table, prediction, top, kMonteCarloTrials, scene.name,
                                     rows, n, max_gap, within, noise);
  out.top_starts = n;
  out.max_abs_gap_top = max_gap;
  out.gap_table_best = NAN;
  if (!top.empty()) {
    const double p = table.lookup(top.front().pose).probability_of_success;
    out.gap_table_best =
        std::abs(p - st::runMonteCarlo(world, top.front().pose, st::tablePolicy(table),
                                       kMonteCarloTrials, kMonteCarloSeed, 2)
                         .rate());
  }
  out.mean_abs_gap_boundary = scoreStarts(world, table, prediction, boundary, kEntryTrials,
                                          scene.name, rows, n, max_gap, within, noise);
  out.boundary_starts = n;
  out.max_abs_gap_boundary = max_gap;
  out.noise_floor_boundary = noise;
  out.closed_loop = closedLoop(scene, problem, table, out.chosen.start.pose);
  out.mc_s = secondsSince(t0);
  return out;
}

/// ps_gap_chosen_start: |the P_s the procedure reports at its start - the long Monte Carlo|.
double reportedGap(const DecisionTruth& d) {
  return std::abs(d.chosen.reported() - d.chosen_mc.rate());
}

/// ps_gap_chosen_start, the entry line's and the near-boundary starts' mean |gap| within the
/// scene's tolerance (no near-boundary start with P_s >= 0.01: nothing to miss).
bool targetsMet(const DecisionTruth& d) {
  const double tolerance =
      d.ps_tolerance > 0.0 ? d.ps_tolerance : st::kDefaultVerificationTolerance;
  return reportedGap(d) <= tolerance && d.mean_abs_gap_entry <= tolerance &&
         !(d.mean_abs_gap_boundary > tolerance);
}

/// The JSON keys of one decisionTruth, each name followed by `suffix`.
std::string decisionJson(const DecisionTruth& d, const std::string& suffix) {
  const double p = d.chosen.predicted();
  const double noise = noiseFloor(p, d.chosen_mc.trials);
  std::ostringstream j;
  auto key = [&](const std::string& name, const std::string& value) {
    j << ",\n  \"" << name << suffix << "\": " << value;
  };
  auto num = [](double v) { return ng::report::jsonNumber(v); };
  key("ps_tolerance", num(d.ps_tolerance));
  key("model", "\"" + d.model + "\"");
  key("estimated_error", num(d.estimated_error));
  key("model_check_mean_gap_entry", num(d.check.gap_entry));
  key("model_check_mean_gap_top", num(d.check.gap_top));
  key("model_check_mean_gap_boundary", num(d.check.gap_boundary));
  key("model_check_trials", std::to_string(d.check.trials_per_start));
  key("model_check_passed", d.check.passed ? "true" : "false");
  key("chosen_start_y_mm", num(d.chosen.start.pose.p_SceneTip.y() * kMmPerM));
  key("chosen_start_theta_deg", num(d.chosen.start.pose.theta_rad * kDegPerRad));
  key("chosen_start_bevel", "\"" + st::toString(d.chosen.start.pose.bevel) + "\"");
  key("chosen_start_rank", std::to_string(d.chosen.rank_by_prediction));
  key("chosen_start_confirmed", d.chosen.confirmed ? "true" : "false");
  key("reported_ps_chosen_start", num(d.chosen.reported()));
  key("predicted_ps_chosen_start", num(p));
  key("verified_ps_chosen_start", num(d.chosen.verification.rate()));
  key("verified_ps_chosen_start_ci", jsonInterval(d.chosen.verification.interval()));
  key("verification_trials_chosen_start", std::to_string(d.chosen.verification.trials));
  key("verification_looks_chosen_start", std::to_string(d.chosen.looks));
  key("verification_se_chosen_start", num(d.chosen.standardError()));
  key("mc_ps_chosen_start", num(d.chosen_mc.rate()));
  key("mc_ps_chosen_start_ci", jsonInterval(d.chosen_mc.interval()));
  key("mc_trials_chosen_start", std::to_string(d.chosen_mc.trials));
  key("ps_gap_chosen_start", num(reportedGap(d)));
  key("ps_gap_chosen_start_model", num(std::abs(p - d.chosen_mc.rate())));
  key("noise_floor_chosen_start", num(noise));
  key("ps_gap_table_best_start", num(d.gap_table_best));
  key("ps_mean_abs_gap_entry", num(d.mean_abs_gap_entry));
  key("mc_within_ci_fraction_entry", num(d.within_entry));
  key("noise_floor_entry", num(d.noise_floor_entry));
  key("ps_mean_abs_gap_top10", num(d.mean_abs_gap_top));
  key("ps_max_abs_gap_top10", num(d.max_abs_gap_top));
  key("ps_mean_abs_gap_boundary", num(d.mean_abs_gap_boundary));
  key("ps_max_abs_gap_boundary", num(d.max_abs_gap_boundary));
  key("truth_starts_boundary", std::to_string(d.boundary_starts));
  key("noise_floor_boundary", num(d.noise_floor_boundary));
  key("selection_s", num(d.selection_s));
  key("selection_models", std::to_string(d.selection_models));
  key("selection_check_s", num(d.selection_check_s));
  key("solve_s_chosen_model", num(d.solve_s));
  key("verify_start_s", num(d.verify_s));
  key("verify_start_cpu_s", num(d.verify_cpu_s));
  key("solve_and_verify_s", num(d.solve_s + d.verify_s));
  key("solve_and_verify_cpu_s", num(d.solve_cpu_s + d.verify_cpu_s));
  key("closed_loop_ps_chosen_start", num(d.closed_loop.rate()));
  key("closed_loop_ps_chosen_start_ci",
      jsonInterval(st::wilsonInterval(d.closed_loop.successes, d.closed_loop.trials)));
  key("closed_loop_trials", std::to_string(d.closed_loop.trials));
  key("closed_loop_successes_first30", std::to_string(d.closed_loop.launch_successes));
  key("truth_mc_s", num(d.mc_s));
  key("targets_met", targetsMet(d) ? "true" : "false");
  return j.str();
}

/// --truth-only: decisionTruth of every --scene; summary.json, truth_decision.csv and its plot.
int truthOnly(const ng::report::BenchArgs& args) {
  ng::report::Table rows = decisionRows();
  ng::report::Table ladder = ladderRows();
  std::ostringstream json;
  json << "{\n  \"benchmark\": \"steering\",\n  \"mode\": \"truth_only\"";
  const std::vector<std::string> scenes =
      args.scenes.empty() ? std::vector<std::string>{"steering_workspace"} : args.scenes;
  bool all_met = true;
  for (const std::string& spec : scenes) {
    const ng::scene::Scene scene = ng::scene::loadSceneSpec(spec);
    const std::string suffix = scenes.size() > 1 ? "_" + scene.name : "";
    json << ",\n  \"scene" << suffix << "\": \"" << spec << "\"";
    std::string keys;
    try {
      const DecisionTruth d = decisionTruth(scene, rows);
      keys = decisionJson(d, suffix);
      all_met = all_met && targetsMet(d);
      addLadderRows(d, ladder);
      ladder.writeCsv(args.out_dir + "/selection_ladder.csv");
    } catch (const std::exception& e) {  // e.g. a tolerance refused: recorded, the rest run on
      std::string why = e.what();
      std::replace(why.begin(), why.end(), '"', '\'');
      keys = ",\n  \"refused" + suffix + "\": \"" + why + "\",\n  \"targets_met" + suffix +
             "\": false";
      all_met = false;
      std::cerr << "bench_steering: " << scene.name << ": " << e.what() << "\n";
    }
    json << keys;
    rows.writeCsv(args.out_dir + "/truth_decision.csv");  // after each scene
    std::cout << keys.substr(2) << "\n" << std::flush;
  }
  json << ",\n  \"all_targets_met\": " << (all_met ? "true" : "false") << "\n}\n";
  ng::report::writeTextFile(args.out_dir + "/summary.json", json.str());
  ng::report::writeTextFile(
      args.out_dir + "/plot.json",
      R"json([{"csv": "truth_decision.csv", "x": "predicted_ps", "y": "mc_ps", "group": "group", "points": true,
  "title": "Predicted P_s vs Monte Carlo where the start is chosen (all scenes)", "png": "truth_decision.png"}])json");
  std::cout << (all_met ? "every target met\n" : "some target missed (targets_met)\n");
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  // --truth-only (this tool's own flag): only the truth check where the start is chosen.
  std::vector<char*> rest;
  bool truth_only = false;
  for (int i = 0; i < argc; ++i) {
    if (std::string(argv[i]) == "--truth-only") {
      truth_only = true;
    } else {
      rest.push_back(argv[i]);
    }
  }
  const auto args = ng::report::parseBenchArgs(
      static_cast<int>(rest.size()), rest.data(), "bench_steering",
      "       bench_steering --truth-only --out DIR [--scene SPEC]...\n"
      "  --truth-only: only the truth check where the start is chosen (the chosen start, the 10 "
      "best starts, starts near every edge and obstacle), on every --scene\n");
  if (!args) {
    return 2;
  }
  try {
    if (truth_only) {
      return truthOnly(*args);
    }
    // BenchArgs defaults to the prostate scene, which has no steering section.
    const std::string scene_spec =
        args->scene == "prostate_sagittal" ? "steering_workspace" : args->scene;
    const ng::scene::Scene scene = ng::scene::loadSceneSpec(scene_spec);
    const st::SteeringProblem problem = st::problemFromScene(scene);
    const st::StartOptions start = st::startOptionsFromScene(scene);
    const double baseline_mb = peakMb();
    // ---- the scene's model as ps_tolerance chooses it, first, so that the peak resident memory
    // after it is its own; every rung of the ladder checked against Monte Carlo ----
    const st::ContinuousWorkspace world(problem);
    ng::report::Table selection_table = selectionTable();
    TruthCheck selection_truth(world, entryStarts(problem, start, kTruthHeights_mm));
    const Selection selected =
        selectModel(scene.name, problem, start, &selection_truth, selection_table);
    const Solved scene_model = solveAt(selected.chosen, selected.chosen.params.grid_spacing_m, 2,
                                       1e-3, start, problem.params.orientation_subdivision,
                                       kDefaultSolveRepeats, problem.params.transition_model);
    printSceneModel(scene.name, problem, scene_model);

    Scaling scaled = scalingRuns(problem, start, args->quick, args->out_dir);
    std::vector<Solved>& runs = scaled.runs;
    const Solved& single = scaled.single;
    const Solved& solved_r25 = scaled.r25;
    const ng::report::Table& scaling = scaled.scaling;
    const Solved* run800k = &the800k(runs);

    const double ps_finest = convergenceAndResolution(runs, *run800k, args->out_dir);
    const Solved& finest = runs.back();

    TruthCheck::Summary truth_default;
    const TruthCheck truth = truthChecks(world, problem, start, runs, *run800k, scene_model,
                                         args->quick, args->out_dir, truth_default);
    const double within_800k = truth.withinFraction(kSpacing800k_m, 1);
    selection_truth.writeCsv(args->out_dir + "/selection_");
    const std::string adaptation_keys =
        adaptationAndHeldOut(scene.name, selected, start, selection_table, args->out_dir);
    // The truth where the start is chosen, on the scene and the held-out workspace.
    ng::report::Table decision_rows = decisionRows();
    const std::string decision_keys =
        decisionJson(decisionTruth(scene, decision_rows), "") +
        decisionJson(decisionTruth(ng::scene::loadSceneSpec("steering_heldout"), decision_rows),
                     "_heldout");
    decision_rows.writeCsv(args->out_dir + "/truth_decision.csv");
    selection_table.writeCsv(args->out_dir + "/selection.csv");
    const TruthCheck::Summary truth_best = truth.best();
    const double mc_seconds = truth.seconds();
    const std::int64_t mc_trials_total = truth.trials();
    // P_s measured by Monte Carlo from the best start (the headline mdp_ps).
    const st::MonteCarloResult mdp_mc =
        st::runMonteCarlo(world, run800k->best.best.pose, st::tablePolicy(*run800k->table),
                          kMonteCarloTrials, kMonteCarloSeed, 2);

    const Baseline base =
        shortestPathBaseline(world, problem, run800k->best.best.pose, mdp_mc, args->out_dir);
    const st::ShortestPath& sp = base.sp;
    const st::MonteCarloResult& sp_open = base.sp_open;
    const st::MonteCarloResult& sp_closed = base.sp_closed;

    const std::unique_ptr<st::SteeringModel> model800k =
        epsilonSweep(problem, start, args->quick, args->out_dir);
    const st::PolicyTable& table = *run800k->table;
    const double lookup_us = lookupMicroseconds(table, problem);
    const TableFile file = tableFile(table, model800k->hash(), args->out_dir);
    startSurface(table, start, run800k->best.best.pose.bevel, args->out_dir);

    const st::BestStart& best = run800k->best;
    std::ostringstream json;
    json.precision(6);
    json << "{\n  \"benchmark\": \"steering\",\n  \"scene\": \"" << scene.name
         << "\",\n  \"quick\": " << (args->quick ? "true" : "false")
         << ",\n  \"radius_mm\": " << problem.params.radius_m * kMmPerM
         << ",\n  \"orientations\": " << problem.params.orientations
         << ",\n  \"sigma_insert_deg\": " << problem.params.sigma_insert_rad * kDegPerRad
         << ",\n  \"sigma_flip_deg\": " << problem.params.sigma_flip_rad * kDegPerRad
         << ",\n  \"states_800k\": " << run800k->states
         << ",\n  \"solve_s_800k\": " << ng::report::jsonNumber(run800k->stats.seconds)
         << ",\n  \"build_s_800k\": " << ng::report::jsonNumber(run800k->build_s)
         << ",\n  \"total_s_800k\": "
         << ng::report::jsonNumber(run800k->build_s + run800k->stats.seconds)
         << ",\n  \"sweeps_800k\": " << run800k->stats.sweeps
         << ",\n  \"converged_800k\": " << (run800k->stats.converged ? "true" : "false")
         << ",\n  \"epsilon\": 0.001,\n  \"threads\": 2"
         << ",\n  \"solve_s_800k_1thread\": " << ng::report::jsonNumber(single.stats.seconds)
         << ",\n  \"solve_s_800k_r25mm\": " << ng::report::jsonNumber(solved_r25.stats.seconds)
         << ",\n  \"sweeps_800k_r25mm\": " << solved_r25.stats.sweeps
         << ",\n  \"transitions_max_800k_r25mm\": " << solved_r25.transitions
         << ",\n  \"sweeps_800k_1thread\": " << single.stats.sweeps
         << ",\n  \"peak_mb_800k\": " << ng::report::jsonNumber(run800k->peak_mb)
         << ",\n  \"baseline_mb\": " << ng::report::jsonNumber(baseline_mb)
         << ",\n  \"lookup_us\": " << ng::report::jsonNumber(lookup_us)
         << ",\n  \"mdp_ps\": " << ng::report::jsonNumber(mdp_mc.rate()) << ",\n  \"mdp_ps_ci\": ["
         << ng::report::jsonNumber(mdp_mc.interval().low) << ", "
         << ng::report::jsonNumber(mdp_mc.interval().high) << "]"
         << ",\n  \"mdp_ps_predicted\": "
         << ng::report::jsonNumber(best.best.probability_of_success)
         << ",\n  \"mc_within_ci_fraction\": " << ng::report::jsonNumber(within_800k)
         << ",\n  \"mc_within_ci_fraction_best\": " << ng::report::jsonNumber(truth_best.within)
         << ",\n  \"truth_best_spacing_mm\": " << ng::report::jsonNumber(truth_best.spacing_mm)
         << ",\n  \"truth_best_subdivision\": " << truth_best.subdivision
         << ",\n  \"truth_best_states\": " << truth_best.states
         << ",\n  \"truth_best_total_s\": " << ng::report::jsonNumber(truth_best.total_s)
         << ",\n  \"truth_best_mean_abs_gap\": " << ng::report::jsonNumber(truth_best.mean_abs_gap)
         << ",\n  \"truth_best_noise_floor\": " << ng::report::jsonNumber(truth_best.noise_floor)
         << ",\n  \"shortest_path_ps\": " << ng::report::jsonNumber(sp_closed.rate())
         << ",\n  \"shortest_path_open_loop_ps\": "
         << (sp.found ? ng::report::jsonNumber(sp_open.rate()) : std::string("null"))
         << ",\n  \"mdp_gain_over_shortest_path\": "
         << ng::report::jsonNumber(sp_closed.rate() > 0.0 ? mdp_mc.rate() / sp_closed.rate() - 1.0
                                                          : NAN)
         << ",\n  \"shortest_path_steps\": " << sp.steps
         << ",\n  \"shortest_path_proven\": " << (sp.proven_shortest ? "true" : "false")
         << ",\n  \"shortest_path_plan_s\": " << ng::report::jsonNumber(sp.seconds)
         << ",\n  \"mc_trials_per_start\": " << kMonteCarloTrials
         << ",\n  \"mc_trials_total\": " << mc_trials_total
         << ",\n  \"mc_seconds_total\": " << ng::report::jsonNumber(mc_seconds)
         << ",\n  \"best_start_y_mm\": "
         << ng::report::jsonNumber(best.best.pose.p_SceneTip.y() * kMmPerM)
         << ",\n  \"best_start_theta_deg\": "
         << ng::report::jsonNumber(best.best.pose.theta_rad * kDegPerRad)
         << ",\n  \"best_start_bevel\": \"" << st::toString(best.best.pose.bevel) << "\""
         << ",\n  \"ps_reference_start_finest\": " << ng::report::jsonNumber(ps_finest)
         << ",\n  \"finest_spacing_mm\": " << ng::report::jsonNumber(finest.spacing_m * kMmPerM)
         << ",\n  \"table_mb_800k\": " << ng::report::jsonNumber(file.mb)
         << ",\n  \"table_save_s\": " << ng::report::jsonNumber(file.save_s)
         << ",\n  \"table_load_s\": " << ng::report::jsonNumber(file.load_s)
         << defaultModelJson(scene_model, truth_default, problem, selected) << adaptation_keys
         << decision_keys << "\n}\n";
    ng::report::writeTextFile(args->out_dir + "/summary.json", json.str());
    writePlotJson(args->out_dir);
    std::cout << scaling.toText() << truth.summaryText() << json.str();
  } catch (const std::exception& e) {
    std::cerr << "bench_steering: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
