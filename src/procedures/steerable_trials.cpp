// The closed-loop steerable-needle trials (see steerable_trials.h; dissertation 5.5).
#include "needle_guidance/procedures/steerable_trials.h"
#include "needle_guidance/math.h"
#include "needle_guidance/steering/start_verification.h"

#include <chrono>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::procedures {
namespace {

double secondsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

/// A stopped insertion as a trial outcome: the world's referee first (a tip outside the
/// workspace left it, whatever the device said), then the device's reason.
SteerableOutcome stoppedOutcome(StepEnd end, const std::optional<SteerableTip>& stopped,
                                const needle_model::PlanarWorld& world) {
  if (end == StepEnd::kLeftWorkspace || (stopped && !world.inWorkspace(stopped->pose.p_SceneTip))) {
    return SteerableOutcome::kLeftWorkspace;
  }
  switch (end) {
    case StepEnd::kObstacle:
      return SteerableOutcome::kHitObstacle;
    case StepEnd::kJointLimit:
      return SteerableOutcome::kNeedleLength;  // a miss: the needle was used up before the target
    default:
      return SteerableOutcome::kError;
  }
}

/// The end-of-trial entry of the decision list (no control).
SteerableDecision endOfTrial(const SteerableTip& tip, double probability_of_success) {
  SteerableDecision d;
  d.truth = tip;
  d.answer.looked_up = tip.pose;
  d.answer.source = tip.source;
  d.answer.probability_of_success = probability_of_success;
  return d;
}

}  // namespace

const char* toString(SteerableOutcome outcome) {
  switch (outcome) {
    case SteerableOutcome::kReachedTarget:
      return "reached_target";
    case SteerableOutcome::kHitObstacle:
      return "hit_obstacle";
    case SteerableOutcome::kLeftWorkspace:
      return "left_workspace";
    case SteerableOutcome::kStepLimit:
      return "step_limit";
    case SteerableOutcome::kNeedleLength:
      return "needle_length";
    case SteerableOutcome::kError:
      return "error";
  }
  return "error";
}

double SteerableDecision::tipError_m() const {
  return (answer.looked_up.p_SceneTip - truth.pose.p_SceneTip).norm();
}

double SteerableDecision::headingError_rad() const {
  return std::abs(std::remainder(answer.looked_up.theta_rad - truth.pose.theta_rad, 2.0 * kPi));
}

SteerableTrials::SteerableTrials(std::string scene_name, const steering::SteeringProblem& problem,
                                 const steering::PolicyTable& table,
                                 const steering::StartOptions& starts, SteerableSettings settings)
    : scene_name_(std::move(scene_name)),
      problem_(problem),
      world_(problem),
      table_(table),
      starts_(starts),
      settings_(std::move(settings)) {
  if (settings_.trials < 1 || settings_.max_steps < 1) {
    throw std::invalid_argument("SteerableTrials: trials (" + std::to_string(settings_.trials) +
                                ") and max_steps (" + std::to_string(settings_.max_steps) +
                                ") must be at least 1");
  }
}

SteerableTrialRecord runSteerableTrial(SteerableDevices& devices,
                                       const needle_model::PlanarWorld& world, double delta_m,
                                       const steering::TipPose& start, std::uint64_t seed,
                                       bool reseed, int max_steps) {
  SteerableTrialRecord rec;
  const auto t0 = std::chrono::steady_clock::now();
  std::string why;
  bool running = devices.placeAtEntry(start, seed, reseed, why);
  if (!running) {
    rec.message = why;
  }
  while (running) {
    const std::optional<SteerableTip> tip = devices.tip(why);
    if (!tip) {
      rec.message = why;
      break;
    }
    if (world.inTarget(tip->pose.p_SceneTip)) {
      rec.outcome = SteerableOutcome::kReachedTarget;
      rec.decisions.push_back(endOfTrial(*tip, 1.0));
      break;
    }
    if (rec.steps >= max_steps) {
      rec.outcome = SteerableOutcome::kStepLimit;
      break;
    }
    const std::optional<PolicyAnswer> answer = devices.control(why);
    if (!answer) {
      rec.message = why;
      break;
    }
    if (!answer->usable) {
      // No control to act on (e.g. the pose was not finite): stop here. Off the grid the world
      // referees the next step.
      std::ostringstream m;
      m << "the policy answered status '" << answer->status << "' for the tip ("
        << answer->looked_up.p_SceneTip.x() << ", " << answer->looked_up.p_SceneTip.y()
        << ") m; no control";
      rec.message = m.str();
      break;
    }
    if (!rec.noise && std::isfinite(answer->sigma_insert_rad) &&
        std::isfinite(answer->sigma_flip_rad)) {
      rec.noise = steering::TrialNoise{answer->sigma_insert_rad, answer->sigma_flip_rad};
    }
    rec.unconfident_decisions += answer->confident ? 0 : 1;
    rec.decisions.push_back({*tip, *answer, true});
    if (answer->control == steering::Control::kFlip) {
      if (!devices.flip(why)) {
        rec.message = "flip_bevel: " + why;
        break;
      }
      ++rec.flips;
    }
    ++rec.steps;
    const StepEnd end = devices.insertTo(tip->inserted_length_m + delta_m, why);
    if (end != StepEnd::kMoved) {
      std::string unused;
      const std::optional<SteerableTip> stopped = devices.tip(unused);
      rec.outcome = stoppedOutcome(end, stopped, world);
      rec.message = why;
      if (stopped) {
        rec.decisions.push_back(endOfTrial(*stopped, 0.0));
      }
      break;
    }
  }
  rec.samples = devices.takeSamples();
  rec.seconds = secondsSince(t0);
  if (const auto f = devices.fault()) {
    rec.outcome = SteerableOutcome::kError;  // whatever the trial saw last, a node died
    rec.message = f->toString();
  }
  return rec;
}

