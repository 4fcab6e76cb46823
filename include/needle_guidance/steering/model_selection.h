// Choosing the discretisation from the P_s accuracy a scene asks for: a ladder of
// grid spacings, coarse to fine by a factor sqrt(2) (twice the states per step), each solved;
// the error of a model is estimated from the change of P_s against the previous, coarser model
// (Richardson: for an error of order p in Delta, e(Delta) = D / (r^p - 1) with r = sqrt(2); p = 2,
// the order of bilinear interpolation, gives e = D). The first model whose estimate meets the
// tolerance is a candidate. A candidate is accepted only once a Monte Carlo of the continuous
// needle at a fixed-seed sample of start states (the entry line, the best distinct starts the
// procedure chooses from, and starts near every workspace edge and obstacle, where rounding to
// the grid is worst) confirms it (checkModel); else the ladder goes on to the next rung. The finest
// rung that fits the memory limit is checked too, so a tolerance the change estimate cannot reach
// is still met when the continuous needle confirms it. Not in the dissertation (5.4.2 fixes Delta
// by hand).
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "needle_guidance/status.h"
#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/steering_model.h"
#include "needle_guidance/steering/value_iteration.h"

namespace needle_guidance::steering {

struct SelectionOptions {
  double ps_tolerance = 0.005;     ///< mean |P_s error| wanted in each checked group, in (0, 1)
  double memory_limit_mb = 500.0;  ///< refuse models whose estimated footprint exceeds this [MB]
  int max_steps = 10;              ///< rungs of the ladder at most (grids and transitions together)
  SolverOptions solver;            ///< for every solve
  int threads = 2;                 ///< model building
  StartOptions start;              ///< the entry line the error is measured on
  /// Monte Carlo trials per start of the model check; 0 = from the tolerance (checkTrials), < 0 =
  /// no check (the change estimate alone decides).
  std::int64_t check_trials = 0;
  std::uint64_t check_seed = 31;  ///< trial i of every checked start uses (check_seed, i)
};

/// The Monte Carlo check of one solved model: predicted P_s against the continuous needle
/// following the table's policy, at a fixed sample of start states.
struct ModelCheck {
  bool run = false;
  std::int64_t trials_per_start = 0;  ///< trials run per start (fewer when stopped early)
  std::int64_t trials_requested = 0;  ///< trials per start the check would run to the end
  int entry_starts = 0;               ///< non-trivial entry-line starts scored (both ends included)
  int top_starts = 0;                 ///< best distinct starts scored
  int boundary_starts = 0;            ///< near-boundary starts scored (nearBoundaryStarts)
  /// Mean over the group of |predicted - Monte Carlo| with its binomial noise removed,
  /// sqrt(max(0, gap^2 - p (1 - p) / n)) per start: an estimate of the group's mean |P_s error|
  /// that the Monte Carlo noise does not inflate. NaN when the group has no non-trivial start.
  double gap_entry = 0.0;
  double gap_top = 0.0;
  double gap_boundary = 0.0;
  double max_abs_gap = 0.0;  ///< largest measured |gap| of any start (noise included)
  double tolerance = 0.0;
  bool passed = false;  ///< every group's mean gap <= tolerance
  /// max over the groups of (mean gap - the bias of its noise correction - 3 standard errors -
  /// tolerance): > 0 means the check fails whatever more trials would show (about 0.1 % wrong).
  double clear_fail_margin = -1.0;
  bool clearlyFailed() const { return clear_fail_margin > 0.0; }
  double seconds = 0.0;
  /// "Monte Carlo check (80 starts x 10000 trials): mean gap 0.0031 on the entry line, 0.0024 at
  /// the best starts, 0.0040 near boundaries, tolerance 0.005: passed".
  std::string toString() const;
};

/// Trials per start of the model check for a tolerance: 0.25 / tolerance^2 (the binomial
/// standard error at P_s 0.5 is half the tolerance) within [2000, 10000].
std::int64_t checkTrials(double tolerance);

/// A start state near a boundary and the boundary it is near.
struct NearBoundaryStart {
  std::string group;  ///< "edge" (a workspace edge or an end of the start range) | "obstacle"
  TipPose pose;
};

/// Distance of the near-boundary starts from a workspace edge or an expanded obstacle edge [m].
constexpr double kNearBoundaryDistance_m = 2.5e-3;

/// The start range's heights within the workspace [m]: lo = max(start.min_height_m, workspace's
/// lowest y), hi = min(start.max_height_m, its highest y).
struct HeightRange {
  double lo = 0.0;
  double hi = 0.0;
};
HeightRange startRange(const SteeringProblem& problem, const StartOptions& start);

/// The entry-line starts x = start.start_x_m at each of `heights_m` within the start range and
/// the workspace, at -18, 0, 18 degrees and both bevels (heights outside are skipped).
std::vector<TipPose> entryLineStarts(const SteeringProblem& problem, const StartOptions& start,
                                     const std::vector<double>& heights_m);

/// Starts within 5 mm of every boundary, inside the free space: on the entry line 1.5 and 4 mm
/// from both ends of the start range (entryLineStarts); kNearBoundaryDistance_m inside each
/// workspace edge at a quarter, half and three quarters of it; kNearBoundaryDistance_m outside
/// the middle of each expanded obstacle edge. An interior start takes the orientation and bevel
/// of the highest P_s at its grid point (the states a good policy passes through); interior
/// points in an obstacle or the target, off the grid, or whose every state is below P_s 0.01 are
/// left out. Shared by the model check and the benchmark's truth check.
std::vector<NearBoundaryStart> nearBoundaryStarts(const StartOptions& start,
                                                  const PolicyTable& table,
                                                  const ContinuousWorkspace& world);

/// Scores `table` against the continuous needle in three groups: the entry-line starts (heights
/// 2.5 mm inside both ends of the start range and at 1/6 .. 5/6 of it, angles -20, 0, 20 degrees,
/// both bevels), the 4 best distinct starts (distinctBestStarts) and the near-boundary starts
/// (nearBoundaryStarts), each predicted at its own pose (ExactPosePrediction, the table's
/// control); starts where prediction and Monte Carlo are both below 0.01 are left out.
/// Sequential: a quarter of the trials first; a check
/// that has then clearly failed (ModelCheck::clearlyFailed) stops there, any other runs the rest
/// (trials i from the quarter on, so the result is that of one run of `trials`). Throws
/// std::invalid_argument for trials < 1.
ModelCheck checkModel(const SteeringModel& model, const PolicyTable& table,
                      const StartOptions& start, double tolerance, std::int64_t trials,
                      std::uint64_t seed, int threads = 2);

/// One rung of the ladder.
struct ModelRung {
  double grid_spacing_m = 0.0;
  TransitionModel transition_model = TransitionModel::kRounded;
  int orientation_subdivision = 1;
  std::int64_t states = 0;
  double build_s = 0.0;
  double solve_s = 0.0;
  int sweeps = 0;
  /// Mean |P_s - P_s of the previous rung| over the evaluation states (of the finer accepted
  /// model for a coarsened rung); NaN on the first rung and the first of new transitions.
  double change_vs_coarser = 0.0;
  double estimated_error = 0.0;  ///< the estimate of this rung's mean |P_s error| (NaN first)
  int evaluation_states = 0;     ///< states where either rung predicts P_s >= 0.01
  ModelCheck check;              ///< run when this rung was a candidate
  /// Solved after a finer model was accepted: a coarser grid of its transitions (coarsen).
  bool coarsened = false;
  bool chosen = false;  ///< the model chosen
};

/// The model chosen for a tolerance, with its table.
struct ModelChoice {
  SteeringProblem problem;  ///< with the chosen grid spacing
  std::unique_ptr<const SteeringModel> model;
  std::unique_ptr<PolicyTable> table;
  double estimated_error = 0.0;  ///< of the chosen rung
  ModelCheck check;              ///< the chosen rung's Monte Carlo check (run = false: none)
  double total_s = 0.0;          ///< build + solve of every rung [s]
  double peak_estimate_mb = 0.0;
  std::vector<ModelRung> ladder;
  /// One line: "interpolated, grid 0.71 mm, s = 3, 4.8 M states, estimated P_s error 0.003 ..."
  std::string toString() const;
};

/// Estimated resident memory of building and solving a model with these parameters [MB].
double estimatedModelMb(const SteeringProblem& problem);

/// The continuous poses the error is measured at: the entry line x = start.start_x_m, heights
/// every 2.5 mm between the start heights (within the workspace), angles every 9 degrees in
/// [-36, 36] degrees and both bevels.
std::vector<TipPose> evaluationPoses(const SteeringProblem& problem, const StartOptions& start);

/// Mean |P_s(fine) - P_s(coarse)| at the poses where either predicts >= 0.01 (table look-ups,
/// as the truth check does); `count` receives how many there were.
double meanAbsChange(const PolicyTable& fine, const PolicyTable& coarse,
                     const std::vector<TipPose>& poses, int& count);

/// True when the last rung's check failed a group (entry line, best starts, near boundaries) that
/// the previous checked rung of the same transitions, a coarser grid, failed too with no smaller
/// mean gap: a finer grid did not shrink that error, so the grid does not explain it and
/// chooseModel refines the transitions instead. False when no earlier rung of these transitions
/// was checked.
bool finerGridDidNotHelp(const std::vector<ModelRung>& ladder);

/// Solves the ladder from problem.params.grid_spacing_m (the coarsest) until a rung's estimate
/// meets options.ps_tolerance and its checkModel passes (or, when the next rung would exceed
/// memory_limit_mb or max_steps, the last rung's check passes whatever its estimate). A failed
/// check the grid's estimated error does not explain (a group's mean gap above twice the
/// estimate, or finerGridDidNotHelp) refines the transitions instead (rounded -> interpolated ->
/// s doubled); when memory stops the grid, the transitions are refined once
/// within the last rung's memory (s doubled on a grid sqrt(2) coarser). An accepted model whose
/// transitions came in on a finer grid is then coarsened: the grid sqrt(2) coarser with the same
/// transitions (never coarser than problem.params.grid_spacing_m) is taken while its estimate
/// (its change to the finer, times 2) meets the tolerance and its check passes. Refuses
/// (StatusCode::kRefused, naming the tolerance, the finest estimate and check reached and why)
/// otherwise; then nothing is kept.
/// Throws std::invalid_argument for a tolerance outside (0, 1).
Result<ModelChoice> chooseModel(const SteeringProblem& problem, const SelectionOptions& options);

}  // namespace needle_guidance::steering

