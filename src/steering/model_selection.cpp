// Choosing the discretisation from a P_s tolerance (see model_selection.h).
#include "needle_guidance/steering/model_selection.h"
#include "needle_guidance/math.h"

#include <unistd.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <optional>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/format.h"
#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/exact_pose_prediction.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/start_verification.h"

namespace needle_guidance::steering {
namespace {

/// Spacing ratio between rungs: twice the positions per rung.
const double kRatio = std::sqrt(2.0);
/// Assumed order of the error in Delta (bilinear interpolation of a smooth P_s): with kRatio,
/// e = D / (kRatio^2 - 1) = D.
constexpr double kOrder = 2.0;
/// Start states whose P_s both rungs put below this are left out (they agree trivially).
constexpr double kTrivialPs = 0.01;
/// Bytes per state while building and solving (values, controls, snapshot, end masks, policy
/// bits, plus the coarser rung's table kept for the comparison), measured on steering_workspace.
constexpr double kBytesPerState = 14.0;
constexpr double kBaseMb = 50.0;  ///< the process without the model [MB]
constexpr double kEvalStep_m = 2.5e-3;
constexpr double kEvalAngleStep_rad = 9.0 * kPi / 180.0;
constexpr int kEvalAngles = 4;  ///< -36 .. 36 degrees

/// Model check: entry-line starts this far inside both ends of the start range [m].
constexpr double kCheckEdge_m = 2.5e-3;
/// Model check: entry-line angles [deg] and the best distinct starts scored.
constexpr double kCheckAngles_deg[] = {-20.0, 0.0, 20.0};
constexpr int kCheckTopStarts = 4;
/// entryLineStarts' angles [deg], and the distances of the near-boundary entry-line starts from
/// the ends of the start range [m] (all within 5 mm of the edge).
constexpr double kEntryLineAngles_deg[] = {-18.0, 0.0, 18.0};
constexpr double kEntryEndDistances_m[] = {1.5e-3, 4e-3};
/// Model check trials per start: 0.25 / tolerance^2 within these bounds.
constexpr std::int64_t kMinCheckTrials = 2000;
constexpr std::int64_t kMaxCheckTrials = 10000;

double secondsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

/// The entry-line starts of checkModel.
/// Poses x = start_x_m at each height, each angle [deg] rounded to a multiple of `quantum` [rad]
/// (0: exact), both bevels.
std::vector<TipPose> entryPoses(const StartOptions& start, const std::vector<double>& heights_m,
                                const std::vector<double>& angles_deg, double quantum) {
  std::vector<TipPose> poses;
  for (double y : heights_m) {
    for (double a : angles_deg) {
      for (Bevel b : {Bevel::kLeft, Bevel::kRight}) {
        TipPose pose;
        pose.p_SceneTip = Point2(start.start_x_m, y);
        pose.theta_rad = a * kPi / 180.0;
        if (quantum > 0.0) {
          pose.theta_rad = std::round(pose.theta_rad / quantum) * quantum;
        }
        pose.bevel = b;
        poses.push_back(pose);
      }
    }
  }
  return poses;
}

std::vector<TipPose> checkPoses(const SteeringProblem& problem, const StartOptions& start) {
  // Angles on the model's orientations: the check measures the P_s of the model's states.
  const double quantum =
      2.0 * kPi / (problem.params.orientations * problem.params.orientation_subdivision);
  const auto [lo, hi] = startRange(problem, start);
  std::vector<double> heights;
  if (hi - lo > 2.0 * kCheckEdge_m) {
    heights = {lo + kCheckEdge_m, hi - kCheckEdge_m};
  }
  for (int i = 1; i <= 5; ++i) {
    heights.push_back(lo + (hi - lo) * i / 6.0);
  }
  return entryPoses(start, heights, {std::begin(kCheckAngles_deg), std::end(kCheckAngles_deg)},
                    quantum);
}

/// Mean noise-corrected |gap| of a group: the mean of sqrt(max(0, gap^2 - p (1 - p) / n)); NaN if
/// empty.
struct GapSum {
  double sum = 0.0;
  int count = 0;
  void add(double predicted, double rate, std::int64_t trials) {
    const double p = std::clamp(predicted, 0.0, 1.0);
    const double gap = predicted - rate;
    sum += std::sqrt(std::max(0.0, gap * gap - p * (1.0 - p) / double(trials)));
    ++count;
  }
  double mean() const { return count > 0 ? sum / count : std::numeric_limits<double>::quiet_NaN(); }
};

/// A check that fails by more than this multiple of the rung's estimated error (the change with
/// the grid) has an error the grid does not explain: the transitions are refined instead.
constexpr double kGridErrorShare = 2.0;

bool sameTransitions(const SteeringParams& a, const SteeringParams& b) {
  return a.transition_model == b.transition_model &&
         a.orientation_subdivision == b.orientation_subdivision;
}

/// The next finer transitions at the same grid: rounded -> interpolated, then s doubled (at
/// most 64); false when there is none.
bool refineTransitions(SteeringParams& params) {
  if (params.transition_model == TransitionModel::kRounded) {
    params.transition_model = TransitionModel::kInterpolated;
    return true;
  }
  if (params.orientation_subdivision * 2 > 64) {
    return false;
  }
  params.orientation_subdivision *= 2;
  return true;
}

/// Trials of the model check's first stage: 1 / kCheckStages of them.
constexpr std::int64_t kCheckStages = 4;
/// A first stage fails the check when a group's mean gap, less the bias of its noise correction
/// and kClearFailZ standard errors, still exceeds the tolerance.
constexpr double kClearFailZ = 3.0;
/// Upper bound of the mean of sqrt(max(0, g^2 - s^2)) for g ~ N(0, s^2), in units of s (0.40):
/// the noise correction's bias when a start has no error at all.
constexpr double kCorrectionBias = 0.41;

/// The check's groups, in ModelCheck's order.
enum CheckGroup { kEntryGroup = 0, kTopGroup = 1, kBoundaryGroup = 2, kCheckGroups = 3 };

/// The check's figures from the Monte Carlo results so far (Checked: pose, predicted, group, mc).
template <typename Checked>
ModelCheck scoreCheck(const std::vector<Checked>& starts, double tolerance) {
  ModelCheck out;
  out.run = true;
  out.tolerance = tolerance;
  GapSum group[kCheckGroups];
  double noise[kCheckGroups] = {}, variance[kCheckGroups] = {};
  for (const Checked& c : starts) {
    const double rate = c.mc.rate();
    if (c.predicted < kTrivialPs && rate < kTrivialPs) {
      continue;
    }
    const int g = c.group;
    group[g].add(c.predicted, rate, c.mc.trials);
    const double p = std::clamp(c.predicted, 0.0, 1.0);
    const double v = p * (1.0 - p) / double(c.mc.trials);
    noise[g] += std::sqrt(v);
    variance[g] += v;
    out.max_abs_gap = std::max(out.max_abs_gap, std::abs(c.predicted - rate));
  }
  out.entry_starts = group[kEntryGroup].count;
  out.top_starts = group[kTopGroup].count;
  out.boundary_starts = group[kBoundaryGroup].count;
  out.gap_entry = group[kEntryGroup].mean();
  out.gap_top = group[kTopGroup].mean();
  out.gap_boundary = group[kBoundaryGroup].mean();
  // An empty group (no start with P_s >= 0.01) has nothing to contradict.
  out.passed =
      !(out.gap_entry > tolerance) && !(out.gap_top > tolerance) && !(out.gap_boundary > tolerance);
  for (int g = 0; g < kCheckGroups; ++g) {
    if (group[g].count > 0) {
      const double n = group[g].count;
      const double low = group[g].mean() - kCorrectionBias * noise[g] / n -
                         kClearFailZ * std::sqrt(variance[g]) / n;
      out.clear_fail_margin = std::max(out.clear_fail_margin, low - tolerance);
    }
  }
  return out;
}

/// The state of highest P_s at the grid point nearest p (any orientation and bevel), as a pose
/// at p; nullopt when p is off the grid, not free, or every state there is below kTrivialPs.
std::optional<TipPose> bestPoseAt(const PolicyTable& table, const Point2& p) {
  TipPose probe;
  probe.p_SceneTip = p;
  const ControlLookup l = table.lookup(probe);
  if (l.status != ControlLookup::Status::kOk) {
    return std::nullopt;
  }
  const GridSpec& g = table.grid();
  int ix = 0, iy = 0, k = 0;
  Bevel b = Bevel::kLeft;
  g.decode(l.state, ix, iy, k, b);
  StateId best = -1;
  for (int bevel = 0; bevel < 2; ++bevel) {
    for (int kk = 0; kk < g.nc; ++kk) {
      const StateId s = g.state(ix, iy, kk, static_cast<Bevel>(bevel));
      if (best < 0 || table.value(s) > table.value(best)) {
        best = s;
      }
    }
  }
  if (table.value(best) < kTrivialPs) {
    return std::nullopt;
  }
  TipPose pose = g.pose(best);
  pose.p_SceneTip = p;
  return pose;
}

/// A rung built and solved, with its table and model.
struct SolvedRung {
  ModelRung rung;
  std::unique_ptr<const SteeringModel> model;
  std::unique_ptr<PolicyTable> table;
};

SolvedRung solveRung(const SteeringProblem& rung_problem, const SelectionOptions& options) {
  SolvedRung out;
  const SteeringParams& params = rung_problem.params;
  out.rung.grid_spacing_m = params.grid_spacing_m;
  out.rung.transition_model = params.transition_model;
  out.rung.orientation_subdivision = params.orientation_subdivision;
  const auto tb = std::chrono::steady_clock::now();
  out.model = std::make_unique<const SteeringModel>(rung_problem, options.threads);
  out.rung.build_s = secondsSince(tb);
  out.rung.states = out.model->numStates();
  SolveStats stats;
  out.table =
      std::make_unique<PolicyTable>(solveValueIteration(*out.model, options.solver, &stats));
  out.rung.solve_s = stats.seconds;
  out.rung.sweeps = stats.sweeps;
  out.rung.change_vs_coarser = std::numeric_limits<double>::quiet_NaN();
  out.rung.estimated_error = std::numeric_limits<double>::quiet_NaN();
  return out;
}

/// True when the ladder already holds a rung of these transitions at this grid.
bool solvedBefore(const std::vector<ModelRung>& ladder, const SteeringParams& params) {
  for (const ModelRung& r : ladder) {
    if (r.transition_model == params.transition_model &&
        r.orientation_subdivision == params.orientation_subdivision &&
        std::abs(r.grid_spacing_m / params.grid_spacing_m - 1.0) < 1e-9) {
      return true;
    }
  }
  return false;
}

}  // namespace

std::string ModelCheck::toString() const {
  if (!run) {
    return "no Monte Carlo check";
  }
  auto gap = [](double v) { return std::isnan(v) ? std::string("undefined") : formatNumber(v, 2); };
  std::ostringstream out;
  out << "Monte Carlo check (" << entry_starts + top_starts + boundary_starts << " starts x "
      << trials_per_start << " trials"
      << (trials_per_start < trials_requested ? ", stopped: clearly failed" : "") << "): mean gap "
      << gap(gap_entry) << " on the entry line, " << gap(gap_top) << " at the best starts, "
      << gap(gap_boundary) << " near boundaries, tolerance " << formatNumber(tolerance, 3) << ": "
      << (passed ? "passed" : "FAILED");
  return out.str();
}

HeightRange startRange(const SteeringProblem& problem, const StartOptions& start) {
  return {std::max(start.min_height_m, problem.workspace_min.y()),
          std::min(start.max_height_m, problem.workspace_max.y())};
}

std::vector<TipPose> entryLineStarts(const SteeringProblem& problem, const StartOptions& start,
                                     const std::vector<double>& heights_m) {
  const auto [lo, hi] = startRange(problem, start);
  std::vector<double> inside;
  for (double y : heights_m) {
    if (y >= lo && y <= hi) {
      inside.push_back(y);
    }
  }
  return entryPoses(start, inside,
                    {std::begin(kEntryLineAngles_deg), std::end(kEntryLineAngles_deg)}, 0.0);
}

std::vector<NearBoundaryStart> nearBoundaryStarts(const StartOptions& start,
                                                  const PolicyTable& table,
                                                  const ContinuousWorkspace& world) {
  const SteeringProblem& problem = world.problem();
  std::vector<NearBoundaryStart> out;
  const auto [lo, hi] = startRange(problem, start);
  std::vector<double> ends;
  for (double d : kEntryEndDistances_m) {
    ends.push_back(lo + d);
    ends.push_back(hi - d);
  }
  for (const TipPose& pose : entryLineStarts(problem, start, ends)) {
    out.push_back({"edge", pose});
  }
  auto add = [&](const std::string& group, const Point2& p) {
    if (!world.inWorkspace(p) || world.obstacleAt(p) >= 0 || world.inTarget(p)) {
      return;
    }
    if (const std::optional<TipPose> pose = bestPoseAt(table, p)) {
      out.push_back({group, *pose});
    }
  };
  const Point2 lo_w = problem.workspace_min, hi_w = problem.workspace_max;
  const double in = kNearBoundaryDistance_m;
  for (double f : {0.25, 0.5, 0.75}) {
    const Point2 along = lo_w + f * (hi_w - lo_w);
    add("edge", {along.x(), lo_w.y() + in});
    add("edge", {along.x(), hi_w.y() - in});
    add("edge", {lo_w.x() + in, along.y()});
    add("edge", {hi_w.x() - in, along.y()});
  }
  for (const geometry::Polygon& poly : world.expandedObstacles()) {
    const std::size_t n = poly.size();
    for (std::size_t i = 0; i < n; ++i) {
      const Point2 a = poly.vertices()[i], b = poly.vertices()[(i + 1) % n];
      const Point2 edge = b - a;
      if (edge.norm() < 1e-9) {
        continue;
      }
      const Point2 outward(edge.y() / edge.norm(), -edge.x() / edge.norm());  // CCW polygon
      add("obstacle", 0.5 * (a + b) + in * outward);
    }
  }
  return out;
}

std::int64_t checkTrials(double tolerance) {
  const double n = 0.25 / (tolerance * tolerance);
  return std::clamp<std::int64_t>(static_cast<std::int64_t>(std::ceil(n)), kMinCheckTrials,
                                  kMaxCheckTrials);
}

ModelCheck checkModel(const SteeringModel& model, const PolicyTable& table,
                      const StartOptions& start, double tolerance, std::int64_t trials,
                      std::uint64_t seed, int threads) {
  if (trials < 1) {
    throw std::invalid_argument("checkModel: trials must be >= 1, got " + std::to_string(trials));
  }
  const auto t0 = std::chrono::steady_clock::now();
  const ContinuousWorkspace world(model.problem());
  // Off-grid starts (entry line, near boundaries) are predicted from the pose itself, not from
  // the state it rounds to; a grid state's own pose gives the table's value.
  const ExactPosePrediction prediction(model, table);
  const SteeringPolicy policy = prediction.policy();
  struct Checked {
    TipPose pose;
    double predicted = 0.0;
    int group = kEntryGroup;  // CheckGroup
    MonteCarloResult mc;
  };
  std::vector<Checked> starts;
  auto add = [&](const TipPose& pose, int group) {
    starts.push_back({pose, prediction.predict(pose).probability_of_success, group, {}});
  };
  for (const TipPose& pose : checkPoses(model.problem(), start)) {
    add(pose, kEntryGroup);
  }
  StartVerificationOptions best;
  best.candidates = kCheckTopStarts;
  for (const StartCandidate& c : distinctBestStarts(table, start, best)) {
    add(c.pose, kTopGroup);
  }
  for (const NearBoundaryStart& b : nearBoundaryStarts(start, table, world)) {
    add(b.pose, kBoundaryGroup);
  }
  // First a quarter of the trials: a check that clearly fails stops there (sequential stop).
  TrialOptions options;
  const std::int64_t first = std::max<std::int64_t>(1, trials / kCheckStages);
  for (Checked& c : starts) {
    c.mc = runMonteCarlo(world, c.pose, policy, first, seed, threads, options);
  }
  ModelCheck out = scoreCheck(starts, tolerance);
  out.trials_per_start = first;
  if (first < trials && !out.clearlyFailed()) {
    options.first_trial = first;
    for (Checked& c : starts) {
      c.mc = combined(c.mc,
                      runMonteCarlo(world, c.pose, policy, trials - first, seed, threads, options));
    }
    out = scoreCheck(starts, tolerance);
    out.trials_per_start = trials;
  }
  out.trials_requested = trials;
  out.seconds = secondsSince(t0);
  return out;
}

std::string ModelChoice::toString() const {
  std::ostringstream out;
  const SteeringParams& p = problem.params;
  out << steering::toString(p.transition_model) << ", grid "
      << formatNumber(p.grid_spacing_m * 1e3, 3) << " mm, s = " << p.orientation_subdivision << ", "
      << (model ? model->numStates() : 0) << " states; estimated mean P_s error "
      << formatNumber(estimated_error, 2) << " (change from the " << ladder.size() - 1
      << " coarser model(s)); " << ladder.size() << " model(s) solved in "
      << formatNumber(total_s, 3) << " s";
  return out.str();
}

double estimatedModelMb(const SteeringProblem& problem) {
  const SteeringParams& p = problem.params;
  const auto size = problem.workspace_max - problem.workspace_min;
  const double positions = std::floor(size.x() / p.grid_spacing_m + 1e-9) *
                           std::floor(size.y() / p.grid_spacing_m + 1e-9);
  const double states = positions * 2.0 * p.orientations * p.orientation_subdivision;
  return kBaseMb + states * kBytesPerState / (1024.0 * 1024.0);
}

std::vector<TipPose> evaluationPoses(const SteeringProblem& problem, const StartOptions& start) {
  std::vector<TipPose> poses;
  const auto [lo, hi] = startRange(problem, start);
  for (double y = lo + 0.5 * kEvalStep_m; y < hi; y += kEvalStep_m) {
    for (int a = -kEvalAngles; a <= kEvalAngles; ++a) {
      for (Bevel b : {Bevel::kLeft, Bevel::kRight}) {
        TipPose pose;
        pose.p_SceneTip = Point2(start.start_x_m, y);
        pose.theta_rad = a * kEvalAngleStep_rad;
        pose.bevel = b;
        poses.push_back(pose);
      }
    }
  }
  return poses;
}

double meanAbsChange(const PolicyTable& fine, const PolicyTable& coarse,
                     const std::vector<TipPose>& poses, int& count) {
  double sum = 0.0;
  count = 0;
  for (const TipPose& pose : poses) {
    const double a = fine.lookup(pose).probability_of_success;
    const double b = coarse.lookup(pose).probability_of_success;
    if (a < kTrivialPs && b < kTrivialPs) {
      continue;
    }
    sum += std::abs(a - b);
    ++count;
  }
  return count > 0 ? sum / count : 0.0;
}

bool finerGridDidNotHelp(const std::vector<ModelRung>& ladder) {
  if (ladder.size() < 2 || !ladder.back().check.run) {
    return false;
  }
  const ModelRung& now = ladder.back();
  const double tol = now.check.tolerance;
  for (auto it = ladder.rbegin() + 1; it != ladder.rend(); ++it) {
    if (it->transition_model != now.transition_model ||
        it->orientation_subdivision != now.orientation_subdivision) {
      return false;
    }
    if (!it->check.run) {
      continue;
    }
    auto stuck = [tol](double before, double after) {
      return before > tol && after > tol && after >= before;
    };
    return stuck(it->check.gap_entry, now.check.gap_entry) ||
           stuck(it->check.gap_top, now.check.gap_top) ||
           stuck(it->check.gap_boundary, now.check.gap_boundary);
  }
  return false;
}

namespace {

/// After a model is accepted: the grids coarser than it with its transitions that the ladder never
/// solved (its transitions came in on a finer grid) are tried in turn, none coarser than the
/// scene's own grid. Each is accepted when its estimated error (its change to the finer accepted
/// model, Richardson: e = D r^k / (r^k - 1)) meets the tolerance and its check passes; the first
/// that does not ends the descent.
void coarsen(ModelChoice& choice, const SteeringProblem& problem, const SelectionOptions& options,
             const std::vector<TipPose>& poses, std::int64_t trials) {
  const double rk = std::pow(kRatio, kOrder);
  for (;;) {
    SteeringParams params = choice.model->params();
    params.grid_spacing_m *= kRatio;
    if (params.grid_spacing_m > problem.params.grid_spacing_m * (1.0 + 1e-9) ||
        solvedBefore(choice.ladder, params)) {
      return;
    }
    SteeringProblem rung_problem = problem;
    rung_problem.params = params;
    SolvedRung solved = solveRung(rung_problem, options);
    ModelRung& rung = solved.rung;
    rung.coarsened = true;
    rung.change_vs_coarser =
        meanAbsChange(*choice.table, *solved.table, poses, rung.evaluation_states);
    rung.estimated_error = rung.change_vs_coarser * rk / (rk - 1.0);
    const bool estimate_met = rung.estimated_error <= options.ps_tolerance;
    if (estimate_met && trials >= 0) {
      rung.check = checkModel(*solved.model, *solved.table, options.start, options.ps_tolerance,
                              trials, options.check_seed, options.solver.threads);
    }
    choice.ladder.push_back(rung);
    if (!estimate_met || (trials >= 0 && !rung.check.passed)) {
      return;
    }
    choice.problem = rung_problem;
    choice.model = std::move(solved.model);
    choice.table = std::move(solved.table);
    choice.estimated_error = rung.estimated_error;
    choice.check = rung.check;
  }
}

}  // namespace

Result<ModelChoice> chooseModel(const SteeringProblem& problem, const SelectionOptions& options) {
  if (!(options.ps_tolerance > 0.0 && options.ps_tolerance < 1.0)) {
    throw std::invalid_argument("chooseModel: ps_tolerance must be in (0, 1), got " +
                                formatNumber(options.ps_tolerance, 6));
  }
  const std::vector<TipPose> poses = evaluationPoses(problem, options.start);
  const std::int64_t trials =
      options.check_trials == 0 ? checkTrials(options.ps_tolerance) : options.check_trials;
  ModelChoice choice;
  const auto t0 = std::chrono::steady_clock::now();
  // The accepted model, or a coarser one of its transitions that also meets the tolerance.
  auto finish = [&]() {
    coarsen(choice, problem, options, poses, trials);
    for (ModelRung& r : choice.ladder) {
      r.chosen = solvedBefore({r}, choice.model->params());
    }
    choice.total_s = secondsSince(t0);
  };
  // The current rung checked by Monte Carlo (once); true when it is accepted.
  auto accepted = [&]() {
    if (trials < 0) {
      return true;
    }
    ModelRung& rung = choice.ladder.back();
    if (!rung.check.run) {
      rung.check = checkModel(*choice.model, *choice.table, options.start, options.ps_tolerance,
                              trials, options.check_seed, options.solver.threads);
    }
    choice.check = rung.check;
    return rung.check.passed;
  };
  // No further rung: the last one is accepted if its check passes, else the tolerance is refused.
  auto lastRung = [&](const std::string& why_no_further) -> Result<ModelChoice> {
    if (choice.table && accepted()) {
      finish();
      return std::move(choice);
    }
    std::ostringstream why;
    why << "ps_tolerance " << formatNumber(options.ps_tolerance, 4)
        << " cannot be met: " << why_no_further << "; the finest model (grid "
        << (choice.ladder.empty()
                ? std::string("none")
                : formatNumber(choice.ladder.back().grid_spacing_m * 1e3, 3) + " mm")
        << ") has "
        << (choice.ladder.empty() || !std::isfinite(choice.ladder.back().estimated_error)
                ? std::string("no estimated error (the first grid of its transitions)")
                : "an estimated mean P_s error of " +
                      formatNumber(choice.ladder.back().estimated_error, 2))
        << (choice.ladder.empty() ? std::string() : ", " + choice.ladder.back().check.toString());
    // The rungs tried, so the user sees where the ladder went.
    why << "; rungs:";
    for (const ModelRung& r : choice.ladder) {
      why << " [" << toString(r.transition_model) << " " << formatNumber(r.grid_spacing_m * 1e3, 3)
          << " mm s=" << r.orientation_subdivision;
      if (std::isfinite(r.estimated_error)) {
        why << " est " << formatNumber(r.estimated_error, 2);
      }
      if (r.check.run) {
        why << (r.check.passed ? " check passed" : " check failed");
      }
      why << "]";
    }
    return GeneralStatus(StatusCode::kRefused, why.str());
  };
  SteeringParams params = problem.params;
  bool traded = false;
  for (int step = 0; step < options.max_steps; ++step) {
    SteeringProblem rung_problem = problem;
    rung_problem.params = params;
    const double mb = estimatedModelMb(rung_problem);
    if (mb > options.memory_limit_mb && !traded && choice.table && !accepted()) {
      // Once: finer transitions instead of a finer grid, within the last rung's memory (twice
      // the orientations on a grid sqrt(2) coarser).
      SteeringParams finer = choice.model->params();
      const bool doubles = finer.transition_model == TransitionModel::kInterpolated;
      if (refineTransitions(finer)) {
        finer.grid_spacing_m *= doubles ? kRatio : 1.0;
        SteeringProblem traded_problem = problem;
        traded_problem.params = finer;
        if (estimatedModelMb(traded_problem) <= options.memory_limit_mb) {
          params = finer;
          traded = true;
          --step;  // not a rung of the grid ladder
          continue;
        }
      }
    }
    if (mb > options.memory_limit_mb) {
      return lastRung("the next model (" + steering::toString(params.transition_model) + ", grid " +
                      formatNumber(params.grid_spacing_m * 1e3, 3) +
                      " mm, s = " + std::to_string(params.orientation_subdivision) +
                      ") needs about " + formatNumber(mb, 4) + " MB against the memory limit of " +
                      formatNumber(options.memory_limit_mb, 4) + " MB");
    }
    SolvedRung solved = solveRung(rung_problem, options);
    ModelRung& rung = solved.rung;
    std::unique_ptr<const SteeringModel>& model = solved.model;
    std::unique_ptr<PolicyTable>& table = solved.table;
    // The change estimate compares two grids of the same transitions; after a change of the
    // transitions the check alone decides.
    const bool new_transitions =
        choice.model && !sameTransitions(choice.model->params(), rung_problem.params);
    if (choice.table && !new_transitions) {
      rung.change_vs_coarser = meanAbsChange(*table, *choice.table, poses, rung.evaluation_states);
      rung.estimated_error = rung.change_vs_coarser / (std::pow(kRatio, kOrder) - 1.0);
    }
    choice.ladder.push_back(rung);
    choice.problem = rung_problem;
    choice.model = std::move(model);
    choice.table = std::move(table);
    choice.estimated_error = rung.estimated_error;
    choice.peak_estimate_mb = std::max(choice.peak_estimate_mb, mb);
    // false for NaN (the first rung)
    if ((rung.estimated_error <= options.ps_tolerance || new_transitions) && accepted()) {
      finish();
      return choice;
    }
    const ModelCheck& check = choice.ladder.back().check;
    const double limit = kGridErrorShare * rung.estimated_error;  // NaN: the grid explains it
    const bool grid_explains =
        !check.run || !(check.gap_entry > limit || check.gap_top > limit ||
                        check.gap_boundary > limit || finerGridDidNotHelp(choice.ladder));
    if (grid_explains || !refineTransitions(params)) {
      params.grid_spacing_m /= kRatio;
    }
  }
  return lastRung(std::to_string(options.max_steps) + " refinements of grid " +
                  formatNumber(problem.params.grid_spacing_m * 1e3, 3) + " mm were solved");
}

}  // namespace needle_guidance::steering

