// RRT with the reachability metric, goal connection by one arc, and the LQG-MP-style choice
// (planner_3d.h).
#include "needle_guidance/steering_3d/planner_3d.h"
#include "needle_guidance/math.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <deque>
#include <limits>
#include <optional>
#include <random>

#include "needle_guidance/steering_3d/closed_loop_3d.h"

namespace needle_guidance::steering_3d {

using namespace needle_model;  // the needle, meshes and scene the planner works on
namespace {

/// The tree samples in the box spanning its roots and the target, grown by this much and
/// clipped to the tissue [m]: room for the S-curves a needle of r ~ 5 cm needs.
constexpr double kSampleMargin_m = 0.03;
/// A goal arc whose duty cycle could not give the exact curvature must still end this close to
/// the centre, as a fraction of the target radius.
constexpr double kGoalEndFraction = 0.25;
/// Plan points and the clearance margins of successProbability are sampled this densely [m].
constexpr double kPointSpacing_m = 1e-3;

using Clock = std::chrono::steady_clock;

struct Node {
  TipPose3 pose;
  int parent = -1;
  Control3 control;  ///< from the parent to this node
  double cost = 0.0;
};

/// The single arc from `pose` towards q: bevel rotation, curvature (snapped to what duty
/// cycling achieves) and its length to q.
struct Steer {
  bool ok = false;
  double rotate = 0.0;
  double kappa = 0.0;
  double length = 0.0;
  bool exact = true;  ///< the arc passes through q (no rotation snap, no curvature saturation)
};

Steer steerTo(const TipPose3& pose, const Vector3& q, const NeedleParams3& needle,
              double cycle_length, double rotation_snap) {
  Steer out;
  const Vector3 w = q - pose.p_SceneTip;
  const Vector3 t = pose.tangent();
  const double along = w.dot(t);
  const double w2 = w.squaredNorm();
  if (!(along > 0.0) || w2 == 0.0) {
    return out;
  }
  const Vector3 perp = w - along * t;
  const double pn = perp.norm();
  const double kreq = 2.0 * pn / w2;
  if (kreq > needle.kappa_max_per_m * (1.0 + 1e-9)) {
    return out;
  }
  out.ok = true;
  double kappa = kreq;
  if (pn > 1e-12) {
    out.rotate = std::atan2(perp.dot(pose.R_SceneTip.col(1)), perp.dot(pose.bevel()));
    if (std::abs(out.rotate) < rotation_snap) {
      kappa = 2.0 * std::max(0.0, perp.dot(pose.bevel())) / w2;  // stay in the bevel plane
      out.rotate = 0.0;
      out.exact = false;
    }
  }
  const DutyCycle cycle = dutyCycleFor(kappa, needle, cycle_length);
  out.kappa = cycle.kappa_per_m;
  out.exact = out.exact && !cycle.saturated;
  out.length = kreq > 1e-9 ? 2.0 * std::atan2(pn, along) / kreq : std::sqrt(w2);
  return out;
}

/// The final arc from `pose` into the target: to its centre when one arc of achievable
/// curvature reaches it; otherwise the arc bending towards it at kappa_max up to its closest
/// approach, if that lies within the ball (the closed loop then ends off-centre rather than not
/// at all). ok = false if neither.
Steer goalArc(const TipPose3& pose, const Target3& target, const NeedleParams3& needle,
              double cycle_length, double rotation_snap) {
  // Without a bevel rotation if the arc in the current bevel plane still ends close enough
  // (a rotation costs sigma_spin), else with the exact rotation.
  Steer g = steerTo(pose, target.center_m, needle, cycle_length, rotation_snap);
  if (g.ok && g.rotate == 0.0) {
    const TipPose3 end = advanceArc(pose, g.kappa, g.length);
    if ((end.p_SceneTip - target.center_m).norm() <= kGoalEndFraction * target.radius_m) {
      return g;
    }
  }
  g = steerTo(pose, target.center_m, needle, cycle_length, 0.0);
  if (g.ok) {
    const TipPose3 end = advanceArc(rotateBevel(pose, g.rotate), g.kappa, g.length);
    g.ok = (end.p_SceneTip - target.center_m).norm() <= kGoalEndFraction * target.radius_m;
    return g;
  }
  const Vector3 w = target.center_m - pose.p_SceneTip;
  const double along = w.dot(pose.tangent());
  if (!(along > 0.0)) {
    return g;
  }
  const Vector3 perp = w - along * pose.tangent();
  g.rotate = std::atan2(perp.dot(pose.R_SceneTip.col(1)), perp.dot(pose.bevel()));
  g.kappa = needle.kappa_max_per_m;
  const TipPose3 rotated = rotateBevel(pose, g.rotate);
  // Closest approach along the arc, sampled at kPointSpacing_m up to a quarter turn.
  double best = std::numeric_limits<double>::infinity();
  for (double s = 0.0; s <= 0.5 * kPi / g.kappa; s += kPointSpacing_m) {
    const double d = (advanceArc(rotated, g.kappa, s).p_SceneTip - target.center_m).norm();
    if (d < best) {
      best = d;
      g.length = s;
    }
  }
  g.ok = best <= target.radius_m && g.length > 0.0;
  g.exact = false;
  return g;
}

Plan3 assemble(const std::vector<Node>& nodes, int leaf, const Control3& goal) {
  Plan3 plan;
  std::vector<Control3> reversed{goal};
  int i = leaf;
  while (nodes[static_cast<std::size_t>(i)].parent >= 0) {
    reversed.push_back(nodes[static_cast<std::size_t>(i)].control);
    i = nodes[static_cast<std::size_t>(i)].parent;
  }
  plan.start = nodes[static_cast<std::size_t>(i)].pose;
  plan.controls.assign(reversed.rbegin(), reversed.rend());
  for (const Control3& c : plan.controls) {
    plan.length_m += c.length_m;
  }
  return plan;
}

/// Tail of the lateral deviation beyond m: 2-D isotropic (Rayleigh) or 1-D (in-plane noise).
double tail(double m, double variance, bool one_axis) {
  if (variance <= 0.0) {
    return m > 0.0 ? 0.0 : 1.0;
  }
  if (m <= 0.0) {
    return 1.0;
  }
  return one_axis ? std::erfc(m / std::sqrt(2.0 * variance)) : std::exp(-m * m / (2.0 * variance));
}

struct TreeContext {
  const CollisionWorld3& world;
  const Target3& target;
  const NeedleParams3& needle;
  const PlannerParams3& params;
  Vector3 lo;  ///< sampling box [m]
  Vector3 hi;
  Clock::time_point deadline;
};

/// Grows one RRT from `roots` until it connects to the target (one plan appended to `plans`),
/// reaches max_nodes or the deadline. Adds its node count to rep.nodes. The roots' own goal
/// arcs are tried only when try_roots (the first tree), so later trees add other plans.
void growTree(const TreeContext& ctx, const std::vector<Node>& roots, std::mt19937_64& rng,
              bool try_roots, std::vector<Plan3>& plans, PlanReport& rep) {
  std::vector<Node> nodes = roots;
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const double cycle = ctx.needle.duty_cycle_length_m;
  const std::size_t before = plans.size();
  const auto tryGoal = [&](int index) {
    const Node& n = nodes[static_cast<std::size_t>(index)];
    rep.closest_approach_m =
        std::min(rep.closest_approach_m, (n.pose.p_SceneTip - ctx.target.center_m).norm());
    const Steer g = goalArc(n.pose, ctx.target, ctx.needle, cycle, ctx.params.rotation_snap_rad);
    if (!g.ok) {
      return;
    }
    const TipPose3 rotated = rotateBevel(n.pose, g.rotate);
    if (!ctx.world.checkArc(rotated, g.kappa, g.length, ctx.params.safety_margin_m).free()) {
      return;
    }
    plans.push_back(assemble(nodes, index, Control3{g.rotate, g.kappa, g.length}));
  };
  for (int i = 0; try_roots && i < static_cast<int>(nodes.size()) && plans.size() == before; ++i) {
    tryGoal(i);
  }
  while (plans.size() == before && static_cast<int>(nodes.size()) < ctx.params.max_nodes &&
         Clock::now() < ctx.deadline) {
    Vector3 q = ctx.target.center_m;
    if (unit(rng) >= ctx.params.goal_bias) {
      q = ctx.lo + (ctx.hi - ctx.lo).cwiseProduct(Vector3(unit(rng), unit(rng), unit(rng)));
    }
    int best = -1;
    Steer best_steer;
    for (int i = 0; i < static_cast<int>(nodes.size()); ++i) {
      const Steer s = steerTo(nodes[static_cast<std::size_t>(i)].pose, q, ctx.needle, cycle,
                              ctx.params.rotation_snap_rad);
      if (s.ok && (best < 0 || s.length < best_steer.length)) {
        best = i;
        best_steer = s;
      }
    }
    if (best < 0) {
      continue;
    }
    const Node& from = nodes[static_cast<std::size_t>(best)];
    const double length = std::min(best_steer.length, ctx.params.max_edge_length_m);
    const TipPose3 rotated = rotateBevel(from.pose, best_steer.rotate);
    if (length <= 0.0 ||
        !ctx.world.checkArc(rotated, best_steer.kappa, length, ctx.params.safety_margin_m).free()) {
      continue;
    }
    nodes.push_back(Node{advanceArc(rotated, best_steer.kappa, length), best,
                         Control3{best_steer.rotate, best_steer.kappa, length},
                         from.cost + length});
    tryGoal(static_cast<int>(nodes.size()) - 1);
  }
  rep.nodes += static_cast<int>(nodes.size());
}

/// The plan's pose after arc length s (clamped to the plan) [m].
TipPose3 poseAlong(const Plan3& plan, double s) {
  TipPose3 pose = plan.start;
  for (const Control3& c : plan.controls) {
    const TipPose3 rotated = rotateBevel(pose, c.rotate_rad);
    if (s <= c.length_m) {
      return advanceArc(rotated, c.curvature_per_m, std::max(0.0, s));
    }
    s -= c.length_m;
    pose = advanceArc(rotated, c.curvature_per_m, c.length_m);
  }
  return pose;
}

/// A rollout's step: the noisy needle moves `pose` by `c`; false if the step touched an expanded
/// obstacle or left the tissue. The step's path (arc length c.length_m) stays within the free
/// ball about its start when the margin exceeds it: one query instead of tracing the path.
bool rolloutStep(NoisyNeedle3& needle, const CollisionWorld3& world, const Control3& c,
                 TipPose3& pose) {
  const double free_radius = world.margin(pose.p_SceneTip);
  const StepRecord r = needle.step(pose, c);
  pose = r.pose;
  return free_radius > c.length_m + world.tolerance() || world.checkPolyline(r.path).free();
}

/// A turn-then-straight approach from a tip to the target centre (the aware choice's candidates,
/// planner_3d.h): rotate the bevel towards the target unless the rotation is below
/// hold_bevel_rad (then turn in the current bevel plane), turn at kappa_1 = kappa_req +
/// turn_fraction (kappa_max - kappa_req) until the tangent points at the target, then go straight
/// (duty cycle alpha = 1). turn_fraction 0 is the single arc of the baseline's goal connection; 1
/// aims as fast as the needle can, which leaves the whole of kappa_max for later corrections.
struct AimPolicy {
  double turn_fraction;
  double hold_bevel_rad;
};
/// The candidates, the default first: a turn that straightens the approach with the bevel held
/// while the rotation is under 0.6 rad (a rotation costs sigma_spin instead of sigma_insert),
/// the single arc with the bevel held, and the single arc with the planner's rotation snap (what
/// the baseline's replan finds first). A negative hold_bevel_rad stands for
/// PlannerParams3::rotation_snap_rad.
constexpr AimPolicy kAimPolicies[] = {{0.6, 0.6}, {0.0, 0.6}, {0.0, -1.0}};
constexpr int kAimPolicyCount = static_cast<int>(sizeof(kAimPolicies) / sizeof(kAimPolicies[0]));
/// The candidate monteCarloSuccesses' rollouts home in with: the default, which the aware loop
/// keeps unless its rollouts show another does better, so the estimate of a tree's plan does
/// not score the baseline's single arc instead.
constexpr int kRolloutPolicy = 0;

struct Aim {
  bool ok = false;
  double rotate = 0.0;
  double kappa = 0.0;       ///< kappa_1 [1/m]
  double turn_m = 0.0;      ///< length of the turn [m]
  double straight_m = 0.0;  ///< length of the straight part that follows [m]
};

/// The approach of `policy` from `pose` (ok = false if the target is behind the tip or needs more
/// than kappa_max in the chosen plane).
Aim aimAt(const TipPose3& pose, const Vector3& target, const NeedleParams3& needle,
          const AimPolicy& policy, double rotation_snap, double cycle_length) {
  Aim out;
  const Vector3 w = target - pose.p_SceneTip;
  const double x = w.dot(pose.tangent());
  if (!(x > 0.0)) {
    return out;
  }
  const Vector3 perp = w - x * pose.tangent();
  out.rotate = std::atan2(perp.dot(pose.R_SceneTip.col(1)), perp.dot(pose.bevel()));
  double y = perp.norm();
  const double hold = policy.hold_bevel_rad < 0.0 ? rotation_snap : policy.hold_bevel_rad;
  if (std::abs(out.rotate) < hold) {
    out.rotate = 0.0;
    y = std::max(0.0, perp.dot(pose.bevel()));
  }
  const double range = std::hypot(x, y);
  const double kmax = needle.kappa_max_per_m;
  const double kreq = 2.0 * y / (range * range);
  if (kreq > kmax * (1.0 + 1e-9)) {
    return out;
  }
  out.ok = true;
  // In the plane of the turn (x along the tangent, y towards the target) the arc of curvature k
  // is at angle th at (sin th, 1 - cos th) / k, heading (cos th, sin th); it is aimed at the
  // target where g(th) = (1 - cos th) / k - range sin(th - phi) = 0, between phi and 2 phi (the
  // single arc's end angle) when k > kreq.
  const double phi = std::atan2(y, x);
  double k = kreq + policy.turn_fraction * (kmax - kreq);
  if (dutyCycleFor(k, needle, cycle_length).kappa_per_m < k * (1.0 - 1e-9)) {
    k = kmax;  // the spin-rate gap below kappa_max: turn harder, the straight part absorbs it
  }
  if (y <= 1e-12 * range) {
    out.straight_m = range;
    return out;
  }
  if (k <= kreq * (1.0 + 1e-9)) {
    out.kappa = kreq;
    out.turn_m = 2.0 * phi / kreq;
    return out;
  }
  double lo = phi, hi = 2.0 * phi;
  for (int i = 0; i < 60; ++i) {
    const double mid = 0.5 * (lo + hi);
    ((1.0 - std::cos(mid)) / k - range * std::sin(mid - phi) > 0.0 ? lo : hi) = mid;
  }
  const double th = 0.5 * (lo + hi);
  out.kappa = k;
  out.turn_m = th / k;
  out.straight_m = std::hypot(x - std::sin(th) / k, y - (1.0 - std::cos(th)) / k);
  return out;
}

/// The next step of an approach: its first step_length_m with the turn's heading change spread
/// over the step (a duty-cycled curvature), so that a turn shorter than a step costs one step.
Control3 aimStep(const Aim& aim, double step_length_m) {
  const double length = std::min(step_length_m, aim.turn_m + aim.straight_m);
  const double turned = aim.kappa * std::min(aim.turn_m, length);
  return Control3{aim.rotate, length > 0.0 ? turned / length : 0.0, length};
}

/// The approach as a plan from `pose`: its first step, then the rest of the turn and the straight.
Plan3 aimPlan(const TipPose3& pose, const Aim& aim, double step_length_m) {
  Plan3 plan;
  plan.start = pose;
  const Control3 first = aimStep(aim, step_length_m);
  plan.controls.push_back(first);
  const double turn_left = std::max(0.0, aim.turn_m - first.length_m);
  const double straight_left = aim.turn_m + aim.straight_m - first.length_m - turn_left;
  if (turn_left > 0.0) {
    plan.controls.push_back(Control3{0.0, aim.kappa, turn_left});
  }
  if (straight_left > 1e-12) {
    plan.controls.push_back(Control3{0.0, 0.0, straight_left});
  }
  for (const Control3& c : plan.controls) {
    plan.length_m += c.length_m;
  }
  return plan;
}

/// Whether the approach's turn and straight keep the obstacles' clearance plus `margin`.
bool aimFree(const CollisionWorld3& world, const TipPose3& pose, const Aim& aim, double margin) {
  const TipPose3 turned = rotateBevel(pose, aim.rotate);
  if (aim.turn_m > 0.0 && !world.checkArc(turned, aim.kappa, aim.turn_m, margin).free()) {
    return false;
  }
  return aim.straight_m <= 0.0 ||
         world.checkArc(advanceArc(turned, aim.kappa, aim.turn_m), 0.0, aim.straight_m, margin)
             .free();
}

/// One rollout of an approach policy from `pose`: the noisy needle executes `first`, then the
/// policy's approach from every new tip (the replanning loop with that candidate kept); where
/// the policy has no approach from a tip (the target beside it, out of kappa_max's reach) the
/// rollout keeps to the previous one, as the loop keeps its plan when a replan finds none.
/// Ends where the approach followed ends. Returns the final distance to the target centre, or
/// infinity if a step touched something.
double aimRollout(TipPose3 pose, const Aim& first, const AimPolicy& policy, const Scene3d& scene,
                  const CollisionWorld3& world, const PlannerParams3& params,
                  NoisyNeedle3& needle) {
  const double step = scene.step_length_m;
  const double cycle = scene.needle.duty_cycle_length_m;
  std::deque<Control3> queue = controlQueue(aimPlan(pose, first, step));
  for (int k = 0; k < 1000 && !queue.empty(); ++k) {
    if (!rolloutStep(needle, world, nextStep(queue, step), pose)) {
      return std::numeric_limits<double>::infinity();
    }
    const Aim aim = queue.empty() ? Aim{}
                                  : aimAt(pose, scene.target.center_m, scene.needle, policy,
                                          params.rotation_snap_rad, cycle);
    if (aim.ok) {
      queue = controlQueue(aimPlan(pose, aim, step));
    }
  }
  return (pose.p_SceneTip - scene.target.center_m).norm();
}

/// One rollout of monteCarloSuccesses: the candidate's first step, then the replanning loop's
/// stand-in. Once a free approach to the target is found (the replan the aware loop then takes;
/// the robust candidate kAimPolicies[kRolloutPolicy] stands for its choice) the rollout homes in
/// as aimRollout does, without checking the approach again (the executed steps are checked
/// anyway: the check dominates the rollout's cost); before that it steers towards the plan two
/// steps ahead.
bool rolloutSucceeds(const Plan3& plan, const Scene3d& scene, const CollisionWorld3& world,
                     const PlannerParams3& params, NoisyNeedle3& needle) {
  const double step = scene.step_length_m;
  const NeedleParams3& np = scene.needle;
  const double cycle = np.duty_cycle_length_m;
  const int max_steps = static_cast<int>(std::ceil(plan.length_m / step)) + 4;
  TipPose3 pose = plan.start;
  std::deque<Control3> queue = controlQueue(plan);
  bool homing = false;
  const AimPolicy& policy = kAimPolicies[kRolloutPolicy];
  for (int k = 0; k < max_steps && !queue.empty(); ++k) {
    if (!rolloutStep(needle, world, nextStep(queue, step), pose)) {
      return false;
    }
    if (queue.empty()) {
      break;  // the plan followed ends here
    }
    const Aim a = aimAt(pose, scene.target.center_m, np, policy, params.rotation_snap_rad, cycle);
    if (a.ok && (homing || aimFree(world, pose, a, params.safety_margin_m))) {
      homing = true;
      queue = controlQueue(aimPlan(pose, a, step));
    } else if (!homing) {
      const Steer st = steerTo(pose, poseAlong(plan, (k + 2) * step).p_SceneTip, np, cycle,
                               params.rotation_snap_rad);
      // The plan's remaining length, its first step steered back towards it.
      queue.assign(1, Control3{st.ok ? st.rotate : 0.0, st.ok ? st.kappa : 0.0,
                               std::max(0.0, plan.length_m - (k + 1) * step)});
    }  // homing without an approach from here: keep to the previous one, as aimRollout does
  }
  return (pose.p_SceneTip - scene.target.center_m).norm() <= scene.target.radius_m;
}

}  // namespace

std::string toString(PlanCode code) {
  switch (code) {
    case PlanCode::kOk:
      return "ok";
    case PlanCode::kStartOutsideTissue:
      return "start_outside_tissue";
    case PlanCode::kStartInObstacle:
      return "start_in_obstacle";
    case PlanCode::kTargetOutsideTissue:
      return "target_outside_tissue";
    case PlanCode::kTargetInObstacle:
      return "target_in_obstacle";
    case PlanCode::kNoPathWithinBudget:
      return "no_path_within_budget";
  }
  return "unknown";
}

std::deque<Control3> controlQueue(const Plan3& plan) {
  return std::deque<Control3>(plan.controls.begin(), plan.controls.end());
}

Control3 nextStep(std::deque<Control3>& queue, double step_length_m) {
  Control3 c = queue.front();
  if (c.length_m <= step_length_m * (1.0 + 1e-9)) {
    queue.pop_front();
  } else {
    c.length_m = step_length_m;
    queue.front().length_m -= step_length_m;
    queue.front().rotate_rad = 0.0;  // the bevel was rotated at the control's first step
  }
  return c;
}

std::vector<Vector3> Plan3::points() const {
  std::vector<Vector3> out{start.p_SceneTip};
  TipPose3 pose = start;
  for (const Control3& c : controls) {
    const TipPose3 rotated = rotateBevel(pose, c.rotate_rad);
    const int pieces = std::max(1, static_cast<int>(std::ceil(c.length_m / kPointSpacing_m)));
    for (int i = 1; i <= pieces; ++i) {
      out.push_back(advanceArc(rotated, c.curvature_per_m, c.length_m * i / pieces).p_SceneTip);
    }
    pose = advanceArc(rotated, c.curvature_per_m, c.length_m);
  }
  return out;
}

double successProbability(const Plan3& plan, const CollisionWorld3& world, const Target3& target,
                          const NoiseParams3& noise, double step_length_m, double kappa_max) {
  const double lookahead = 2.0 * step_length_m;
  const double k1 = 2.0 / (lookahead * lookahead), k2 = 2.0 / lookahead;
  Eigen::Matrix2d P = Eigen::Matrix2d::Zero();
  double p = 1.0;
  TipPose3 pose = plan.start;
  for (const Control3& c : plan.controls) {
    const TipPose3 rotated = rotateBevel(pose, c.rotate_rad);
    const int steps = std::max(1, static_cast<int>(std::ceil(c.length_m / step_length_m - 1e-9)));
    for (int k = 0; k < steps; ++k) {
      const double s0 = c.length_m * k / steps, l = c.length_m / steps;
      const double sigma =
          (k == 0 && c.rotate_rad != 0.0) ? noise.sigma_spin_rad : noise.sigma_insert_rad;
      Eigen::Matrix2d A;
      A << 1.0 - 0.5 * l * l * k1, l - 0.5 * l * l * k2, -l * k1, 1.0 - l * k2;
      const Eigen::Vector2d b(l, 1.0);
      P = A * P * A.transpose() + sigma * sigma * b * b.transpose();
      // Clearance over the step: the smallest margin at points <= 1 mm apart.
      double margin = std::numeric_limits<double>::infinity();
      const int pieces = std::max(1, static_cast<int>(std::ceil(l / kPointSpacing_m)));
      for (int i = 1; i <= pieces; ++i) {
        margin = std::min(
            margin, world.obstacleMargin(
                        advanceArc(rotated, c.curvature_per_m, s0 + l * i / pieces).p_SceneTip));
      }
      p *= 1.0 - tail(margin, P(0, 0), noise.in_plane_only);
      // The next step's correction c must fit in the curvature the plan leaves unused.
      const Eigen::RowVector2d K(k1, k2);
      const double correction_variance = K * P * K.transpose();
      p *= 1.0 - 0.5 * tail(kappa_max - c.curvature_per_m, correction_variance, true);
    }
    pose = advanceArc(rotated, c.curvature_per_m, c.length_m);
  }
  return p * (1.0 - tail(target.radius_m, P(0, 0), noise.in_plane_only));
}

int monteCarloSuccesses(const Plan3& plan, const Scene3d& scene, const CollisionWorld3& world,
                        const NoiseParams3& noise, const PlannerParams3& params, int rollouts,
                        std::uint64_t seed) {
  int successes = 0;
  for (int j = 0; j < rollouts; ++j) {
    NoisyNeedle3 needle(scene.needle, noise, callSeed(seed, static_cast<std::uint64_t>(j)));
    successes += rolloutSucceeds(plan, scene, world, params, needle) ? 1 : 0;
  }
  return successes;
}

Planner3::Planner3(const Scene3d& scene, const CollisionWorld3& world, PlannerParams3 params,
                   NoiseParams3 noise)
    : scene_(scene), world_(world), params_(params), noise_(noise) {
  if (!(params_.time_budget_s > 0.0) || !(params_.entry_time_budget_s > 0.0) ||
      params_.max_plans < 1 || params_.max_nodes < 1 ||
      !(params_.goal_bias >= 0.0 && params_.goal_bias <= 1.0) ||
      !(params_.max_edge_length_m > 0.0) || params_.entry_samples < 1 ||
      !(params_.safety_margin_m >= 0.0) || params_.rollouts < 1 || params_.entry_rollouts < 1 ||
      !(params_.estimate_budget_s > 0.0) || !(params_.entry_estimate_budget_s > 0.0)) {
    throw std::invalid_argument(
        "Planner3: needs time budgets > 0, max_plans >= 1, max_nodes >= 1, goal_bias in "
        "[0, 1], max_edge_length_m > 0, entry_samples >= 1, safety_margin_m >= 0, rollouts >= 1, "
        "entry_rollouts >= 1, estimate budgets > 0");
  }
  noise_.validate();
}

PlanStatus Planner3::checkTarget() const {
  const PointCheck target = world_.classify(scene_.target.center_m);
  if (target.contact == Contact3::kOutsideTissue) {
    return PlanStatus(PlanCode::kTargetOutsideTissue,
                      "no plan: the target centre lies outside "
                      "the tissue");
  }
  if (target.contact == Contact3::kObstacle) {
    return PlanStatus(PlanCode::kTargetInObstacle,
                      "no plan: the target centre lies within "
                      "obstacle '" +
                          target.obstacle + "' (with its clearance)");
  }
  return PlanStatus::success();
}

Result<Plan3, PlanStatus> Planner3::planFromEntry(std::uint64_t seed, PlanReport* report) const {
  std::mt19937_64 rng(seed ^ 0x9e3779b97f4a7c15ULL);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const EntryRegion3& e = scene_.entry;
  const Vector3 u = e.direction.unitOrthogonal();
  const Vector3 v = e.direction.cross(u);
  std::vector<TipPose3> roots;
  for (int i = 0; i < params_.entry_samples; ++i) {
    // Uniform on the disc; tangents uniform in the cone's solid angle; bevel at random.
    const double r = e.radius_m * std::sqrt(unit(rng)), a = 2.0 * kPi * unit(rng);
    const double cos_t = 1.0 - unit(rng) * (1.0 - std::cos(e.cone_half_angle_rad));
    const double sin_t = std::sqrt(std::max(0.0, 1.0 - cos_t * cos_t)), b = 2.0 * kPi * unit(rng);
    const Vector3 p = e.center_m + r * (std::cos(a) * u + std::sin(a) * v);
    const Vector3 t = cos_t * e.direction + sin_t * (std::cos(b) * u + std::sin(b) * v);
    const double bevel = 2.0 * kPi * unit(rng);
    const Vector3 d0 = t.unitOrthogonal();
    roots.push_back(makeTipPose(p, t, std::cos(bevel) * d0 + std::sin(bevel) * t.cross(d0)));
  }
  return plan(roots, seed, params_.entry_time_budget_s, params_.entry_rollouts,
              params_.entry_estimate_budget_s, report);
}

Result<Plan3, PlanStatus> Planner3::planFromTip(const TipPose3& tip, std::uint64_t seed,
                                                PlanReport* report) const {
  return plan({tip}, seed, params_.time_budget_s, params_.rollouts, params_.estimate_budget_s,
              report);
}

Result<Plan3, PlanStatus> Planner3::plan(const std::vector<TipPose3>& roots, std::uint64_t seed,
                                         double budget_s, int rollouts, double estimate_budget_s,
                                         PlanReport* report) const {
  const auto started = Clock::now();
  PlanReport local;
  PlanReport& rep = report != nullptr ? *report : local;
  rep = PlanReport{};
  const PlanStatus target_status = checkTarget();
  if (!target_status) {
    return target_status;
  }
  std::vector<Node> nodes;
  PointCheck first_refusal;
  for (const TipPose3& root : roots) {
    const PointCheck check = world_.classify(root.p_SceneTip);
    if (check.contact == Contact3::kFree) {
      nodes.push_back(Node{root, -1, Control3{}, 0.0});
    } else if (first_refusal.contact == Contact3::kFree) {
      first_refusal = check;
    }
  }
  if (nodes.empty()) {
    if (first_refusal.contact == Contact3::kObstacle) {
      return PlanStatus(PlanCode::kStartInObstacle,
                        "no plan: the start lies within obstacle '" + first_refusal.obstacle + "'");
    }
    return PlanStatus(PlanCode::kStartOutsideTissue, "no plan: the start lies outside the tissue");
  }
  const Target3& target = scene_.target;
  const NeedleParams3& needle = scene_.needle;
  Vector3 lo = target.center_m, hi = target.center_m;
  for (const Node& n : nodes) {
    lo = lo.cwiseMin(n.pose.p_SceneTip);
    hi = hi.cwiseMax(n.pose.p_SceneTip);
  }
  TreeContext context{world_,
                      target,
                      needle,
                      params_,
                      (lo - Vector3::Constant(kSampleMargin_m)).cwiseMax(world_.tissueMin()),
                      (hi + Vector3::Constant(kSampleMargin_m)).cwiseMin(world_.tissueMax()),
                      started + std::chrono::duration_cast<Clock::duration>(
                                    std::chrono::duration<double>(budget_s))};
  rep.closest_approach_m = std::numeric_limits<double>::infinity();
  if (params_.choice == PlanChoice::kMaxSuccessProbability && nodes.size() == 1) {
    // A replan from the tip: a free direct approach needs no tree (planApproach).
    // Its rollouts get the tree's wall budget (they cost ~5 ms of CPU at the defaults).
    std::optional<Plan3> approach = planApproach(
        nodes.front().pose, rollouts,
        started +
            std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(budget_s)),
        seed, rep);
    if (approach) {
      rep.seconds = std::chrono::duration<double>(Clock::now() - started).count();
      return *approach;
    }
  }
  std::mt19937_64 rng(seed);
  std::vector<Plan3> plans;
  // The baseline grows one tree to its first plan. Ours grows a fresh tree per plan, so the
  // candidates it chooses among differ in more than their last arc.
  const int wanted = params_.choice == PlanChoice::kFirstFound ? 1 : params_.max_plans;
  int trees = 0;
  do {
    growTree(context, nodes, rng, trees++ == 0, plans, rep);
  } while (static_cast<int>(plans.size()) < wanted && Clock::now() < context.deadline);
  rep.plans_found = static_cast<int>(plans.size());
  if (plans.empty()) {
    rep.seconds = std::chrono::duration<double>(Clock::now() - started).count();
    return PlanStatus(PlanCode::kNoPathWithinBudget,
                      "no plan: no feasible path to the target under kappa_max = " +
                          std::to_string(needle.kappa_max_per_m) + " /m within " +
                          std::to_string(budget_s * 1e3) + " ms (" + std::to_string(rep.nodes) +
                          " nodes; closest approach " +
                          std::to_string(rep.closest_approach_m * 1e3) + " mm)");
  }
  const std::size_t chosen =
      choose(plans, rollouts,
             context.deadline + std::chrono::duration_cast<Clock::duration>(
                                    std::chrono::duration<double>(estimate_budget_s)),
             seed);
  rep.seconds = std::chrono::duration<double>(Clock::now() - started).count();
  return plans[chosen];
}

