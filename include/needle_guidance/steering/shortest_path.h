// The shortest-path baseline of dissertation 5.1 and 5.5 (figures 5.1(a), 5.5(a)): the shortest
// feasible needle path under the assumption of deterministic motion, which the MDP of 5.4 is
// compared against ("over 30 % better P_s than shortest-path planning", 5.1).
//
// Two forms of the same baseline:
//   - planShortestPath(): an open-loop plan in the continuous world (exact constant-curvature
//     arcs of length delta = 2 pi r / N_c, continuous_workspace.h) found with OMPL's SST control
//     planner; executed with openLoopPolicy(plan.controls) (monte_carlo.h).
//   - ShortestPathTable: the feedback form. Re-planning with OMPL after every imaged step of a
//     10,000-trial Monte Carlo run would be far too slow, so the table holds the deterministic
//     steps-to-go of every state of the MDP's own discretisation (5.4.2, sigma = 0), computed by
//     one backward breadth-first search; shortestPathPolicy() then steers along a shortest path
//     from wherever the tip is imaged, with an O(1) look-up like the MDP's (5.4.3).
// Plain C++; no ROS, and no OMPL types here (OMPL is a private dependency of the core library).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance::steering {

// ---- open loop: OMPL --------------------------------------------------------------------------

/// Settings of planShortestPath().
struct ShortestPathOptions {
  /// Wall-clock budget of the SST planner [s], finite and > 0. SST improves its best path until
  /// the budget is spent, unless the path reaches the lower bound of ShortestPath first.
  double time_limit_s = 2.0;
  /// Optional budget of planner iterations (0: none). With an iteration budget that runs out
  /// before the time limit the plan depends on the seed only, not on the machine's speed.
  std::uint64_t max_iterations = 0;
  /// Seed of OMPL's random number generators, > 0. OMPL seeds every generator from one
  /// process-wide seed generator (ompl::RNG::setSeed), which OMPL means to be set once before the
  /// first generator exists. planShortestPath() re-seeds it at the start of every call (OMPL 1.5
  /// honours that for the generators created afterwards, and all of the planner's are), so one
  /// call with one seed and an iteration budget gives the same plan in any process; it also
  /// changes the seeds of OMPL generators created later elsewhere in the process.
  std::uint32_t seed = 1;
  /// Longest acceptable plan [steps], >= 1; a longer one comes back as not found.
  int max_steps = 200;
  /// SST's selection radius delta_BN in the planner's state metric [m] (position, plus r times the
  /// orientation difference, so one step of delta moves a state by about 2 delta); 0 picks
  /// delta = 2 pi r / N_c. Finite and >= 0.
  double selection_radius_m = 0.0;
  /// SST's pruning radius delta_s in the same metric [m]: of two tree nodes this close the
  /// costlier one is pruned. Must stay well below the narrowest gap the path has to thread; 0
  /// picks half the grid spacing Delta of problem().params. Finite and >= 0.
  double pruning_radius_m = 0.0;
  /// Probability of extending towards a sample in the target disc, in [0, 1].
  double goal_bias = 0.05;
};

/// Result of planShortestPath(): found, or a message saying why not (never both).
struct ShortestPath {
  bool found = false;
  /// Why no path came back (bad start, nothing found in time, too long); empty when found.
  std::string message;
  /// One control per step of delta, in order (empty when the start is in the target).
  std::vector<Control> controls;
  /// The start (theta wrapped into (-pi, pi]) and the tip after every step: controls.size() + 1
  /// poses when found, the last one in the target disc [m, rad].
  std::vector<TipPose> poses;
  int steps = 0;          ///< controls.size()
  double length_m = 0.0;  ///< inserted length, steps * delta [m]
  /// No feasible path can be shorter: the distance from the start to the target disc over the
  /// chord 2 r sin(pi / N_c) of one step, rounded up [steps].
  int lower_bound_steps = 0;
  /// steps == lower_bound_steps: the plan is provably shortest (SST then stops early).
  bool proven_shortest = false;
  std::uint64_t iterations = 0;  ///< SST iterations run
  double seconds = 0.0;          ///< wall time of the call [s]

  explicit operator bool() const { return found; }
  /// E.g. "shortest path: 12 steps (94.2 mm), lower bound 11, 0.41 s" or the message.
  std::string toString() const;
};