namespace needle_guidance::steering {

/// A solved or loaded policy and where it came from (the node, the procedure, the bench and the
/// guided trial share this one definition).
struct PolicySource {
  std::unique_ptr<const SteeringModel> model;
  std::unique_ptr<const PolicyTable> table;
  std::string source;  ///< "solved" | "loaded"
  /// The chosen model's estimated mean |P_s error| (NaN: not estimated, when ps_tolerance is 0 or
  /// the chosen model was the first of its transitions; its ModelCheck then measured it).
  double estimated_error = 0.0;
  double seconds = 0.0;           ///< wall time of this call [s]
  std::vector<ModelRung> ladder;  ///< the rungs solved (empty when loaded or fixed)
  ModelCheck check;               ///< the chosen model's Monte Carlo check (run = false: none)
  std::string note;               ///< where the table was saved, or why not
  /// "interpolated, grid 0.707 mm, s = 3, 4771440 states, estimated P_s error 0.0070, solved in
  /// 2.4 s (4 models)".
  std::string description() const;
};

/// The problem of a table re-solved for other noise (AdaptivePolicy): `chosen` (the model a
/// tolerance chose: its grid is kept, ps_tolerance set to 0) assuming sigma_i, sigma_r [rad].
/// solveOrLoad(withNoise(...), scene, table_dir, ...) loads the table steering_policy saved after
/// a re-solve (AdaptationOptions::table_dir), or solves it. Throws std::invalid_argument for a
/// negative or non-finite sigma.
SteeringProblem withNoise(const SteeringProblem& chosen, double sigma_insert_rad,
                          double sigma_flip_rad);

/// Writes `table` to `path` through a temporary file and a rename (readers never see half a
/// table). Creates the folder. Throws std::runtime_error / std::filesystem errors on failure.
void saveTableAtomically(const PolicyTable& table, const std::string& path);

/// The policy for `problem`. With problem.ps_tolerance > 0: the model recorded for this problem
/// and tolerance in table_dir and its table, if both load; else chooseModel (refusals come back
/// as the status), saving the table and the record. With ps_tolerance 0: problem.params as
/// given, its table loaded or solved and saved. table_dir "" = no files. force = solve even if
/// files exist. options.ps_tolerance is taken from the problem.
Result<PolicySource> solveOrLoad(const SteeringProblem& problem, const std::string& scene_name,
                                 const std::string& table_dir, SelectionOptions options,
                                 bool force = false);

}  // namespace needle_guidance::steering