std::size_t Planner3::choose(std::vector<Plan3>& plans, int rollouts,
                             std::chrono::steady_clock::time_point deadline,
                             std::uint64_t seed) const {
  for (Plan3& p : plans) {
    p.p_success_lqg_mp = successProbability(p, world_, scene_.target, noise_, scene_.step_length_m,
                                            scene_.needle.kappa_max_per_m);
    p.p_success = p.p_success_lqg_mp;
  }
  if (params_.choice == PlanChoice::kFirstFound) {
    return 0;
  }
  std::size_t chosen = 0;
  if (params_.estimate == SuccessEstimate::kLqgMp) {
    for (std::size_t i = 1; i < plans.size(); ++i) {
      const bool better = plans[i].p_success > plans[chosen].p_success ||
                          (plans[i].p_success == plans[chosen].p_success &&
                           plans[i].length_m < plans[chosen].length_m);
      chosen = better ? i : chosen;
    }
    return chosen;
  }
  // Rollout j of every candidate uses the same seed (common random numbers), so the comparison
  // is paired. Rounds of one rollout per candidate run until `rollouts` rounds or the estimate
  // budget is spent (a round cut short is dropped, except the first). Another plan
  // replaces the first found (the baseline's) only if, over the paired rollouts, it succeeds
  // where the first fails at least kSwitchMargin times more often than the reverse: the
  // maximum of several noisy estimates is biased upwards, and a tie must keep the baseline.
  constexpr int kSwitchMargin = 2;
  if (noise_.sigma_insert_rad == 0.0 && noise_.sigma_spin_rad == 0.0 &&
      noise_.sigma_roll_rad == 0.0) {
    rollouts = 1;  // every rollout would be the same
  }
  const std::uint64_t mc_seed = seed ^ 0x5851f42d4c957f2dULL;
  std::vector<std::vector<char>> outcome(plans.size());
  std::vector<char> round(plans.size());
  for (int j = 0; j < rollouts; ++j) {
    const std::uint64_t rollout_seed = callSeed(mc_seed, static_cast<std::uint64_t>(j));
    bool complete = true;
    for (std::size_t i = 0; i < plans.size() && complete; ++i) {
      NoisyNeedle3 needle(scene_.needle, noise_, rollout_seed);
      round[i] = rolloutSucceeds(plans[i], scene_, world_, params_, needle) ? 1 : 0;
      complete = Clock::now() < deadline;
      if (!complete && j == 0) {  // the candidates not reached drop out
        plans.resize(i + 1);
      }
    }
    if (!complete && j > 0) {
      break;
    }
    for (std::size_t i = 0; i < plans.size(); ++i) {
      outcome[i].push_back(round[i]);
    }
  }
  const std::size_t done = outcome[0].size();
  int best_gain = kSwitchMargin - 1;
  for (std::size_t i = 0; i < plans.size(); ++i) {
    int successes = 0, gain = 0;
    for (std::size_t j = 0; j < done; ++j) {
      successes += outcome[i][j];
      gain += outcome[i][j] - outcome[0][j];
    }
    plans[i].p_success = double(successes) / double(done);
    if (gain > best_gain) {
      best_gain = gain;
      chosen = i;
    }
  }
  return chosen;
}

}  // namespace needle_guidance::steering_3d