namespace needle_guidance::steering {
namespace {

/// The groups checkModel scores: part of the saved choice's name and contents, so a choice that
/// a check of other groups accepted is never loaded (change it with the check's groups).
constexpr char kCheckDefinition[] = "entry-best4-boundary";

/// The file recording which grid spacing a tolerance chose for a problem (beside its tables).
std::string choicePath(const std::string& table_dir, const std::string& scene_name,
                       const SteeringProblem& problem) {
  std::string name = PolicyTable::fileName(scene_name, problemHash(problem));
  name = name.substr(0, name.size() - 6) + "_tol" + formatNumber(problem.ps_tolerance, 6) +
         "_check-" + kCheckDefinition + ".choice";
  return (std::filesystem::path(table_dir) / name).string();
}

}  // namespace

std::string PolicySource::description() const {
  std::ostringstream out;
  const SteeringParams& p = model->params();
  out << toString(p.transition_model) << ", grid " << formatNumber(p.grid_spacing_m * 1e3, 3)
      << " mm, s = " << p.orientation_subdivision << ", " << model->numStates()
      << " states, sigma_i " << formatNumber(p.sigma_insert_rad * 180.0 / kPi, 3)
      << " deg, sigma_r " << formatNumber(p.sigma_flip_rad * 180.0 / kPi, 3)
      << " deg, estimated P_s error "
      << (!std::isnan(estimated_error) ? formatNumber(estimated_error, 2)
          : ladder.empty()             ? std::string("not estimated")
                           : std::string("not estimated (first model of its transitions)"))
      << ", " << source << " in " << formatNumber(seconds, 3) << " s";
  if (!ladder.empty()) {
    out << " (" << ladder.size() << " models)";
  }
  if (check.run) {
    out << "; " << check.toString();
  }
  return out.str();
}

void saveTableAtomically(const PolicyTable& table, const std::string& path) {
  namespace fs = std::filesystem;
  const fs::path target(path);
  if (target.has_parent_path()) {
    fs::create_directories(target.parent_path());
  }
  const std::string temporary = path + ".tmp" + std::to_string(::getpid());
  try {
    table.save(temporary);
    fs::rename(temporary, target);
  } catch (...) {
    std::error_code ignored;
    fs::remove(temporary, ignored);
    throw;
  }
}

SteeringProblem withNoise(const SteeringProblem& chosen, double sigma_insert_rad,
                          double sigma_flip_rad) {
  if (!(sigma_insert_rad >= 0.0) || !(sigma_flip_rad >= 0.0) || !std::isfinite(sigma_insert_rad) ||
      !std::isfinite(sigma_flip_rad)) {
    throw std::invalid_argument("withNoise: sigmas must be finite and >= 0, got " +
                                formatNumber(sigma_insert_rad) + ", " +
                                formatNumber(sigma_flip_rad) + " rad");
  }
  SteeringProblem out = chosen;
  out.ps_tolerance = 0.0;
  out.params.sigma_insert_rad = sigma_insert_rad;
  out.params.sigma_flip_rad = sigma_flip_rad;
  return out;
}

Result<PolicySource> solveOrLoad(const SteeringProblem& problem, const std::string& scene_name,
                                 const std::string& table_dir, SelectionOptions options,
                                 bool force) {
  const auto t0 = std::chrono::steady_clock::now();
  PolicySource out;
  out.estimated_error = std::numeric_limits<double>::quiet_NaN();
  SteeringProblem chosen = problem;
  const bool select = problem.ps_tolerance > 0.0;
  const std::string record =
      select && !table_dir.empty() ? choicePath(table_dir, scene_name, problem) : "";
  if (!force && !table_dir.empty()) {
    bool known = !select;
    if (select) {
      std::ifstream in(record);
      std::string key_spacing, key_error, key_model, model_name, key_s, key_check, check_name;
      double spacing = 0.0, error = 0.0;
      int subdivision = 0;
      known = static_cast<bool>(in >> key_spacing >> spacing >> key_error >> error >> key_model >>
                                model_name >> key_s >> subdivision >> key_check >> check_name) &&
              key_spacing == "grid_spacing_m" && key_error == "estimated_error" &&
              key_model == "transition_model" && key_s == "orientation_subdivision" &&
              key_check == "model_check" && check_name == kCheckDefinition && spacing > 0.0 &&
              transitionModelFromString(model_name) && subdivision >= 1 && subdivision <= 64;
      if (known) {
        chosen.params.grid_spacing_m = spacing;
        chosen.params.transition_model = *transitionModelFromString(model_name);
        chosen.params.orientation_subdivision = subdivision;
        out.estimated_error = error >= 0.0 ? error : std::numeric_limits<double>::quiet_NaN();
      }
    }
    if (known) {
      auto model = std::make_unique<const SteeringModel>(chosen, options.threads);
      LoadStatus status;
      const std::string path =
          (std::filesystem::path(table_dir) / PolicyTable::fileName(scene_name, model->hash()))
              .string();
      std::optional<PolicyTable> loaded =
          PolicyTable::load(path, model->hash(), status, options.solver.epsilon);
      if (loaded && loaded->converged()) {
        out.model = std::move(model);
        out.table = std::make_unique<const PolicyTable>(std::move(*loaded));
        out.source = "loaded";
        out.seconds = secondsSince(t0);
        return out;
      }
    }
  }
  if (select) {
    options.ps_tolerance = problem.ps_tolerance;
    Result<ModelChoice> choice = chooseModel(problem, options);
    if (!choice) {
      return choice.status();
    }
    out.model = std::move(choice.value().model);
    out.table = std::move(choice.value().table);
    out.estimated_error = choice.value().estimated_error;
    out.ladder = choice.value().ladder;
    out.check = choice.value().check;
  } else {
    out.model = std::make_unique<const SteeringModel>(chosen, options.threads);
    SolveStats stats;
    out.table = std::make_unique<const PolicyTable>(
        solveValueIteration(*out.model, options.solver, &stats));
  }
  if (!out.table->converged()) {
    return GeneralStatus(StatusCode::kFailed, "value iteration did not converge to epsilon " +
                                                  formatNumber(options.solver.epsilon) + " in " +
                                                  std::to_string(out.table->sweeps()) + " sweeps");
  }
  out.source = "solved";
  if (!table_dir.empty()) {
    const std::string path =
        (std::filesystem::path(table_dir) / PolicyTable::fileName(scene_name, out.model->hash()))
            .string();
    try {
      saveTableAtomically(*out.table, path);
      if (select) {
        std::ofstream rec(record + ".tmp");
        rec.precision(17);
        const SteeringParams& chosen_params = out.model->params();
        // -1: not estimated (the chosen model was the first of its transitions).
        rec << "grid_spacing_m " << chosen_params.grid_spacing_m << "\nestimated_error "
            << (std::isnan(out.estimated_error) ? -1.0 : out.estimated_error)
            << "\ntransition_model " << steering::toString(chosen_params.transition_model)
            << "\norientation_subdivision " << chosen_params.orientation_subdivision
            << "\nmodel_check " << kCheckDefinition << "\n";
        rec.close();
        std::filesystem::rename(record + ".tmp", record);
      }
      out.note = "saved to '" + path + "'";
    } catch (const std::exception& e) {
      out.note =
          std::string("not saved: ") + e.what();  // the table is good; only the cache is missing
    }
  }
  out.seconds = secondsSince(t0);
  return out;
}

}  // namespace needle_guidance::steering
