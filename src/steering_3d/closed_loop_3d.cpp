// One simulated insertion per strategy (closed_loop_3d.h).
#include "needle_guidance/steering_3d/closed_loop_3d.h"
#include "needle_guidance/cpu_time.h"

#include <chrono>
#include <cmath>
#include <deque>
#include <limits>
#include <memory>

namespace needle_guidance::steering_3d {

using namespace needle_model;  // the needle, meshes and scene the planner works on
namespace {

using Clock = std::chrono::steady_clock;

double secondsSince(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

/// The straight needle: from the disc point nearest the target, aimed at it (clamped into the
/// cone), spun continuously (duty cycle alpha = 1) for the distance to the target's foot point.
std::pair<TipPose3, double> straightStart(const Scene3d& scene) {
  const EntryRegion3& e = scene.entry;
  const Vector3 c = scene.target.center_m;
  Vector3 radial = (c - e.center_m) - (c - e.center_m).dot(e.direction) * e.direction;
  if (radial.norm() > e.radius_m) {
    radial *= e.radius_m / radial.norm();
  }
  const Vector3 p0 = e.center_m + radial;
  Vector3 dir = (c - p0).normalized();
  const double angle = std::acos(std::clamp(dir.dot(e.direction), -1.0, 1.0));
  if (angle > e.cone_half_angle_rad) {
    const Vector3 side = (dir - dir.dot(e.direction) * e.direction).normalized();
    dir = std::cos(e.cone_half_angle_rad) * e.direction + std::sin(e.cone_half_angle_rad) * side;
  }
  return {makeTipPose(p0, dir, dir.unitOrthogonal()), (c - p0).dot(dir)};
}

/// The tip the planner sees after a step: the truth, or the biplane estimate (else the previous
/// estimate advanced by the control, without noise).
TipPose3 estimateTip(const TipPose3& truth, const TipPose3& previous, const Control3& control,
                     const NeedleParams3& needle, BiplaneObserver3* observer, TrialResult3& r) {
  if (observer == nullptr) {
    return truth;
  }
  const TipPose3 predicted = predictTip3(previous, control, needle);
  return acceptBiplane(observer->observe(truth, predicted), predicted, truth, r);
}

}  // namespace

TipPose3 predictTip3(const TipPose3& previous, const Control3& control,
                     const NeedleParams3& needle) {
  const DutyCycle cycle =
      dutyCycleFor(control.curvature_per_m, needle, cycleLength(control.length_m, needle));
  return advanceArc(rotateBevel(previous, control.rotate_rad), cycle.kappa_per_m, control.length_m);
}

TipPose3 acceptBiplane(const Result<TipPose3, BiplaneStatus>& seen, const TipPose3& predicted,
                       const TipPose3& truth, TrialResult3& r) {
  if (seen) {
    ++r.views_fused;
  } else if (seen.status().code() == BiplaneCode::kDisagree) {
    ++r.views_gated;
  } else {
    ++r.views_dropped;
  }
  const TipPose3 estimate = seen ? seen.value() : predicted;
  r.estimate_error_m_max =
      std::max(r.estimate_error_m_max, (estimate.p_SceneTip - truth.p_SceneTip).norm());
  return estimate;
}

std::uint64_t callSeed(std::uint64_t seed, std::uint64_t k) {
  std::uint64_t z = seed * 0x9e3779b97f4a7c15ULL + k + 0x632be59bd9b4e019ULL;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

bool executeStep3(NoisyNeedle3& needle, const CollisionWorld3& world, const Control3& control,
                  TipPose3& tip, TrialResult3& r, const TrialOptions3& options) {
  const StepRecord step = needle.step(tip, control);
  ++r.steps;
  const PathCheck check = world.checkPolyline(step.path);
  if (options.record_path) {
    r.path.insert(r.path.end(), step.path.begin() + 1, step.path.end());
  }
  tip = step.pose;
  if (!check.free()) {
    r.contact = check.contact;
    r.obstacle = check.obstacle;
    r.message =
        "touched " + (check.contact == Contact3::kObstacle ? "obstacle '" + check.obstacle + "'"
                                                           : std::string("the tissue boundary"));
    return false;
  }
  return true;
}

void finishTrial3(const Scene3d& scene, const TipPose3& tip, TrialResult3& r) {
  r.target_error_m = (tip.p_SceneTip - scene.target.center_m).norm();
  r.success = r.contact == Contact3::kFree && r.target_error_m <= scene.target.radius_m;
  if (!r.success && r.message.empty()) {
    r.message = "ended " + std::to_string(r.target_error_m * 1e3) + " mm from the target centre";
  }
}

std::string toString(Strategy3 strategy) {
  switch (strategy) {
    case Strategy3::kReplanUncertainty:
      return "replan_uncertainty";
    case Strategy3::kReplanFirstFound:
      return "replan_first_found";
    case Strategy3::kOpenLoop:
      return "open_loop";
    case Strategy3::kStraight:
      return "straight";
  }
  return "unknown";
}

TrialResult3 runTrial3(const Scene3d& scene, const CollisionWorld3& world, Strategy3 strategy,
                       const NoiseParams3& noise, const PlannerParams3& planner_params,
                       std::uint64_t seed, const TrialOptions3& options) {
  TrialResult3 r;
  r.target_error_m = std::numeric_limits<double>::infinity();
  NoisyNeedle3 needle(scene.needle, noise, seed);
  const double step = scene.step_length_m;
  TipPose3 tip;
  if (strategy == Strategy3::kStraight) {
    double remaining = 0.0;
    std::tie(tip, remaining) = straightStart(scene);
    r.path.push_back(tip.p_SceneTip);
    while (remaining > 1e-9 && r.steps < options.max_steps) {
      const double l = std::min(step, remaining);
      remaining -= l;
      if (!executeStep3(needle, world, Control3{0.0, 0.0, l}, tip, r, options)) {
        break;
      }
    }
    finishTrial3(scene, tip, r);
    return r;
  }
  PlannerParams3 params = planner_params;
  params.choice = strategy == Strategy3::kReplanFirstFound ? PlanChoice::kFirstFound
                                                           : PlanChoice::kMaxSuccessProbability;
  const Planner3 planner(scene, world, params, noise);
  const auto t0 = Clock::now();
  const Result<Plan3, PlanStatus> initial = planner.planFromEntry(callSeed(seed, 0));
  r.initial_plan_s = secondsSince(t0);
  if (!initial) {
    r.no_plan = initial.status().code();
    r.message = initial.status().toString();
    return r;
  }
  r.predicted_p_success = initial.value().p_success;
  r.predicted_p_success_lqg_mp = initial.value().p_success_lqg_mp;
  tip = initial.value().start;
  TipPose3 estimate = tip;  // the entry pose is where the robot put the needle
  std::unique_ptr<BiplaneObserver3> observer;
  if (options.biplane) {
    observer = std::make_unique<BiplaneObserver3>(options.imaging, callSeed(seed, 0xb1b1a4eULL));
  }
  r.path.push_back(tip.p_SceneTip);
  std::deque<Control3> queue = controlQueue(initial.value());
  const bool replan = strategy != Strategy3::kOpenLoop;
  while (!queue.empty() && r.steps < options.max_steps) {
    const Control3 c = nextStep(queue, step);
    if (!executeStep3(needle, world, c, tip, r, options)) {
      break;
    }
    estimate = estimateTip(tip, estimate, c, scene.needle, observer.get(), r);
    if (!replan || queue.empty()) {
      continue;
    }
    const auto t1 = Clock::now();
    const double cpu1 = threadCpuSeconds();
    const Result<Plan3, PlanStatus> next =
        planner.planFromTip(estimate, callSeed(seed, static_cast<std::uint64_t>(r.steps)));
    r.replan_s.push_back(secondsSince(t1));
    r.replan_cpu_s.push_back(threadCpuSeconds() - cpu1);
    r.replan_approach.push_back(next ? next.value().approach : -2);
    if (next) {  // otherwise keep following the previous plan
      queue = controlQueue(next.value());
    }
  }
  finishTrial3(scene, tip, r);
  return r;
}

}  // namespace needle_guidance::steering_3d