namespace needle_guidance::steering_3d {

using namespace needle_model;  // the needle, meshes and scene the planner works on

std::optional<Plan3> Planner3::planApproach(const TipPose3& tip, int rollouts,
                                            std::chrono::steady_clock::time_point deadline,
                                            std::uint64_t seed, PlanReport& rep) const {
  const double step = scene_.step_length_m;
  const Target3& target = scene_.target;
  std::vector<int> policy;
  std::vector<Aim> aims;
  rep.closest_approach_m = (tip.p_SceneTip - target.center_m).norm();
  for (int i = 0; i < kAimPolicyCount; ++i) {
    const Aim a = aimAt(tip, target.center_m, scene_.needle, kAimPolicies[i],
                        params_.rotation_snap_rad, scene_.needle.duty_cycle_length_m);
    if (a.ok && aimFree(world_, tip, a, params_.safety_margin_m)) {
      policy.push_back(i);
      aims.push_back(a);
    }
  }
  if (aims.empty()) {
    return std::nullopt;
  }
  const bool noiseless = noise_.sigma_insert_rad == 0.0 && noise_.sigma_spin_rad == 0.0 &&
                         noise_.sigma_roll_rad == 0.0;
  if (noiseless) {
    rollouts = 1;  // every rollout would be the same
  }
  // Rounds of one rollout per candidate with the same draws for all (common random numbers),
  // whole rounds only, until `rollouts` rounds or the deadline (the first round always runs).
  const std::size_t n = aims.size();
  std::vector<int> successes(n, 0);
  std::vector<double> error_sum(n, 0.0);
  int done = 0;
  const std::uint64_t mc_seed = seed ^ 0x5851f42d4c957f2dULL;
  for (int j = 0; j < rollouts && (j == 0 || Clock::now() < deadline); ++j, ++done) {
    const std::uint64_t rollout_seed = callSeed(mc_seed, static_cast<std::uint64_t>(j));
    for (std::size_t i = 0; i < n; ++i) {
      NoisyNeedle3 needle(scene_.needle, noise_, rollout_seed);
      const double e =
          aimRollout(tip, aims[i], kAimPolicies[policy[i]], scene_, world_, params_, needle);
      if (e <= target.radius_m) {
        ++successes[i];
        error_sum[i] += e;
      }
    }
  }
  // The most successes; among equals the earlier candidate (the default first: rounds cut short
  // by the budget fall back on it), or without noise the smallest final error (every candidate
  // succeeds; the most exact one ends at the centre).
  std::size_t best = 0;
  const auto meanError = [&](std::size_t k) {
    return successes[k] > 0 ? error_sum[k] / successes[k] : std::numeric_limits<double>::infinity();
  };
  for (std::size_t i = 1; i < n; ++i) {
    if (successes[i] > successes[best] ||
        (noiseless && successes[i] == successes[best] && meanError(i) < meanError(best))) {
      best = i;
    }
  }
  Plan3 plan = aimPlan(tip, aims[best], step);
  plan.approach = policy[best];
  plan.p_success = double(successes[best]) / double(done);
  plan.p_success_lqg_mp =
      successProbability(plan, world_, target, noise_, step, scene_.needle.kappa_max_per_m);
  rep.plans_found = static_cast<int>(n);
  return plan;
}

}  // namespace needle_guidance::steering_3d