SteerableReport SteerableTrials::run(SteerableDevices& devices, const SteerableStart& start) const {
  const auto t0 = std::chrono::steady_clock::now();
  SteerableReport rep;
  rep.scene = scene_name_;
  rep.problem = problem_;
  rep.settings = settings_;
  rep.start = start;
  const steering::SteeringParams& params = world_.problem().params;
  const double delta_m = 2.0 * kPi * params.radius_m / params.orientations;
  for (int trial = 0; trial < settings_.trials; ++trial) {
    // Trial k draws its deflections from its own stream: runs with ground-truth and image
    // feedback see the same needle as long as they make the same decisions.
    const std::uint64_t seed =
        static_cast<std::uint64_t>(settings_.seed) * SteerableSettings::kTrialSeedStride +
        static_cast<std::uint64_t>(trial);
    SteerableTrialRecord rec = runSteerableTrial(devices, world_, delta_m, start.pose, seed,
                                                 settings_.seed >= 0, settings_.max_steps);
    std::ostringstream line;
    line << "trial " << trial + 1 << "/" << settings_.trials << ": " << toString(rec.outcome)
         << " after " << rec.steps << " steps, " << rec.flips << " flips"
         << (rec.message.empty() ? "" : " (" + rec.message + ")");
    devices.progress(line.str());
    rep.records.push_back(std::move(rec));
    if ((rep.fault = devices.fault())) {
      break;
    }
  }
  rep.safe_stop = devices.leaveSafe();

  // The same start in the core simulator (continuous needle, same policy table) and the P_s
  // map of figure 5.7.
  rep.monte_carlo = steering::runMonteCarlo(
      world_, start.pose, steering::tablePolicy(table_),
      monteCarloTrials(start.reportedPs(), steering::verificationTolerance(problem_)),
      kMonteCarloSeed, 2);
  rep.ps_map = table_.startCandidates(starts_);
  rep.wall_time_s = secondsSince(t0);
  return rep;
}

std::int64_t SteerableTrials::monteCarloTrials(double ps, double tolerance) {
  return steering::verificationCap(ps, tolerance, steering::StartVerificationOptions{}.z,
                                   kMinMonteCarloTrials, kMaxMonteCarloTrials);
}

}  // namespace needle_guidance::procedures

namespace needle_guidance::procedures {

std::vector<steering::TrialNoise> SteerableReport::trialNoises(
    std::vector<int>& record_index) const {
  std::vector<steering::TrialNoise> out;
  record_index.clear();
  for (std::size_t i = 0; i < records.size(); ++i) {
    if (records[i].noise) {
      out.push_back(*records[i].noise);
      record_index.push_back(static_cast<int>(i));
    }
  }
  return out;
}

void SteerableReport::addTablesUsed(const std::vector<steering::TableUsed>& used,
                                    const std::vector<int>& record_index) {
  tables.clear();
  for (const steering::TableUsed& u : used) {
    SteerableTableReport t;
    t.noise = u.noise;
    for (int k : u.trials) {
      t.trials.push_back(record_index.at(static_cast<std::size_t>(k)));
    }
    const steering::PolicyTable& table = *u.policy->table;
    t.predicted_ps = table.lookup(start.pose).probability_of_success;
    const steering::SteeringParams& scene = problem.params;
    if (u.noise.sigma_insert_rad == scene.sigma_insert_rad &&
        u.noise.sigma_flip_rad == scene.sigma_flip_rad && t.predicted_ps == start.predicted_ps) {
      t.monte_carlo = monte_carlo;  // the run's own table: the same seeded trials as the headline
    } else {
      const steering::ContinuousWorkspace world(u.policy->model->problem());
      const std::int64_t n = SteerableTrials::monteCarloTrials(
          t.predicted_ps, steering::verificationTolerance(problem));
      t.monte_carlo = steering::runMonteCarlo(world, start.pose, steering::tablePolicy(table), n,
                                              SteerableTrials::kMonteCarloSeed, 2);
    }
    tables.push_back(std::move(t));
  }
}

}  // namespace needle_guidance::procedures