/// The shortest feasible path from `start` to the target disc of world.problem() under
/// deterministic motion (sigma = 0; 5.1, 5.5), found by OMPL's SST (asymptotically near-optimal
/// kinodynamic planner) with the needle's kinematics (5.3): the state is SE(2) (x, y, theta) plus
/// the bevel b in {0, 1}; the two discrete controls insert / flip each advance the tip by one arc
/// of length delta = 2 pi r / N_c (advanceTip with beta = 0); an arc counts only if
/// world.traceArc() finds it free, and success is judged at the end of a step, where the tip is
/// imaged (5.3). The cost is the number of steps (all steps have length delta).
/// Expected failures come back as found = false with a message, never as NaN or a throw: a
/// non-finite start, a start outside the workspace or inside an expanded obstacle, no path within
/// the time limit (e.g. an unreachable target), a path longer than max_steps. A start in the
/// target is found with 0 steps. Not safe to call from several threads at once (OMPL's seed
/// generator and log level are process-wide; OMPL's INFO messages are muted during the call).
/// Throws std::invalid_argument for nonsense options (time_limit_s <= 0 or not finite, seed 0,
/// max_steps < 1, negative or non-finite radii, goal_bias outside [0, 1]).
/// @param[in] world continuous workspace; its params give r and N_c (its sigmas are ignored)
/// @param[in] start tip pose in frame scene [m, rad]
ShortestPath planShortestPath(const ContinuousWorkspace& world, const TipPose& start,
                              const ShortestPathOptions& options = {});

// ---- closed loop: the discretisation's steps-to-go --------------------------------------------

/// The result of a ShortestPathTable look-up (expected failures come back as a status).
struct ShortestPathLookup {
  enum class Status {
    kOk,           ///< control and steps_to_go valid
    kOutsideGrid,  ///< the rounded tip position is off the grid (or the pose is not finite)
    kInTarget,     ///< the rounded tip is in a target cell: stop inserting (steps_to_go = 0)
    kInObstacle,   ///< the rounded tip is in an expanded obstacle
    kUnreachable,  ///< no deterministic path from the rounded state reaches the target
  };
  Status status = Status::kOutsideGrid;
  Control control = Control::kInsert;  ///< first control of a shortest path (kInsert unless kOk)
  int steps_to_go = -1;  ///< steps of a shortest path; 0 in the target, -1 when none [steps]
  StateId state = -1;    ///< the rounded state, -1 when off the grid

  explicit operator bool() const { return status == Status::kOk; }
  /// E.g. "ok: flip, 7 steps to go" or "unreachable".
  std::string toString() const;
};

/// Steps-to-go of every state of the MDP's discretisation under deterministic motion (5.4.2 with
/// sigma_i = sigma_r = 0, so each control has exactly one outcome), by breadth-first search
/// backwards from the target cells over the reversed transitions, and the control that starts a
/// shortest path (ties keep kInsert, as in the MDP solver). With unit steps BFS gives exact
/// shortest paths in O(N) time; the states with finite steps-to-go are exactly those with
/// P_s = 1 in value iteration at sigma = 0.
class ShortestPathTable {
public:
  /// Builds the table from a deterministic model. Throws std::invalid_argument if the model's
  /// sigma_insert_rad or sigma_flip_rad is not 0 (use fromProblem() to zero them).
  explicit ShortestPathTable(const SteeringModel& deterministic_model);
  /// Builds SteeringModel(problem with both sigmas set to 0, threads) and the table from it.
  /// Throws what SteeringModel throws.
  static ShortestPathTable fromProblem(SteeringProblem problem, int threads = 2);

  const GridSpec& grid() const { return grid_; }
  /// Steps-to-go of a state (unchecked index): 0 in target cells, -1 if unreachable [steps].
  int stepsToGo(StateId s) const { return steps_[static_cast<std::size_t>(s)]; }
  /// First control of a shortest path from a state (unchecked index; kInsert if unreachable).
  Control control(StateId s) const {
    return (bits_[static_cast<std::size_t>(s) >> 6] >> (s & 63)) & 1u ? Control::kFlip
                                                                      : Control::kInsert;
  }
  Cell cell(std::int64_t position) const {
    return static_cast<Cell>(cells_[static_cast<std::size_t>(position)]);
  }
  /// Free (non-target, non-obstacle) states from which the target is reachable.
  std::int64_t reachableStates() const { return reachable_; }
  /// Largest finite steps-to-go [steps].
  int maxStepsToGo() const { return max_steps_; }
  /// Wall time of the search (not of building the model) [s].
  double buildSeconds() const { return seconds_; }

  /// Shortest-path control for a continuous tip pose, by rounding to the nearest state (5.4.2):
  /// O(1), no allocation, never throws.
  ShortestPathLookup lookup(const TipPose& pose) const noexcept;

private:
  GridSpec grid_;
  std::vector<std::int32_t> steps_;
  std::vector<std::uint64_t> bits_;
  std::vector<std::uint8_t> cells_;
  std::int64_t reachable_ = 0;
  int max_steps_ = 0;
  double seconds_ = 0.0;
};

/// The closed-loop shortest-path policy: the table's control at the imaged pose, kInsert where
/// the table defines none (off the grid, in the target or an obstacle, unreachable). The table
/// must outlive the returned function; safe to call from several threads.
SteeringPolicy shortestPathPolicy(const ShortestPathTable& table);

}  // namespace needle_guidance::steering
