#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/math.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <random>
#include <stdexcept>
#include <thread>

namespace needle_guidance::steering {
namespace {

/// SplitMix64: decorrelates the seeds of consecutive trials.
std::uint64_t mixSeed(std::uint64_t seed, std::uint64_t index) {
  std::uint64_t z = seed + 0x9E3779B97F4A7C15ull * (index + 1);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

}  // namespace

std::string toString(TrialOutcome outcome) {
  switch (outcome) {
    case TrialOutcome::kReachedTarget:
      return "reached_target";
    case TrialOutcome::kHitObstacle:
      return "hit_obstacle";
    case TrialOutcome::kLeftWorkspace:
      return "left_workspace";
    case TrialOutcome::kStepLimit:
      return "step_limit";
  }
  return "unknown";
}

SteeringPolicy tablePolicy(const PolicyTable& table) {
  return [&table](const TipPose& pose, int) { return table.lookup(pose).control; };
}

SteeringPolicy openLoopPolicy(std::vector<Control> controls) {
  return [controls = std::move(controls)](const TipPose&, int step) {
    return step >= 0 && static_cast<std::size_t>(step) < controls.size()
               ? controls[static_cast<std::size_t>(step)]
               : Control::kInsert;
  };
}

Trial simulateTrial(const ContinuousWorkspace& world, const TipPose& start,
                    const SteeringPolicy& policy, std::uint64_t seed, const TrialOptions& options) {
  Trial trial;
  trial.end = start;
  if (options.record_path) {
    trial.path.push_back(start);
  }
  if (!start.p_SceneTip.allFinite() || !std::isfinite(start.theta_rad) ||
      !world.inWorkspace(start.p_SceneTip)) {
    trial.outcome = TrialOutcome::kLeftWorkspace;
    return trial;
  }
  if (world.obstacleAt(start.p_SceneTip) >= 0) {
    trial.outcome = TrialOutcome::kHitObstacle;
    return trial;
  }
  if (world.inTarget(start.p_SceneTip)) {
    trial.outcome = TrialOutcome::kReachedTarget;
    return trial;
  }
  const SteeringParams& params = world.problem().params;
  const double delta = 2.0 * kPi * params.radius_m / params.orientations;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> normal(0.0, 1.0);
  TipPose pose = start;
  for (int step = 0; step < options.max_steps; ++step) {
    const Control u = policy(pose, step);
    const double sigma = u == Control::kInsert ? params.sigma_insert_rad : params.sigma_flip_rad;
    double beta = sigma > 0.0 ? sigma * normal(rng) : 0.0;
    if (options.deflection_step_rad > 0.0) {
      beta = options.deflection_step_rad * std::round(beta / options.deflection_step_rad);
    }
    const ArcTrace arc = world.traceArc(pose, u, beta, delta);
    ++trial.steps;
    trial.flips += u == Control::kFlip ? 1 : 0;
    pose = arc.end;
    if (options.record_path) {
      trial.path.push_back(pose);
      trial.controls.push_back(u);
    }
    if (arc.outcome != ArcOutcome::kFree) {
      trial.outcome = arc.outcome == ArcOutcome::kObstacle ? TrialOutcome::kHitObstacle
                                                           : TrialOutcome::kLeftWorkspace;
      trial.end = pose;
      return trial;
    }
    if (world.inTarget(pose.p_SceneTip)) {
      trial.outcome = TrialOutcome::kReachedTarget;
      trial.end = pose;
      return trial;
    }
  }
  trial.outcome = TrialOutcome::kStepLimit;
  trial.end = pose;
  return trial;
}

Interval wilsonInterval(std::int64_t successes, std::int64_t trials, double z) {
  if (trials <= 0) {
    return {};
  }
  const double n = static_cast<double>(trials);
  const double p = static_cast<double>(successes) / n;
  const double z2 = z * z;
  const double centre = (p + z2 / (2.0 * n)) / (1.0 + z2 / n);
  const double half = z / (1.0 + z2 / n) * std::sqrt(p * (1.0 - p) / n + z2 / (4.0 * n * n));
  return {std::max(0.0, centre - half), std::min(1.0, centre + half)};
}

PairedDifference pairedDifference(const std::vector<bool>& a, const std::vector<bool>& b,
                                  double z) {
  if (a.size() != b.size() || a.empty()) {
    throw std::invalid_argument(
        "pairedDifference: need two outcome lists of the same non-zero "
        "length, got " +
        std::to_string(a.size()) + " and " + std::to_string(b.size()));
  }
  PairedDifference out;
  out.trials = static_cast<std::int64_t>(a.size());
  for (std::size_t i = 0; i < a.size(); ++i) {
    out.both += a[i] && b[i] ? 1 : 0;
    out.only_a += a[i] && !b[i] ? 1 : 0;
    out.only_b += !a[i] && b[i] ? 1 : 0;
  }
  const double n = static_cast<double>(out.trials);
  const double n11 = double(out.both), n10 = double(out.only_a), n01 = double(out.only_b);
  const double n00 = n - n11 - n10 - n01;
  const double pa = (n11 + n10) / n, pb = (n11 + n01) / n;
  out.difference = pa - pb;
  const Interval ia = wilsonInterval(out.both + out.only_a, out.trials, z);
  const Interval ib = wilsonInterval(out.both + out.only_b, out.trials, z);
  // phi of the 2x2 table; 0 when a margin is empty (then the two rates are unrelated).
  const double margins = (n11 + n10) * (n01 + n00) * (n11 + n01) * (n10 + n00);
  const double phi = margins > 0.0 ? (n11 * n00 - n10 * n01) / std::sqrt(margins) : 0.0;
  const double la = pa - ia.low, ua = ia.high - pa, lb = pb - ib.low, ub = ib.high - pb;
  const double low = std::sqrt(std::max(0.0, la * la - 2.0 * phi * la * ub + ub * ub));
  const double high = std::sqrt(std::max(0.0, ua * ua - 2.0 * phi * ua * lb + lb * lb));
  out.interval = {std::max(-1.0, out.difference - low), std::min(1.0, out.difference + high)};
  return out;
}

MonteCarloResult runMonteCarlo(const ContinuousWorkspace& world, const TipPose& start,
                               const SteeringPolicy& policy, std::int64_t trials,
                               std::uint64_t seed, int threads, const TrialOptions& options) {
  if (trials < 1 || threads < 1 || options.max_steps < 1 || options.first_trial < 0) {
    throw std::invalid_argument(
        "runMonteCarlo: trials, threads and max_steps must be >= 1 and first_trial >= 0, got " +
        std::to_string(trials) + ", " + std::to_string(threads) + ", " +
        std::to_string(options.max_steps) + ", " + std::to_string(options.first_trial));
  }
  const auto t0 = std::chrono::steady_clock::now();
  TrialOptions quiet = options;
  quiet.record_path = false;
  std::vector<MonteCarloResult> parts(static_cast<std::size_t>(threads));
  std::vector<double> steps(parts.size(), 0.0), flips(parts.size(), 0.0);
  auto work = [&](int part) {
    MonteCarloResult& r = parts[static_cast<std::size_t>(part)];
    for (std::int64_t i = part; i < trials; i += threads) {
      const Trial t = simulateTrial(world, start, policy,
                                    mixSeed(seed, std::uint64_t(options.first_trial + i)), quiet);
      ++r.trials;
      r.successes += t.outcome == TrialOutcome::kReachedTarget ? 1 : 0;
      r.hit_obstacle += t.outcome == TrialOutcome::kHitObstacle ? 1 : 0;
      r.left_workspace += t.outcome == TrialOutcome::kLeftWorkspace ? 1 : 0;
      r.step_limit += t.outcome == TrialOutcome::kStepLimit ? 1 : 0;
      steps[static_cast<std::size_t>(part)] += t.steps;
      flips[static_cast<std::size_t>(part)] += t.flips;
    }
  };
  std::vector<std::thread> pool;
  for (int part = 1; part < threads; ++part) {
    pool.emplace_back(work, part);
  }
  work(0);
  for (auto& th : pool) {
    th.join();
  }
  MonteCarloResult total;
  double total_steps = 0.0, total_flips = 0.0;
  for (std::size_t i = 0; i < parts.size(); ++i) {
    total.trials += parts[i].trials;
    total.successes += parts[i].successes;
    total.hit_obstacle += parts[i].hit_obstacle;
    total.left_workspace += parts[i].left_workspace;
    total.step_limit += parts[i].step_limit;
    total_steps += steps[i];
    total_flips += flips[i];
  }
  total.mean_steps = total_steps / double(total.trials);
  total.mean_flips = total_flips / double(total.trials);
  total.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return total;
}

MonteCarloResult combined(const MonteCarloResult& a, const MonteCarloResult& b) {
  MonteCarloResult out;
  out.trials = a.trials + b.trials;
  out.successes = a.successes + b.successes;
  out.hit_obstacle = a.hit_obstacle + b.hit_obstacle;
  out.left_workspace = a.left_workspace + b.left_workspace;
  out.step_limit = a.step_limit + b.step_limit;
  if (out.trials > 0) {
    out.mean_steps =
        (a.mean_steps * double(a.trials) + b.mean_steps * double(b.trials)) / double(out.trials);
    out.mean_flips =
        (a.mean_flips * double(a.trials) + b.mean_flips * double(b.trials)) / double(out.trials);
  }
  out.seconds = a.seconds + b.seconds;
  return out;
}

ChainResult runDiscreteChain(const SteeringModel& model, const PolicyTable& table,
                             const TipPose& start, std::int64_t trials, std::uint64_t seed,
                             int max_steps) {
  const std::string where = "runDiscreteChain: ";
  if (trials < 1 || max_steps < 1) {
    throw std::invalid_argument(where + "trials and max_steps must be >= 1, got " +
                                std::to_string(trials) + ", " + std::to_string(max_steps));
  }
  if (table.problemHash() != model.hash()) {
    throw std::invalid_argument(where + "the table was solved for another problem");
  }
  const GridSpec& grid = model.grid();
  const StateId first = grid.nearestState(start);
  if (first < 0) {
    throw std::invalid_argument(where + "the start pose is off the grid");
  }
  const std::int64_t per_position = 2 * std::int64_t{grid.nc};
  const double alpha = grid.alphaRad();
  const SteeringParams& params = model.params();
  // The discrete deflection of a normal draw: beta rounded to the nearest multiple of alpha,
  // the tails folded onto the end transitions (or wrapped around the circle when the model
  // wraps), which has exactly the model's probabilities. Drawing beta as simulateTrial does
  // (same generator, same seed, one draw per step with sigma > 0) couples this chain with the
  // Monte Carlo of rounded deflections: the two differ only where positions round differently.
  auto deflectionIndex = [&](Control u, double beta) {
    const int first_d = model.firstDeflection(u);
    const int count = static_cast<int>(model.deflectionProbabilities(u).size());
    const auto d = static_cast<std::int64_t>(std::llround(beta / alpha));
    if (count == grid.nc) {
      const std::int64_t wrapped = ((d - first_d) % grid.nc + grid.nc) % grid.nc;
      return static_cast<std::size_t>(wrapped);
    }
    return static_cast<std::size_t>(std::clamp<std::int64_t>(d - first_d, 0, count - 1));
  };
  ChainResult out;
  for (std::int64_t i = 0; i < trials; ++i) {
    std::mt19937_64 rng(mixSeed(seed, std::uint64_t(i)));
    std::normal_distribution<double> normal(0.0, 1.0);
    std::mt19937_64 corner_rng(mixSeed(~seed, std::uint64_t(i)));
    std::uniform_real_distribution<double> corner_draw(0.0, 1.0);
    ++out.trials;
    StateId s = first;
    bool ended = false;
    for (int step = 0; step <= max_steps && !ended; ++step) {
      const Cell cell = model.cell(s / per_position);
      if (cell == Cell::kTarget) {
        ++out.successes;
        ended = true;
      } else if (cell == Cell::kObstacle) {
        ++out.rounded_into_obstacle;  // a start in an obstacle counts here too
        ended = true;
      } else if (step == max_steps) {
        ++out.step_limit;
        ended = true;
      } else {
        const Control u = table.control(s);
        const double sigma =
            u == Control::kInsert ? params.sigma_insert_rad : params.sigma_flip_rad;
        // kInterpolated bins are those of sigma' (model.binSigma): the same draw, scaled.
        const double beta = sigma > 0.0 ? model.binSigma(u) * normal(rng) : 0.0;
        const std::vector<Transition> group = model.successorGroups(s, u)[deflectionIndex(u, beta)];
        s = group.back().next;
        if (group.size() > 1) {  // kInterpolated: a corner by its share (own stream)
          double total = 0.0;
          for (const Transition& t : group) {
            total += t.probability;
          }
          double x = corner_draw(corner_rng) * total;
          for (const Transition& t : group) {
            x -= t.probability;
            if (x < 0.0) {
              s = t.next;
              break;
            }
          }
        }
        if (s == kSuccessState) {
          ++out.successes;
          ended = true;
        } else if (s == kFailState) {
          ++out.failed_arcs;
          ended = true;
        }
      }
    }
  }
  return out;
}

}  // namespace needle_guidance::steering
