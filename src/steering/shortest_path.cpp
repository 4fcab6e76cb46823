// The shortest-path baseline (dissertation 5.1, 5.5): an OMPL SST plan in the continuous world
// and the breadth-first steps-to-go table on the MDP's discretisation (5.4.2, sigma = 0).
#include "needle_guidance/steering/shortest_path.h"
#include "needle_guidance/math.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <memory>
#include <sstream>
#include <stdexcept>
#include <utility>

#include <ompl/base/OptimizationObjective.h>
#include <ompl/base/PlannerTerminationCondition.h>
#include <ompl/base/ProblemDefinition.h>
#include <ompl/base/goals/GoalSampleableRegion.h>
#include <ompl/base/spaces/DiscreteStateSpace.h>
#include <ompl/base/spaces/SE2StateSpace.h>
#include <ompl/control/PathControl.h>
#include <ompl/control/SpaceInformation.h>
#include <ompl/control/StatePropagator.h>
#include <ompl/control/planners/sst/SST.h>
#include <ompl/control/spaces/DiscreteControlSpace.h>
#include <ompl/util/Console.h>
#include <ompl/util/RandomNumbers.h>

#include "needle_guidance/format.h"

namespace needle_guidance::steering {
namespace {

namespace ob = ompl::base;
namespace oc = ompl::control;

/// One planner step is one insertion of delta; OMPL's propagation step size is that unit.
constexpr double kStepDuration = 1.0;
/// Bevel value of a state whose last arc was not free. The propagator writes it, the validity
/// checker rejects it: OMPL control planners check validity only at the end of a propagation,
/// so the arc's own collision check has to be carried to the end state this way.
constexpr int kInvalidArc = 2;
/// Slack when rounding the step lower bound up, so an exact multiple is not rounded past.
constexpr double kBoundSlack = 1e-9;

using Clock = std::chrono::steady_clock;

/// theta wrapped into (-pi, pi]; the identity (bit for bit) on values already in range, so a path
/// that never turns past 180 degrees has exactly the poses the Monte Carlo simulator computes.
double wrapAngle(double theta_rad) {
  if (theta_rad > kPi || theta_rad <= -kPi) {
    theta_rad -= 2.0 * kPi * std::ceil((theta_rad - kPi) / (2.0 * kPi));
  }
  return theta_rad;
}

double secondsSince(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// ---- state layout: compound (SE2, bevel) ------------------------------------------------------

const ob::SE2StateSpace::StateType& se2(const ob::State* s) {
  return *s->as<ob::CompoundState>()->as<ob::SE2StateSpace::StateType>(0);
}
ob::SE2StateSpace::StateType& se2(ob::State* s) {
  return *s->as<ob::CompoundState>()->as<ob::SE2StateSpace::StateType>(0);
}
int bevelValue(const ob::State* s) {
  return s->as<ob::CompoundState>()->as<ob::DiscreteStateSpace::StateType>(1)->value;
}
void setBevelValue(ob::State* s, int value) {
  s->as<ob::CompoundState>()->as<ob::DiscreteStateSpace::StateType>(1)->value = value;
}

TipPose toPose(const ob::State* s) {
  TipPose pose;
  pose.p_SceneTip = Point2(se2(s).getX(), se2(s).getY());
  pose.theta_rad = se2(s).getYaw();
  pose.bevel = bevelValue(s) == 1 ? Bevel::kRight : Bevel::kLeft;
  return pose;
}

void writePose(const TipPose& pose, ob::State* s) {
  se2(s).setXY(pose.p_SceneTip.x(), pose.p_SceneTip.y());
  se2(s).setYaw(wrapAngle(pose.theta_rad));
  setBevelValue(s, static_cast<int>(pose.bevel));
}

Control toControl(const oc::Control* c) {
  return c->as<oc::DiscreteControlSpace::ControlType>()->value == 1 ? Control::kFlip
                                                                    : Control::kInsert;
}

// ---- the needle's kinematics for OMPL (5.3) ---------------------------------------------------

/// One step per unit of duration: apply the control (a flip changes the bevel), then insert
/// delta along the exact arc with beta = 0. A control held for several steps flips only on the
/// first (the planner is set up with exactly one step per control, so this never arises).
class NeedlePropagator : public oc::StatePropagator {
public:
  NeedlePropagator(const oc::SpaceInformationPtr& si, const ContinuousWorkspace& world,
                   double delta_m)
      : oc::StatePropagator(si), world_(world), delta_m_(delta_m) {}

  void propagate(const ob::State* state, const oc::Control* control, double duration,
                 ob::State* result) const override {
    TipPose pose = toPose(state);
    Control u = toControl(control);
    const long steps = std::max(1L, std::lround(duration / kStepDuration));
    bool free = bevelValue(state) != kInvalidArc;
    for (long i = 0; i < steps && free; ++i) {
      free = world_.traceArc(pose, u, 0.0, delta_m_).outcome == ArcOutcome::kFree;
      pose = advanceTip(pose, u, 0.0, delta_m_, world_.problem().params.radius_m);
      u = Control::kInsert;
    }
    writePose(pose, result);
    if (!free) {
      setBevelValue(result, kInvalidArc);
    }
  }

private:
  const ContinuousWorkspace& world_;
  double delta_m_;
};

/// Valid: a real bevel (the arc leading here was free), inside the workspace, outside every
/// expanded obstacle.
class NeedleValidity : public ob::StateValidityChecker {
public:
  NeedleValidity(const ob::SpaceInformationPtr& si, const ContinuousWorkspace& world)
      : ob::StateValidityChecker(si), world_(world) {}

  bool isValid(const ob::State* state) const override {
    const int b = bevelValue(state);
    const Point2 p(se2(state).getX(), se2(state).getY());
    return (b == 0 || b == 1) && world_.inWorkspace(p) && world_.obstacleAt(p) < 0;
  }

private:
  const ContinuousWorkspace& world_;
};

/// The target disc (5.3). Satisfied exactly when ContinuousWorkspace::inTarget says so (the
/// distance is only SST's measure of an approximate solution); samples are uniform in the disc
/// with any orientation and bevel, for SST's goal bias.
class TargetDisc : public ob::GoalSampleableRegion {
public:
  TargetDisc(const ob::SpaceInformationPtr& si, const ContinuousWorkspace& world)
      : ob::GoalSampleableRegion(si), world_(world) {
    setThreshold(0.0);
  }

  double distanceGoal(const ob::State* st) const override {
    const scene::Target& t = world_.problem().target;
    const Point2 p(se2(st).getX(), se2(st).getY());
    return std::max(0.0, (p - t.position).norm() - t.radius_m);
  }
  bool isSatisfied(const ob::State* st) const override { return isSatisfied(st, nullptr); }
  bool isSatisfied(const ob::State* st, double* distance) const override {
    if (distance != nullptr) {
      *distance = distanceGoal(st);
    }
    const int b = bevelValue(st);
    return (b == 0 || b == 1) && world_.inTarget(Point2(se2(st).getX(), se2(st).getY()));
  }

  void sampleGoal(ob::State* st) const override {
    const scene::Target& t = world_.problem().target;
    const double radius = t.radius_m * std::sqrt(rng_.uniform01());
    const double phi = rng_.uniformReal(-kPi, kPi);
    se2(st).setXY(t.position.x() + radius * std::cos(phi), t.position.y() + radius * std::sin(phi));
    se2(st).setYaw(rng_.uniformReal(-kPi, kPi));
    setBevelValue(st, rng_.uniformInt(0, 1));
  }
  unsigned int maxSampleCount() const override { return std::numeric_limits<unsigned int>::max(); }

private:
  const ContinuousWorkspace& world_;
  mutable ompl::RNG rng_;  // created after the seed is set: deterministic
};

/// Path length in steps: every motion of the planner is one step of delta. Satisfied at the lower
/// bound, where no path can be shorter, so SST stops early there.
class StepCount : public ob::OptimizationObjective {
public:
  StepCount(const ob::SpaceInformationPtr& si, int lower_bound_steps)
      : ob::OptimizationObjective(si), lower_bound_steps_(lower_bound_steps) {
    description_ = "insertion steps";
  }
  ob::Cost stateCost(const ob::State*) const override { return identityCost(); }
  ob::Cost motionCost(const ob::State*, const ob::State*) const override { return ob::Cost(1.0); }
  bool isSatisfied(ob::Cost c) const override { return c.value() <= lower_bound_steps_ + 0.5; }

private:
  int lower_bound_steps_;
};

/// OMPL's INFO messages (one per improved solution) muted for the duration of a call; the
/// process-wide level is restored on exit.
class QuietOmpl {
public:
  QuietOmpl() : saved_(ompl::msg::getLogLevel()) {
    if (saved_ < ompl::msg::LOG_WARN) {
      ompl::msg::setLogLevel(ompl::msg::LOG_WARN);
    }
  }
  ~QuietOmpl() { ompl::msg::setLogLevel(saved_); }
  QuietOmpl(const QuietOmpl&) = delete;
  QuietOmpl& operator=(const QuietOmpl&) = delete;

private:
  ompl::msg::LogLevel saved_;
};

/// ompl::RNG::setSeed for the generators created from now on. After the first generator of the
/// process OMPL logs an error ("changing seed now will not lead to deterministic sampling") but
/// still re-seeds its seed generator, which is all a fresh planner needs: the message is muted.
void seedOmpl(std::uint32_t seed) {
  const ompl::msg::LogLevel level = ompl::msg::getLogLevel();
  ompl::msg::setLogLevel(ompl::msg::LOG_NONE);
  ompl::RNG::setSeed(seed);
  ompl::msg::setLogLevel(level);
}

void checkOptions(const ShortestPathOptions& o) {
  const std::string where = "planShortestPath: ";
  if (!(o.time_limit_s > 0.0) || !std::isfinite(o.time_limit_s)) {
    throw std::invalid_argument(where + "time_limit_s must be finite and > 0, got " +
                                formatNumber(o.time_limit_s));
  }
  if (o.seed == 0) {
    throw std::invalid_argument(where + "seed must be > 0 (OMPL cannot use 0)");
  }
  if (o.max_steps < 1) {
    throw std::invalid_argument(where + "max_steps must be >= 1, got " +
                                std::to_string(o.max_steps));
  }
  if (!(o.selection_radius_m >= 0.0) || !std::isfinite(o.selection_radius_m)) {
    throw std::invalid_argument(where + "selection_radius_m must be finite and >= 0, got " +
                                formatNumber(o.selection_radius_m));
  }
  if (!(o.pruning_radius_m >= 0.0) || !std::isfinite(o.pruning_radius_m)) {
    throw std::invalid_argument(where + "pruning_radius_m must be finite and >= 0, got " +
                                formatNumber(o.pruning_radius_m));
  }
  if (!(o.goal_bias >= 0.0 && o.goal_bias <= 1.0)) {
    throw std::invalid_argument(where + "goal_bias must be in [0, 1], got " +
                                formatNumber(o.goal_bias));
  }
}

std::string describe(const Point2& p) {
  return "(" + formatNumber(p.x()) + ", " + formatNumber(p.y()) + ") m";
}

}  // namespace

// ---- ShortestPath -----------------------------------------------------------------------------

std::string ShortestPath::toString() const {
  if (!found) {
    return message;
  }
  std::ostringstream s;
  s.precision(4);
  s << "shortest path: " << steps << " steps (" << length_m * 1e3 << " mm), lower bound "
    << lower_bound_steps << (proven_shortest ? " (proven shortest)" : "") << ", " << iterations
    << " iterations, " << seconds << " s";
  return s.str();
}

/// The control space of the needle for SST: SE(2) x {left, right} states, controls insert / flip
/// held for one step of delta_m, propagated and checked against `world`.
static oc::SpaceInformationPtr needleSpaceInformation(const ContinuousWorkspace& world,
                                                      double delta_m) {
  const SteeringProblem& problem = world.problem();
  const double r = problem.params.radius_m;
  // SE(2) x {left, right} (5.3). The orientation weighs r [m/rad] in the metric, so turning by one
  // arc counts as much as moving by one arc; SE2StateSpace's own 0.5 would let orientation swamp
  // position in a 10 cm workspace. The bevel weighs 0: at sigma = 0 the two bevels of a pose have
  // the same successors (both controls cost one step and pick either bevel for the next arc), so
  // SST may prune one against the other.
  auto pose_space = std::make_shared<ob::SE2StateSpace>();
  ob::RealVectorBounds bounds(2);
  bounds.setLow(0, problem.workspace_min.x());
  bounds.setLow(1, problem.workspace_min.y());
  bounds.setHigh(0, problem.workspace_max.x());
  bounds.setHigh(1, problem.workspace_max.y());
  pose_space->setBounds(bounds);
  pose_space->setSubspaceWeight(1, r);
  auto space = std::make_shared<ob::CompoundStateSpace>();
  space->addSubspace(pose_space, 1.0);
  space->addSubspace(std::make_shared<ob::DiscreteStateSpace>(0, 1), 0.0);
  space->lock();

  // Controls: 0 = insert, 1 = flip (5.3), each held for exactly one step of delta.
  auto controls = std::make_shared<oc::DiscreteControlSpace>(space, 0, 1);
  auto si = std::make_shared<oc::SpaceInformation>(space, controls);
  si->setStatePropagator(std::make_shared<NeedlePropagator>(si, world, delta_m));
  si->setStateValidityChecker(std::make_shared<NeedleValidity>(si, world));
  si->setPropagationStepSize(kStepDuration);
  si->setMinMaxControlDuration(1, 1);
  si->setup();
  return si;
}

/// Why `start` cannot start a plan ("" when it can).
static std::string startRefusal(const ContinuousWorkspace& world, const TipPose& start) {
  if (!start.p_SceneTip.allFinite() || !std::isfinite(start.theta_rad)) {
    return ("start pose is not finite (x, y, theta) = (" + formatNumber(start.p_SceneTip.x()) +
            ", " + formatNumber(start.p_SceneTip.y()) + ", " + formatNumber(start.theta_rad) + ")");
  }
  if (start.bevel != Bevel::kLeft && start.bevel != Bevel::kRight) {
    return "start bevel is neither left nor right";
  }
  if (!world.inWorkspace(start.p_SceneTip)) {
    return ("start " + describe(start.p_SceneTip) + " is outside the workspace");
  }
  if (const int o = world.obstacleAt(start.p_SceneTip); o >= 0) {
    return ("start " + describe(start.p_SceneTip) + " lies inside expanded obstacle '" +
            world.problem().obstacles[static_cast<std::size_t>(o)].name + "'");
  }
  return "";
}

ShortestPath planShortestPath(const ContinuousWorkspace& world, const TipPose& start,
                              const ShortestPathOptions& options) {
  checkOptions(options);
  const auto t0 = Clock::now();
  ShortestPath out;
  const SteeringProblem& problem = world.problem();
  const SteeringParams& params = problem.params;
  if (params.orientations < 1) {
    throw std::invalid_argument("planShortestPath: orientations N_c must be >= 1, got " +
                                std::to_string(params.orientations));
  }
  const double r = params.radius_m;
  const double delta_m = 2.0 * kPi * r / params.orientations;

  auto refuse = [&](const std::string& why) {
    out.found = false;
    out.message = "planShortestPath: " + why;
    out.seconds = secondsSince(t0);
    return out;
  };
  if (const std::string why = startRefusal(world, start); !why.empty()) {
    return refuse(why);
  }
  TipPose start_pose = start;
  start_pose.theta_rad = wrapAngle(start.theta_rad);
  out.poses.push_back(start_pose);

  // Lower bound: one step moves the tip by at most the chord 2 r sin(pi / N_c) of its arc.
  const double chord_m = 2.0 * r * std::sin(kPi / params.orientations);
  const double gap_m =
      (start.p_SceneTip - problem.target.position).norm() - problem.target.radius_m;
  if (world.inTarget(start.p_SceneTip)) {
    out.found = true;
    out.proven_shortest = true;
    out.seconds = secondsSince(t0);
    return out;
  }
  out.lower_bound_steps = std::max(1, static_cast<int>(std::ceil(gap_m / chord_m - kBoundSlack)));
  if (out.lower_bound_steps > options.max_steps) {
    out.poses.clear();
    return refuse("the target is at least " + std::to_string(out.lower_bound_steps) +
                  " steps away, more than max_steps = " + std::to_string(options.max_steps));
  }

  const QuietOmpl quiet;
  seedOmpl(options.seed);  // before any OMPL object with a generator exists (see the header)

  const oc::SpaceInformationPtr si = needleSpaceInformation(world, delta_m);
  const ob::StateSpacePtr& space = si->getStateSpace();

  auto pdef = std::make_shared<ob::ProblemDefinition>(si);
  ob::ScopedState<> start_state(space);
  writePose(start_pose, start_state.get());
  pdef->addStartState(start_state);
  pdef->setGoal(std::make_shared<TargetDisc>(si, world));
  pdef->setOptimizationObjective(std::make_shared<StepCount>(si, out.lower_bound_steps));

  auto planner = std::make_shared<oc::SST>(si);
  planner->setSelectionRadius(options.selection_radius_m > 0.0 ? options.selection_radius_m
                                                               : delta_m);
  planner->setPruningRadius(options.pruning_radius_m > 0.0 ? options.pruning_radius_m
                                                           : 0.5 * params.grid_spacing_m);
  planner->setGoalBias(options.goal_bias);
  planner->setProblemDefinition(pdef);
  planner->setup();

  // Evaluated once per SST iteration: counts them, and ends on the iteration or time budget.
  const auto deadline = t0 + std::chrono::duration_cast<Clock::duration>(
                                 std::chrono::duration<double>(options.time_limit_s));
  std::uint64_t iterations = 0;
  const ob::PlannerTerminationCondition ptc([&]() {
    if ((options.max_iterations > 0 && iterations >= options.max_iterations) ||
        Clock::now() >= deadline) {
      return true;
    }
    ++iterations;
    return false;
  });
  planner->solve(ptc);
  out.iterations = iterations;

  if (!pdef->hasExactSolution()) {
    const double closest_m = pdef->getSolutionDifference();
    std::string why = "no path to target '" + problem.target.name + "' found in " +
                      std::to_string(iterations) + " SST iterations over " +
                      formatNumber(secondsSince(t0)) +
                      " s (time_limit_s = " + formatNumber(options.time_limit_s) +
                      ", max_iterations = " + std::to_string(options.max_iterations) + ")";
    if (closest_m >= 0.0 && std::isfinite(closest_m)) {
      why += "; the closest tip came within " + formatNumber(closest_m * 1e3) +
             " mm of the target disc";
    } else {
      why += "; no step from the start is free";
    }
    out.poses.clear();
    return refuse(why + " (unreachable, or more time needed)");
  }
  const auto* path = pdef->getSolutionPath()->as<oc::PathControl>();
  for (std::size_t i = 0; i < path->getControlCount(); ++i) {
    const long steps = std::max(1L, std::lround(path->getControlDuration(i) / kStepDuration));
    out.controls.push_back(toControl(path->getControl(i)));
    for (long j = 1; j < steps; ++j) {
      out.controls.push_back(Control::kInsert);  // as NeedlePropagator holds a control
    }
  }

  // The poses again, with the propagator's arithmetic, re-checked against the world.
  TipPose pose = start_pose;
  for (std::size_t i = 0; i < out.controls.size(); ++i) {
    const ArcTrace arc = world.traceArc(pose, out.controls[i], 0.0, delta_m);
    if (arc.outcome != ArcOutcome::kFree) {
      out.controls.clear();
      out.poses.clear();
      return refuse("internal error: step " + std::to_string(i) + " of the SST path is " +
                    toString(arc.outcome) + " when traced again");
    }
    pose = advanceTip(pose, out.controls[i], 0.0, delta_m, r);
    pose.theta_rad = wrapAngle(pose.theta_rad);
    out.poses.push_back(pose);
  }
  if (!world.inTarget(pose.p_SceneTip)) {
    out.controls.clear();
    out.poses.clear();
    return refuse("internal error: the SST path ends outside the target when traced again");
  }
  out.steps = static_cast<int>(out.controls.size());
  out.length_m = out.steps * delta_m;
  out.proven_shortest = out.steps <= out.lower_bound_steps;
  if (out.steps > options.max_steps) {
    const int steps = out.steps;
    out.proven_shortest = false;
    out.controls.clear();
    out.poses.clear();
    out.steps = 0;
    out.length_m = 0.0;
    return refuse("the shortest path found has " + std::to_string(steps) +
                  " steps, more than max_steps = " + std::to_string(options.max_steps));
  }
  out.found = true;
  out.seconds = secondsSince(t0);
  return out;
}

// ---- ShortestPathTable ------------------------------------------------------------------------

std::string ShortestPathLookup::toString() const {
  std::ostringstream s;
  switch (status) {
    case Status::kOk:
      s << "ok: " << steering::toString(control) << ", " << steps_to_go << " steps to go";
      break;
    case Status::kOutsideGrid:
      s << "outside grid";
      break;
    case Status::kInTarget:
      s << "in target";
      break;
    case Status::kInObstacle:
      s << "in obstacle";
      break;
    case Status::kUnreachable:
      s << "unreachable";
      break;
  }
  return s.str();
}

ShortestPathTable::ShortestPathTable(const SteeringModel& model)
    : grid_(model.grid()), cells_(model.cells()) {
  const SteeringParams& p = model.params();
  if (p.sigma_insert_rad != 0.0 || p.sigma_flip_rad != 0.0) {
    throw std::invalid_argument(
        "ShortestPathTable: the model must be deterministic (sigma_insert_rad = sigma_flip_rad = "
        "0), got " +
        formatNumber(p.sigma_insert_rad) + " and " + formatNumber(p.sigma_flip_rad) +
        " rad; use ShortestPathTable::fromProblem()");
  }
  const auto t0 = Clock::now();
  const std::int64_t n = grid_.numStates();
  const int nc = grid_.nc;
  const auto size = static_cast<std::size_t>(n);

  // The one successor of every free state under each control (sigma = 0: a single stencil
  // entry), -1 for a failing arc; states fit in 32 bits (SteeringModel refuses >= 2^31).
  std::vector<std::int32_t> next[2];
  next[0].assign(size, -1);
  next[1].assign(size, -1);
  std::vector<std::int64_t> first(size + 1, 0);  // reversed edges, compressed rows
  for (std::int64_t pos = 0; pos < grid_.numPositions(); ++pos) {
    if (model.cell(pos) != Cell::kFree) {
      continue;
    }
    for (int b = 0; b < 2; ++b) {
      for (int k = 0; k < nc; ++k) {
        const StateId s = (pos * 2 + b) * nc + k;
        for (int u = 0; u < 2; ++u) {
          const StencilEntry* e =
              model.stencilBegin(k, static_cast<Bevel>(b), static_cast<Control>(u));
          if (model.arcValid(pos, e->arc)) {
            const StateId t = s + e->offset;
            next[u][static_cast<std::size_t>(s)] = static_cast<std::int32_t>(t);
            ++first[static_cast<std::size_t>(t) + 1];
          }
        }
      }
    }
  }
  for (std::size_t i = 0; i < size; ++i) {
    first[i + 1] += first[i];
  }
  std::vector<std::int32_t> predecessors(static_cast<std::size_t>(first[size]));
  {
    std::vector<std::int64_t> fill(first.begin(), first.end() - 1);
    for (std::size_t s = 0; s < size; ++s) {
      for (int u = 0; u < 2; ++u) {
        const std::int32_t t = next[u][s];
        if (t >= 0) {
          predecessors[static_cast<std::size_t>(fill[static_cast<std::size_t>(t)]++)] =
              static_cast<std::int32_t>(s);
        }
      }
    }
  }

  // Breadth-first from every state of every target cell (steps-to-go 0, absorbing: 5.4.2).
  steps_.assign(size, -1);
  std::vector<std::int32_t> queue;
  queue.reserve(size);
  for (std::int64_t pos = 0; pos < grid_.numPositions(); ++pos) {
    if (model.cell(pos) == Cell::kTarget) {
      for (StateId s = pos * 2 * nc; s < (pos + 1) * 2 * nc; ++s) {
        steps_[static_cast<std::size_t>(s)] = 0;
        queue.push_back(static_cast<std::int32_t>(s));
      }
    }
  }
  for (std::size_t head = 0; head < queue.size(); ++head) {
    const auto s = static_cast<std::size_t>(queue[head]);
    for (std::int64_t i = first[s]; i < first[s + 1]; ++i) {
      const auto q = static_cast<std::size_t>(predecessors[static_cast<std::size_t>(i)]);
      if (steps_[q] < 0) {
        steps_[q] = steps_[s] + 1;
        queue.push_back(static_cast<std::int32_t>(q));
      }
    }
  }

  // The control starting a shortest path; ties keep insert (as value_iteration.h).
  bits_.assign((size + 63) / 64, 0);
  auto to_go = [&](std::int32_t t) {
    return t < 0 || steps_[static_cast<std::size_t>(t)] < 0
               ? std::numeric_limits<std::int32_t>::max()
               : steps_[static_cast<std::size_t>(t)];
  };
  for (std::size_t s = 0; s < size; ++s) {
    if (steps_[s] <= 0) {
      continue;  // target, obstacle, failure or unreachable
    }
    ++reachable_;
    max_steps_ = std::max(max_steps_, static_cast<int>(steps_[s]));
    if (to_go(next[1][s]) < to_go(next[0][s])) {
      bits_[s >> 6] |= std::uint64_t{1} << (s & 63);
    }
  }
  seconds_ = secondsSince(t0);
}

ShortestPathTable ShortestPathTable::fromProblem(SteeringProblem problem, int threads) {
  problem.params.sigma_insert_rad = 0.0;
  problem.params.sigma_flip_rad = 0.0;
  return ShortestPathTable(SteeringModel(std::move(problem), threads));
}

ShortestPathLookup ShortestPathTable::lookup(const TipPose& pose) const noexcept {
  ShortestPathLookup out;
  const StateId s = grid_.nearestState(pose);
  if (s < 0) {
    return out;
  }
  out.state = s;
  switch (cell(s / (2 * std::int64_t{grid_.nc}))) {
    case Cell::kTarget:
      out.status = ShortestPathLookup::Status::kInTarget;
      out.steps_to_go = 0;
      return out;
    case Cell::kObstacle:
      out.status = ShortestPathLookup::Status::kInObstacle;
      return out;
    case Cell::kFree:
      break;
  }
  const int steps = stepsToGo(s);
  if (steps < 0) {
    out.status = ShortestPathLookup::Status::kUnreachable;
    return out;
  }
  out.status = ShortestPathLookup::Status::kOk;
  out.steps_to_go = steps;
  out.control = control(s);
  return out;
}

SteeringPolicy shortestPathPolicy(const ShortestPathTable& table) {
  return [&table](const TipPose& pose, int) {
    const ShortestPathLookup l = table.lookup(pose);
    return l ? l.control : Control::kInsert;
  };
}

}  // namespace needle_guidance::steering
