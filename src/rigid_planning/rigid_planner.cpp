#include "needle_guidance/rigid_planning/rigid_planner.h"

#include "needle_guidance/cpu_time.h"
#include "needle_guidance/report/statistics.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <exception>
#include <mutex>
#include <random>
#include <sstream>
#include <stdexcept>
#include <thread>

namespace needle_guidance::rigid_planning {
namespace {

constexpr double kGolden = 0.6180339887498949;  // (sqrt(5) - 1) / 2
/// A converged secant bracket is accepted below this multiple of the tolerance with the
/// dissertation's interpolated scans (the verification and its corrections then take over). On
/// the depth grid the prediction is the verified seed, so no correction can follow: a bracket
/// over the tolerance goes on to the grid and golden-section search instead (within the budget).
constexpr double kSecantAcceptTolerances = 5.0;
/// A plan's scan stops once the implant point is this far past the target along the needle and
/// the best error is smaller: the implant curve only moves on (4.3.2: no later depth is better).
constexpr double kStopPastTarget_m = 5e-4;
/// The height search stops once a height's error is below this fraction of the placement
/// tolerance. The live loop executes the verified FEM steps (the depth grid), so no headroom is
/// kept for it: the search stops at the scene's tolerance, less a margin for rounding.
constexpr double kGoalFraction = 0.9;
/// Heights closer than this are the same height to the search (rounding of grid points) [m].
constexpr double kSameHeight_m = 1e-12;
/// A seed at rest moves less than this per step with the needle out [m].
constexpr double kRest_m = 1e-9;
/// Insertion prefixes (one per height, the deepest) kept for scans of later targets: a scene's
/// targets share a few heights; each prefix holds a copy of the simulation (a few MB).
constexpr std::size_t kMaxPrefixes = 8;

std::string mm(double metres) {
  std::ostringstream out;
  out.precision(4);
  out << 1e3 * metres << " mm";
  return out.str();
}

/// The point of segment (a, b) closest to t, as a fraction of the segment.
double closestFraction(const Point2& a, const Point2& b, const Point2& t) {
  const Point2 d = b - a;
  const double length2 = d.squaredNorm();
  return length2 > 0.0 ? std::clamp((t - a).dot(d) / length2, 0.0, 1.0) : 0.0;
}

/// Calls body(i) for i in [0, n), `threads` at a time (<= 0: one per core). Each body(i) must
/// touch only its own outputs. The first exception is rethrown after all threads joined.
void parallelFor(std::size_t n, int threads, const std::function<void(std::size_t)>& body) {
  const std::size_t workers =
      std::min<std::size_t>(n, threads > 0 ? static_cast<std::size_t>(threads)
                                           : std::max(1U, std::thread::hardware_concurrency()));
  std::atomic<std::size_t> next{0};
  std::exception_ptr failure;
  std::mutex failure_mutex;
  auto worker = [&] {
    for (std::size_t i = next++; i < n; i = next++) {
      try {
        body(i);
      } catch (...) {
        const std::lock_guard<std::mutex> lock(failure_mutex);
        failure = failure ? failure : std::current_exception();
      }
    }
  };
  std::vector<std::thread> pool;
  for (std::size_t t = 1; t < workers; ++t) {
    pool.emplace_back(worker);
  }
  worker();
  for (auto& thread : pool) {
    thread.join();
  }
  if (failure) {
    std::rethrow_exception(failure);
  }
}

/// Signed distance of `offset` from the line along `along` (left positive) [m]; 0 if `along`
/// has no length.
double signedLateral(const Point2& along, const Point2& offset) {
  const double length = along.norm();
  return length > 0.0 ? (along.x() * offset.y() - along.y() * offset.x()) / length : 0.0;
}

/// Throws std::runtime_error when a scan has fewer than two implant points: the needle never
/// entered the tissue at that height.
void requireEntered(const DepthScan& scan, double height_m) {
  if (scan.implant.size() < 2) {
    throw std::runtime_error("RigidPlanner: the needle never entered the tissue at height " +
                             mm(height_m));
  }
}

}  // namespace

const char* toString(PlanCode code) {
  switch (code) {
    case PlanCode::kOk:
      return "ok";
    case PlanCode::kTargetNotFinite:
      return "target not finite";
    case PlanCode::kTargetOutsideTissue:
      return "target outside tissue";
    case PlanCode::kHeightOutOfRange:
      return "height out of range";
    case PlanCode::kBeyondMaxDepth:
      return "beyond max depth";
    case PlanCode::kSimulationFailed:
      return "simulation failed";
    case PlanCode::kOutOfTolerance:
      return "out of tolerance";
    case PlanCode::kUnstableCut:
      return "unstable cut";
  }
  return "?";
}

bool isPhysicalRefusal(PlanCode code) {
  return code == PlanCode::kTargetOutsideTissue || code == PlanCode::kHeightOutOfRange ||
         code == PlanCode::kBeyondMaxDepth || code == PlanCode::kUnstableCut;
}

Point2 DepthScan::implantAt(double z) const {
  if (depth_m.empty()) {
    throw std::logic_error("DepthScan::implantAt: empty scan");
  }
  const auto it = std::lower_bound(depth_m.begin(), depth_m.end(), z);
  if (it == depth_m.begin()) {
    return implant.front();
  }
  if (it == depth_m.end()) {
    return implant.back();
  }
  const std::size_t i = static_cast<std::size_t>(it - depth_m.begin());
  const double s = (z - depth_m[i - 1]) / (depth_m[i] - depth_m[i - 1]);
  return implant[i - 1] + s * (implant[i] - implant[i - 1]);
}

RigidPlanner::RigidPlanner(scene::Scene scene, tissue::TissueSimOptions sim_options,
                           PlannerOptions options)
    : scene_(std::move(scene)),
      sim_options_(std::move(sim_options)),
      options_(options),
      cache_(std::make_shared<SimulationCache>()) {
  sim_options_.depth_grid.step_m = options_.procedure_grid ? options_.depth_step_m : 0.0;
  if (!scene_.hasTissue()) {
    throw std::invalid_argument("RigidPlanner: scene '" + scene_.name + "' has no tissue model");
  }
  auto positive = [](double v) { return std::isfinite(v) && v > 0.0; };
  if (!positive(options_.height_window_m) || !positive(options_.height_tolerance_m) ||
      !positive(options_.depth_step_m) || !positive(options_.velocity_m_s) ||
      !(options_.depth_margin_m >= 0.0) || options_.grid_points < 3) {
    throw std::invalid_argument(
        "RigidPlanner: window, tolerance, depth step and velocity must be > 0, margin >= 0 and "
        "at least 3 grid points");
  }
  for (const auto& [name, value] :
       {std::pair<const char*, double>{"work_budget", options_.work_budget},
        {"time_budget_s", options_.time_budget_s}}) {
    if (!std::isfinite(value) || value < 0.0) {
      throw std::invalid_argument(std::string("RigidPlanner: ") + name + " " +
                                  std::to_string(value) + " must be finite and >= 0 (0: none)");
    }
  }
}

RigidPlan RigidPlanner::check(const Point2& target) const {
  RigidPlan plan;
  plan.target = target;
  auto refuse = [&](PlanCode code, const std::string& why) {
    plan.code = code;
    plan.message = std::string("RigidPlanner: ") + toString(code) + ": " + why;
    return plan;
  };
  if (!target.allFinite()) {
    return refuse(PlanCode::kTargetNotFinite, "target (" + mm(target.x()) + ", " + mm(target.y()) +
                                                  ") has a non-finite coordinate");
  }
  if (!scene_.inWorkspace(target)) {
    return refuse(PlanCode::kTargetOutsideTissue,
                  "target (" + mm(target.x()) + ", " + mm(target.y()) + ") is not in the tissue");
  }
  for (const auto& region : scene_.regions) {
    if (region.rigid && region.polygon.contains(target)) {
      return refuse(PlanCode::kTargetOutsideTissue,
                    "target lies in rigid region '" + region.name + "'");
    }
  }
  if (sim_options_.needle_model == tissue::NeedleModel::kEmbeddedTrack) {
    // The embedded track cuts along the needle's line and the seed lands on it: the needle must
    // reach the target at its own height, so bone on that line in front of it is a wall.
    constexpr double kLineSample_m = 1e-4;
    for (double x = scene_.workspace_min.x(); x < target.x(); x += kLineSample_m) {
      for (const auto& region : scene_.regions) {
        if (region.rigid && region.polygon.contains(Point2(x, target.y()))) {
          return refuse(PlanCode::kTargetOutsideTissue,
                        "the needle line to the target (height " + mm(target.y()) +
                            ") meets rigid region '" + region.name + "' at depth " + mm(x) +
                            ", short of the target depth " + mm(target.x()));
        }
      }
    }
  }
  if (target.y() < scene_.needle.min_height_m || target.y() > scene_.needle.max_height_m) {
    return refuse(PlanCode::kHeightOutOfRange,
                  "target height " + mm(target.y()) + " is outside the needle's range [" +
                      mm(scene_.needle.min_height_m) + ", " + mm(scene_.needle.max_height_m) + "]");
  }
  if (target.x() >= scene_.needle.max_depth_m) {
    return refuse(PlanCode::kBeyondMaxDepth, "target depth " + mm(target.x()) +
                                                 " is not short of the max depth " +
                                                 mm(scene_.needle.max_depth_m));
  }
  plan.message = "ok";
  return plan;
}

namespace {

/// A step refused because the needle meets bone (the embedded track cannot cut rigid tissue),
/// after the scan has a segment in tissue: the scan ends there.
bool metBone(const tissue::StepStatus& status, const DepthScan& scan) {
  return scan.implant.size() >= 2 && status.toString().find("rigid tissue") != std::string::npos;
}

}  // namespace

/// An insertion at one height on the scene's mesh, as far as a scan went: its implant points and
/// its state there. A scan at that height for a deeper target continues from a copy of it.
struct InsertionPrefix {
  double height_m = 0.0;
  long grid_k = -1;   ///< the state's grid position (grid_k + 1 FEM steps from the entry face)
  double work = 0.0;  ///< solver work from the entry face to the state
  std::vector<double> depth_m;
  std::vector<Point2> implant;
  std::shared_ptr<const tissue::TissueSimulation> state;
};

struct RigidPlanner::SimulationCache {
  std::mutex mutex;
  std::shared_ptr<const tissue::TissueSimulation> scene_sim;     ///< at rest; null until used
  std::vector<std::shared_ptr<const InsertionPrefix>> prefixes;  ///< oldest first
};

std::unique_ptr<tissue::TissueSimulation> RigidPlanner::makeSimulation(const Point2& target) const {
  tissue::TissueSimOptions options = sim_options_;
  // Fine along this target's needle path, whatever the scene's own targets are; a scene target
  // is refined already, and the mesh is then the live tissue_sim's.
  auto& points = options.meshing.refine_points;
  if (std::find(points.begin(), points.end(), target) == points.end()) {
    points.push_back(target);
    options.meshing.refine_lines.push_back({Point2(scene_.workspace_min.x(), target.y()), target});
    return std::make_unique<tissue::TissueSimulation>(scene_, options);
  }
  std::shared_ptr<const tissue::TissueSimulation> scene_sim;
  {
    const std::lock_guard<std::mutex> lock(cache_->mutex);
    if (!cache_->scene_sim) {
      cache_->scene_sim = std::make_shared<const tissue::TissueSimulation>(scene_, options);
    }
    scene_sim = cache_->scene_sim;
  }
  // A copy of the state at rest is the state a fresh build has (bit for bit).
  return scene_sim->copyable() ? std::make_unique<tissue::TissueSimulation>(*scene_sim)
                               : std::make_unique<tissue::TissueSimulation>(scene_, options);
}

DepthScan RigidPlanner::scan(tissue::TissueSimulation& sim, double height_m, const Point2& target,
                             double max_depth_m, bool stop_past_target) const {
  sim.reset();
  DepthScan scan;
  scan.height_m = height_m;
  const double work_from = sim.solverWork();
  double x = scene_.workspace_min
                 .x();  // tip on the entry face: steps outside only solve the unloaded model
  scan.best_error_m = 1e300;
  const double fine_from = target.x() - options_.approach_zone_m;
  while (x < max_depth_m - 1e-12) {
    const double dz = options_.approach_step_m > 0.0 && x + options_.approach_step_m < fine_from
                          ? options_.approach_step_m
                          : options_.depth_step_m;
    const double dt_s = dz / options_.velocity_m_s;
    x = std::min(max_depth_m, x + dz);
    const tissue::StepStatus status = sim.step(dt_s, height_m, x);
    if (!status && metBone(status, scan)) {
      break;  // the needle meets bone at this height: no deeper release exists here
    }
    if (!status) {
      throw std::runtime_error("RigidPlanner: simulation step refused: " + status.toString());
    }
    const std::optional<Point2> tip = sim.tipReference();
    if (!tip) {
      continue;  // not in tissue yet
    }
    scan.depth_m.push_back(x);
    scan.implant.push_back(*tip);
    const std::size_t n = scan.implant.size();
    if (n >= 2) {  // O(1) per step: the best release on the last segment (4.3.2)
      const double s = closestFraction(scan.implant[n - 2], scan.implant[n - 1], target);
      const Point2 p = scan.implant[n - 2] + s * (scan.implant[n - 1] - scan.implant[n - 2]);
      const double error = (p - target).norm();
      if (error < scan.best_error_m) {
        scan.best_error_m = error;
        scan.best_implant = p;
        scan.lateral_m = signedLateral(scan.implant[n - 1] - scan.implant[n - 2], target - p);
        scan.best_depth_m = scan.depth_m[n - 2] + s * (scan.depth_m[n - 1] - scan.depth_m[n - 2]);
      }
      if (stop_past_target && tip->x() - target.x() > kStopPastTarget_m &&
          scan.best_error_m < kStopPastTarget_m) {
        break;
      }
    }
  }
  requireEntered(scan, height_m);
  scan.work = sim.solverWork() - work_from;
  return scan;
}

void RigidPlanner::searchHeights(RigidPlan& plan,
                                 const std::function<HeightResult(double)>& evaluate,
                                 bool early_stop, const Point2& aim, double goal_m,
                                 double first_offset_m,
                                 const std::function<bool()>& expired) const {
  const Point2 target = aim;
  std::vector<std::pair<double, HeightResult>> seen;
  bool goal_met = false;  // with early_stop: any height whose error meets the goal ends the search
  auto f = [&](double y) {
    // A height scanned already (the grid's points include the target height and the window's
    // edges, which the secant may have tried) is not simulated again.
    const auto known = std::find_if(seen.begin(), seen.end(), [&](const auto& s) {
      return std::abs(s.first - y) <= kSameHeight_m;
    });
    seen.emplace_back(y, known != seen.end() ? known->second : evaluate(y));
    goal_met = goal_met || (early_stop && seen.back().second.error_m <= goal_m);
    if (!goal_met && expired && expired()) {
      plan.budget_expired = true;
      goal_met = true;  // ends every loop below; the best height so far is the plan
    }
    return seen.back().second.error_m;
  };
  // The target height first (depth-only planning, 4.4.2): often already good enough.
  f(target.y());
  const double lo_y = std::max(scene_.needle.min_height_m, target.y() - options_.height_window_m);
  const double hi_y = std::min(scene_.needle.max_height_m, target.y() + options_.height_window_m);
  if (!goal_met && first_offset_m != 0.0) {  // warm start: the previous target's height offset
    f(std::clamp(target.y() + first_offset_m, lo_y, hi_y));
    if (seen.back().second.error_m > seen.front().second.error_m) {
      std::swap(seen.front(), seen.back());  // the secant starts from the better of the two
    }
  }
  // Secant search on the lateral offset of the implant curve, which is close to linear in height
  // over the window: a few simulations where the grid + golden section needs many more. Once
  // two heights put the curve on opposite sides of the target the root is bracketed and the
  // Illinois variant of false position keeps it bracketed; the mesh makes the offset a step
  // function of height at the 0.01 mm scale, so a bracket narrower than a tenth of the height
  // tolerance is as good as the golden section can do and ends the search too.
  if (early_stop && !goal_met && options_.secant_iterations > 0 &&
      seen.front().second.lateral_m != 0.0) {
    // (ya, da): the older point, or the far end once bracketed; (yb, db): the newest point.
    double ya = seen.front().first;
    double da = seen.front().second.lateral_m;
    double yb =
        std::clamp(ya + da, lo_y, hi_y);  // the curve moves with the needle: shift by the offset
    f(yb);
    double db = seen.back().second.lateral_m;
    bool bracketed = (da > 0.0) != (db > 0.0);
    for (int i = 1; i < options_.secant_iterations && !goal_met; ++i) {
      if (bracketed && std::abs(yb - ya) < 0.1 * options_.height_tolerance_m) {
        plan.secant = true;  // converged to the mesh's resolution in height
        break;
      }
      if (db == da || db == 0.0) {
        break;
      }
      const double yc = std::clamp(yb - db * (yb - ya) / (db - da), lo_y, hi_y);
      if (yc == yb) {
        break;  // pinned at the window's edge
      }
      f(yc);
      const double dc = seen.back().second.lateral_m;
      if (bracketed && (dc > 0.0) == (db > 0.0)) {
        da *= 0.5;  // Illinois: the far end is kept once more, so halve its weight
      } else {
        bracketed = bracketed || (dc > 0.0) != (db > 0.0);
        ya = yb;
        da = db;
      }
      yb = yc;
      db = dc;
    }
    // A converged bracket with a large error is a jump in the offset (a tissue boundary): the
    // grid below looks for a better minimum elsewhere.
    const double best_error =
        std::min_element(seen.begin(), seen.end(), [](const auto& l, const auto& r) {
          return l.second.error_m < r.second.error_m;
        })->second.error_m;
    plan.secant =
        (goal_met && !plan.budget_expired) ||
        (plan.secant &&
         best_error <= (options_.procedure_grid ? 1.0 : kSecantAcceptTolerances) * tolerance());
    goal_met = plan.secant || plan.budget_expired;
  }
  if (!goal_met) {
    // Coarse grid: detects an error that is not unimodal over the window (4.3.2 notes it need
    // not be, e.g. next to a tissue boundary) and brackets the best grid point.
    const int n = options_.grid_points;
    std::vector<double> ys(static_cast<std::size_t>(n)), errors(static_cast<std::size_t>(n));
    for (int i = 0; i < n; ++i) {
      ys[static_cast<std::size_t>(i)] = lo_y + (hi_y - lo_y) * i / (n - 1);
      errors[static_cast<std::size_t>(i)] = goal_met ? 1e300 : f(ys[static_cast<std::size_t>(i)]);
    }
    int local_minima = 0;
    for (int i = 0; i < n; ++i) {
      const double e = errors[static_cast<std::size_t>(i)];
      const bool left = i == 0 || e < errors[static_cast<std::size_t>(i - 1)];
      const bool right = i == n - 1 || e <= errors[static_cast<std::size_t>(i + 1)];
      local_minima += left && right ? 1 : 0;
    }
    plan.unimodal = goal_met || local_minima <= 1;
    const std::size_t best =
        static_cast<std::size_t>(std::min_element(errors.begin(), errors.end()) - errors.begin());
    // Golden-section search in the bracket around the best grid point (4.3.2, [23]).
    double a = ys[best == 0 ? 0 : best - 1];
    double b = ys[std::min<std::size_t>(best + 1, ys.size() - 1)];
    double c = b - kGolden * (b - a);
    double d = a + kGolden * (b - a);
    double fc = goal_met ? 0.0 : f(c);
    double fd = goal_met ? 0.0 : f(d);
    while (!goal_met && b - a > options_.height_tolerance_m) {
      if (fc < fd) {
        b = d;
        d = c;
        fd = fc;
        c = b - kGolden * (b - a);
        fc = f(c);
      } else {
        a = c;
        c = d;
        fc = fd;
        d = a + kGolden * (b - a);
        fd = f(d);
      }
    }
  }
  const auto best = std::min_element(seen.begin(), seen.end(), [](const auto& l, const auto& r) {
    return l.second.error_m < r.second.error_m;
  });
  plan.release = Point2(best->second.depth_m, best->first);
  plan.predicted_implant = best->second.implant;
  plan.predicted_error_m = best->second.error_m;
  plan.message = plan.budget_expired ? "ok (budget expired: best height so far)"
                 : plan.secant       ? "ok (secant on the lateral offset)"
                 : plan.unimodal     ? "ok"
                                     : "ok (error not unimodal over the window: grid fallback)";
}

double RigidPlanner::maxScanDepth(const Point2& target) const {
  if (sim_options_.needle_model == tissue::NeedleModel::kEmbeddedTrack) {
    // Soft tissue ahead of the tip compresses millimetres before it is cut, more than any fixed
    // margin: scans run to the needle's reach and stop once the tip's tissue point has passed
    // the target.
    return scene_.needle.max_depth_m;
  }
  return std::min(scene_.needle.max_depth_m, target.x() + options_.depth_margin_m);
}

RigidPlan RigidPlanner::timed(const Point2& target,
                              const std::function<void(RigidPlan&)>& body) const {
  const auto start = std::chrono::steady_clock::now();
  const CpuStopwatch cpu;  // a plan runs on one thread
  RigidPlan plan = check(target);
  if (!plan) {
    return plan;
  }
  try {
    body(plan);
  } catch (const std::exception& e) {
    plan.code = PlanCode::kSimulationFailed;
    plan.message = e.what();
  }
  plan.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  plan.cpu_seconds = cpu.seconds();
  return plan;
}

ImplantSchedule RigidPlanner::schedule() const {
  ImplantSchedule schedule;
  schedule.start_x_m = scene_.workspace_min.x() - 0.001;
  schedule.sample_m =
      sim_options_.depth_grid.step_m > 0.0 ? sim_options_.depth_grid.step_m : options_.depth_step_m;
  schedule.dt_s = schedule.sample_m / scene_.needle.insertion_velocity_m_s;
  return schedule;
}

double RigidPlanner::tolerance() const {
  return options_.tolerance_m > 0.0 ? options_.tolerance_m : scene_.needle.placement_tolerance_m;
}

namespace {

/// Commands the needle at `height_m` from `from` to `to` as a robot streams samples: sample k
/// at from + k sample (from its index, no accumulated rounding), then the end point itself.
void commandMove(tissue::TissueSimulation& sim, const ImplantSchedule& schedule, double height_m,
                 double from, double to) {
  auto command = [&](double x) {
    const tissue::StepStatus status = sim.advance(schedule.dt_s, height_m, x);
    if (!status) {
      throw std::runtime_error("simulateImplant: step refused: " + status.toString());
    }
  };
  const double direction = to >= from ? 1.0 : -1.0;
  for (long k = 1;; ++k) {
    const double x = from + direction * static_cast<double>(k) * schedule.sample_m;
    if (direction * (x - to) >= 0.0) {
      break;
    }
    command(x);
  }
  command(to);
}

/// The second half of simulateImplant: `sim` has the needle at `release`; releases the seed,
/// retracts to the schedule's start and waits until the seed is at rest.
Point2 releaseAndRetract(tissue::TissueSimulation& sim, const Point2& release,
                         const ImplantSchedule& schedule) {
  std::string why;
  const std::optional<int> id = sim.implantSeed(&why);
  if (!id) {
    throw std::runtime_error("simulateImplant: seed not released: " + why);
  }
  commandMove(sim, schedule, release.y(), release.x(), schedule.start_x_m);
  Point2 seed = sim.seedPosition(sim.seeds().at(static_cast<std::size_t>(*id)));
  for (int i = 0; i < schedule.max_rest_steps; ++i) {  // wait for steady state (4.3.2)
    const tissue::StepStatus status = sim.advance(schedule.dt_s, release.y(), schedule.start_x_m);
    if (!status) {
      throw std::runtime_error("simulateImplant: step refused: " + status.toString());
    }
    const Point2 next = sim.seedPosition(sim.seeds().at(static_cast<std::size_t>(*id)));
    const bool at_rest = (next - seed).norm() < kRest_m;
    seed = next;
    if (at_rest) {
      break;
    }
  }
  return seed;
}

}  // namespace

Point2 simulateImplant(tissue::TissueSimulation& sim, const Point2& release,
                       const ImplantSchedule& schedule) {
  if (!(schedule.sample_m > 0.0) || !(schedule.dt_s > 0.0)) {
    throw std::invalid_argument("simulateImplant: sample and dt must be > 0");
  }
  sim.reset();
  commandMove(sim, schedule, release.y(), schedule.start_x_m, release.x());
  return releaseAndRetract(sim, release, schedule);
}

bool RigidPlanner::addGridPoint(DepthScan& scan, double x, const Point2& tip, const Point2& target,
                                const tissue::TissueSimulation* state,
                                bool stop_past_target) const {
  scan.depth_m.push_back(x);
  scan.implant.push_back(tip);
  const std::size_t n = scan.implant.size();
  // A release on this grid depth lands on the tip node's reference position exactly (4.3.2);
  // the side of the target is read against the implant curve's last segment.
  const double error = (tip - target).norm();
  if (error < scan.best_error_m) {
    scan.best_error_m = error;
    scan.best_implant = tip;
    scan.best_depth_m = x;
    scan.lateral_m =
        signedLateral(n >= 2 ? Point2(scan.implant[n - 1] - scan.implant[n - 2]) : Point2(1.0, 0.0),
                      target - tip);
    // Within the tolerance: keep the state, a verification of this release continues from it.
    scan.release_state = error <= tolerance() && state && state->copyable()
                             ? std::make_shared<const tissue::TissueSimulation>(*state)
                             : nullptr;
  }
  // The tip's reference x only grows while inserting (cuts move it along +x) and the error is
  // at least tip x - target x: once that exceeds the best error no later depth is better.
  return stop_past_target && tip.x() - target.x() > scan.best_error_m;
}

void RigidPlanner::runGridScan(tissue::TissueSimulation& sim, DepthScan& scan, const Point2& target,
                               long last, bool stop_past_target,
                               const std::function<bool(double)>& out_of_budget,
                               double work_from) const {
  const double dt_s = sim.options().depth_grid.step_m / scene_.needle.insertion_velocity_m_s;
  for (long k = sim.gridPosition() + 1; k <= last; ++k) {
    const double x = sim.gridDepth(k);
    const tissue::StepStatus status = sim.advance(dt_s, scan.height_m, x);
    if (!status && metBone(status, scan)) {
      break;  // the needle meets bone at this height: no deeper release exists here
    }
    if (!status) {
      throw std::runtime_error("RigidPlanner: simulation step refused: " + status.toString());
    }
    const std::optional<Point2> tip = sim.tipReference();
    if (tip && addGridPoint(scan, x, *tip, target, &sim, stop_past_target)) {
      break;
    }
    // Not before the scan has a segment in tissue: a plan always has a release to verify.
    if (out_of_budget && k < last && scan.implant.size() >= 2 &&
        out_of_budget(sim.solverWork() - work_from)) {
      scan.cut_short = true;
      break;
    }
  }
}

void RigidPlanner::storePrefix(const tissue::TissueSimulation& sim, const DepthScan& scan,
                               double work_from) const {
  auto deeper = [&] {  // no prefix at this height reaches as far (call under the lock)
    return std::none_of(cache_->prefixes.begin(), cache_->prefixes.end(), [&](const auto& p) {
      return p->height_m == scan.height_m && p->grid_k >= sim.gridPosition();
    });
  };
  {
    const std::lock_guard<std::mutex> lock(cache_->mutex);
    if (!sim.copyable() || !deeper()) {
      return;
    }
  }
  auto prefix = std::make_shared<InsertionPrefix>();
  prefix->height_m = scan.height_m;
  prefix->grid_k = sim.gridPosition();
  prefix->work = sim.solverWork() - work_from;
  prefix->depth_m = scan.depth_m;
  prefix->implant = scan.implant;
  prefix->state = std::make_shared<const tissue::TissueSimulation>(sim);
  const std::lock_guard<std::mutex> lock(cache_->mutex);
  if (!deeper()) {
    return;  // another thread cached a deeper one meanwhile
  }
  auto& prefixes = cache_->prefixes;
  prefixes.erase(std::remove_if(prefixes.begin(), prefixes.end(),
                                [&](const auto& p) { return p->height_m == scan.height_m; }),
                 prefixes.end());
  prefixes.push_back(std::move(prefix));
  if (prefixes.size() > kMaxPrefixes) {
    prefixes.erase(prefixes.begin());
  }
}

std::optional<DepthScan> RigidPlanner::resumeScan(double height_m, const Point2& target, long last,
                                                  ResumeCounters& counters) const {
  std::shared_ptr<const InsertionPrefix> prefix;
  {
    const std::lock_guard<std::mutex> lock(cache_->mutex);
    for (const auto& p : cache_->prefixes) {
      if (p->height_m == height_m && p->grid_k < last) {
        prefix = p;
      }
    }
  }
  if (!prefix) {
    return std::nullopt;
  }
  DepthScan scan;
  scan.height_m = height_m;
  scan.best_error_m = 1e300;
  for (std::size_t i = 0; i < prefix->depth_m.size(); ++i) {
    if (addGridPoint(scan, prefix->depth_m[i], prefix->implant[i], target, nullptr, true)) {
      return std::nullopt;  // ends within the prefix: a scan from the entry face keeps its state
    }
  }
  if (counters.out_of_budget && counters.out_of_budget(prefix->work)) {
    return std::nullopt;  // the budget ends within the prefix: a scan from the entry face
  }
  tissue::TissueSimulation sim(*prefix->state);
  const long before = sim.femSteps();
  const double work_before = sim.solverWork();
  runGridScan(sim, scan, target, last, true, counters.out_of_budget, work_before - prefix->work);
  if (scan.best_error_m <= tolerance() && !scan.release_state) {
    return std::nullopt;  // the best release lies in the prefix, whose states are not kept
  }
  requireEntered(scan, height_m);
  counters.reused += prefix->grid_k + 1;
  counters.steps += prefix->grid_k + 1 + (sim.femSteps() - before);
  counters.work_reused += prefix->work;
  counters.work += prefix->work + (sim.solverWork() - work_before);
  scan.work = prefix->work + (sim.solverWork() - work_before);
  if (!scan.cut_short) {
    storePrefix(sim, scan, work_before - prefix->work);
  }
  return scan;
}

DepthScan RigidPlanner::gridScan(tissue::TissueSimulation& sim, double height_m,
                                 const Point2& target, double max_depth_m, bool stop_past_target,
                                 ResumeCounters* resume) const {
  const long last = sim.gridIndex(max_depth_m);
  const bool resumable = resume && resume->resume && stop_past_target;
  if (resumable) {
    if (std::optional<DepthScan> resumed = resumeScan(height_m, target, last, *resume)) {
      return std::move(*resumed);
    }
  }
  sim.reset();
  DepthScan scan;
  scan.height_m = height_m;
  scan.best_error_m = 1e300;
  const double work_from = sim.solverWork();
  // Work on the plan's own simulation is in the plan's counters already: no extra.
  const std::function<bool(double)> out_of_budget =
      resume && resume->out_of_budget
          ? std::function<bool(double)>([&](double) { return resume->out_of_budget(0.0); })
          : std::function<bool(double)>();
  runGridScan(sim, scan, target, last, stop_past_target, out_of_budget, work_from);
  requireEntered(scan, height_m);
  scan.work = sim.solverWork() - work_from;
  if (resumable && !scan.cut_short) {
    storePrefix(sim, scan, work_from);
  }
  return scan;
}

void RigidPlanner::searchPlan(RigidPlan& plan, tissue::TissueSimulation& sim, const Point2& aim,
                              double first_offset_m, const std::function<bool()>& expired,
                              ResumeCounters& resume) const {
  const double max_depth = maxScanDepth(aim);
  searchHeights(
      plan,
      [&](double y) {
        plan.scans.push_back(options_.procedure_grid
                                 ? gridScan(sim, y, aim, max_depth, true, &resume)
                                 : scan(sim, y, aim, max_depth, /*stop_past_target=*/true));
        ++plan.simulations;
        const DepthScan& s = plan.scans.back();
        return HeightResult{s.best_error_m, s.best_depth_m, s.best_implant, s.lateral_m};
      },
      /*early_stop=*/true, aim,
      options_.error_goal_m > 0.0 ? std::min(options_.error_goal_m, kGoalFraction * tolerance())
                                  : kGoalFraction * tolerance(),
      first_offset_m, expired);
}

std::optional<Point2> RigidPlanner::verify(tissue::TissueSimulation& sim, RigidPlan& plan,
                                           double work_left) const {
  const DepthScan* found = nullptr;
  for (auto it = plan.scans.rbegin(); it != plan.scans.rend(); ++it) {
    if (it->height_m != plan.release.y() || it->best_depth_m != plan.release.x()) {
      continue;
    }
    found = found ? found : &*it;
    if (it->release_state) {
      tissue::TissueSimulation state(*it->release_state);  // the scan's state, bit for bit
      const long before = state.femSteps();
      const double work_before = state.solverWork();
      const Point2 seed = releaseAndRetract(state, plan.release, schedule());
      plan.fem_steps += state.femSteps() - before;
      plan.solver_work += state.solverWork() - work_before;
      return seed;
    }
  }
  // A full simulation costs about what the scan that found the release did.
  if (options_.work_budget > 0.0 && found && found->work > work_left) {
    return std::nullopt;
  }
  return simulateImplant(sim, plan.release, schedule());  // counted on sim
}

RigidPlan RigidPlanner::plan(const Point2& target, double first_height_offset_m) const {
  const auto start = std::chrono::steady_clock::now();
  return timed(target, [&](RigidPlan& plan) {
    plan.tolerance_m = tolerance();
    const std::unique_ptr<tissue::TissueSimulation> sim = makeSimulation(target);
    const long steps_at_start = sim->femSteps();
    const double work_at_start = sim->solverWork();
    long other_steps = 0;     // FEM steps of verifications on copies
    double other_work = 0.0;  // and their solver work
    // Scans of the scene's own targets (its mesh) may resume an earlier plan's insertion.
    const auto& refined = sim_options_.meshing.refine_points;
    ResumeCounters resume;
    resume.resume =
        sim->copyable() && std::find(refined.begin(), refined.end(), target) != refined.end();
    auto steps = [&] { return sim->femSteps() - steps_at_start + other_steps + resume.steps; };
    auto work = [&] { return sim->solverWork() - work_at_start + other_work + resume.work; };
    resume.out_of_budget = [&](double extra_work) {
      const double seconds =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
      return (options_.work_budget > 0.0 && work() + extra_work > options_.work_budget) ||
             (options_.time_budget_s > 0.0 && seconds > options_.time_budget_s);
    };
    const std::function<bool()> expired = [&] { return resume.out_of_budget(0.0); };
    searchPlan(plan, *sim, target, first_height_offset_m, expired, resume);
    plan.predicted_error_m = (plan.predicted_implant - target).norm();
    if (!options_.verify) {
      plan.within_tolerance = plan.predicted_error_m <= plan.tolerance_m;
      plan.fem_steps = steps();
      plan.fem_steps_reused = resume.reused;
      plan.solver_work = work();
      return;
    }
    // Verify; while the verified seed misses and disagrees with the prediction, aim the O(1)
    // search at the target shifted by the disagreement (the bias of the prediction is smooth in
    // the release point, so this is a fixed-point step on the verified error).
    RigidPlan best = plan;
    Point2 aim = target;
    for (int round = 0;; ++round) {
      plan.fem_steps = 0;
      plan.solver_work = 0.0;
      const double work_left = options_.work_budget - work();
      const std::optional<Point2> verified_or = verify(*sim, plan, work_left);
      other_steps += plan.fem_steps;  // steps on a copy (sim counts its own)
      other_work += plan.solver_work;
      if (!verified_or) {  // over the tolerance, and no budget left to simulate it in full
        plan.budget_expired = true;
        break;
      }
      const Point2 verified = *verified_or;
      ++plan.simulations;
      ++plan.verifications;
      const double verified_error = (verified - target).norm();
      if (!best.verified || verified_error < best.verified_error_m) {
        best = plan;
        best.verified = true;
        best.verified_implant = verified;
        best.verified_error_m = verified_error;
        best.predicted_error_m = (plan.predicted_implant - target).norm();
      }
      const Point2 bias = verified - plan.predicted_implant;
      if (verified_error <= plan.tolerance_m || bias.norm() <= 0.5 * plan.tolerance_m ||
          round >= options_.max_corrections || expired()) {
        plan.budget_expired =
            plan.budget_expired || (verified_error > plan.tolerance_m && expired());
        break;
      }
      aim -= verified - target;  // next aim: cancel the verified miss
      ++plan.corrections;
      RigidPlan next = plan;
      searchPlan(next, *sim, aim, plan.release.y() - aim.y(), expired, resume);
      plan.scans = std::move(next.scans);
      plan.simulations = next.simulations;
      plan.release = next.release;
      plan.predicted_implant = next.predicted_implant;  // the O(1) model's own prediction
      plan.budget_expired = next.budget_expired;
    }
    finishVerifiedPlan(plan, std::move(best), steps(), work());
    plan.fem_steps_reused = resume.reused;
  });
}

namespace {

/// Where the cut front jumps over the target: of the scans, the one nearest the target's height
/// whose implant curve passes the target's depth in one step longer than the tolerance (the cut
/// is unstable there: the tip force stays above the cutting force across the stretch, so no tip
/// ever rests in it).
/// A seed that follows the tip moves about as far as the tip; a cut front that runs this many
/// times farther than the tip in one step is snapping through, not following.
constexpr double kSnapThroughRatio = 10.0;

struct CutJump {
  const DepthScan* scan = nullptr;  ///< null when no scan shows such a jump
  std::size_t at = 0;               ///< the jump runs from implant[at - 1] to implant[at]

  std::string describe() const {
    if (!scan) {
      return "";
    }
    return "at height " + mm(scan->height_m) + " the cut front jumps from depth " +
           mm(scan->implant[at - 1].x()) + " to " + mm(scan->implant[at].x()) +
           " over the target while the tip moves " + mm(scan->depth_m[at] - scan->depth_m[at - 1]) +
           " (the tip force stays above the cutting force there: no tip rests in that stretch)";
  }
};

CutJump jumpOver(const std::vector<DepthScan>& scans, const Point2& target, double tolerance) {
  CutJump jump;
  for (const DepthScan& scan : scans) {
    for (std::size_t i = 1; i < scan.implant.size(); ++i) {
      const Point2 &a = scan.implant[i - 1], &b = scan.implant[i];
      const double tip_move = scan.depth_m[i] - scan.depth_m[i - 1];
      if (a.x() < target.x() && b.x() > target.x() && (b - a).norm() > tolerance &&
          (b - a).norm() > kSnapThroughRatio * tip_move &&
          (!jump.scan ||
           std::abs(scan.height_m - target.y()) < std::abs(jump.scan->height_m - target.y()))) {
        jump = CutJump{&scan, i};
      }
    }
  }
  return jump;
}

}  // namespace

void RigidPlanner::finishVerifiedPlan(RigidPlan& plan, RigidPlan best, long fem_steps,
                                      double work) const {
  const int simulations = plan.simulations, verifications = plan.verifications,
            corrections = plan.corrections;
  const bool budget_expired = plan.budget_expired;
  const Point2 target = plan.target;
  std::vector<DepthScan> scans = std::move(plan.scans);
  plan = std::move(best);
  plan.scans = std::move(scans);
  for (DepthScan& scan : plan.scans) {
    scan.release_state.reset();  // the states are for verification only: free them
  }
  plan.simulations = simulations;
  plan.verifications = verifications;
  plan.corrections = corrections;
  plan.budget_expired = budget_expired;
  plan.fem_steps = fem_steps;
  plan.solver_work = work;
  plan.within_tolerance = plan.verified_error_m <= plan.tolerance_m;
  if (!plan.within_tolerance) {
    std::ostringstream budget;
    budget.precision(4);
    budget << "budget exhausted (" << work << " of " << options_.work_budget << " work units); ";
    // The message states only what the figures show: a verified error over the tolerance, or
    // a prediction the budget left no room to verify (whatever its size).
    const std::string figures = plan.verified ? "best verified error " + mm(plan.verified_error_m) +
                                                    " exceeds the tolerance " + mm(plan.tolerance_m)
                                              : "best release not verified (predicted error " +
                                                    mm(plan.predicted_error_m) + ", tolerance " +
                                                    mm(plan.tolerance_m) +
                                                    "): a full simulation would exceed the budget";
    const CutJump jump = jumpOver(plan.scans, target, plan.tolerance_m);
    plan.message = (budget_expired ? budget.str() : std::string()) + figures +
                   (jump.scan ? "; " + jump.describe() : std::string());
    // The embedded track's seed lands on the needle's own line, so the target's height is the
    // only one that can reach it: a jump over the target there is the physics' answer.
    const bool unstable_cut = sim_options_.needle_model == tissue::NeedleModel::kEmbeddedTrack &&
                              jump.scan &&
                              std::abs(jump.scan->height_m - target.y()) <= kSameHeight_m;
    if (options_.refuse_over_tolerance) {
      plan.code = unstable_cut ? PlanCode::kUnstableCut : PlanCode::kOutOfTolerance;
      plan.message = std::string("RigidPlanner: ") + toString(plan.code) + ": " + plan.message;
    }
  }
}

std::vector<RigidPlan> RigidPlanner::planAll(const std::vector<Point2>& targets,
                                             int threads) const {
  std::vector<RigidPlan> plans(targets.size());
  // plan() never throws: failures are codes.
  parallelFor(targets.size(), threads, [&](std::size_t i) { plans[i] = plan(targets[i]); });
  return plans;
}

scene::Scene withStiffnessFactors(const scene::Scene& scene, const std::vector<double>& factors) {
  if (factors.size() != scene.materials.size()) {
    throw std::invalid_argument("withStiffnessFactors: " + std::to_string(factors.size()) +
                                " factors for " + std::to_string(scene.materials.size()) +
                                " materials");
  }
  scene::Scene out = scene;
  for (std::size_t i = 0; i < factors.size(); ++i) {
    if (!(factors[i] > 0.0) || !std::isfinite(factors[i])) {
      throw std::invalid_argument("withStiffnessFactors: factor " + std::to_string(factors[i]) +
                                  " for material '" + scene.materials[i].name + "' must be > 0");
    }
    out.materials[i].young_modulus_Pa *= factors[i];
  }
  return out;
}

std::vector<std::vector<double>> drawStiffnessFactors(const scene::Scene& scene,
                                                      const StiffnessUncertainty& u) {
  if (!(u.relative >= 0.0 && u.relative < 1.0) || u.samples < 1) {
    throw std::invalid_argument(
        "drawStiffnessFactors: relative uncertainty must be in [0, 1) and samples >= 1");
  }
  std::mt19937 rng(u.seed);
  std::uniform_real_distribution<double> factor(1.0 - u.relative, 1.0 + u.relative);
  std::vector<std::vector<double>> out;
  const std::size_t m = scene.materials.size();
  const std::size_t corners = m < 16 ? (std::size_t{1} << m) : 0;
  if (u.corners_first && corners <= static_cast<std::size_t>(u.samples)) {
    for (std::size_t c = 0; c < corners; ++c) {
      std::vector<double> sample;
      for (std::size_t i = 0; i < m; ++i) {
        sample.push_back((c >> i) & 1U ? 1.0 + u.relative : 1.0 - u.relative);
      }
      out.push_back(sample);
    }
  }
  while (out.size() < static_cast<std::size_t>(u.samples)) {
    std::vector<double> sample;
    for (std::size_t i = 0; i < m; ++i) {
      sample.push_back(factor(rng));
    }
    out.push_back(sample);
  }
  return out;
}

RigidPlan RigidPlanner::planRobust(const Point2& target,
                                   const StiffnessUncertainty& uncertainty) const {
  if (!(uncertainty.quantile > 0.0 && uncertainty.quantile <= 1.0)) {
    throw std::invalid_argument("planRobust: quantile must be in (0, 1]");
  }
  return timed(target, [&](RigidPlan& plan) {
    std::vector<std::unique_ptr<RigidPlanner>> models;
    std::vector<std::unique_ptr<tissue::TissueSimulation>> sims;
    for (const auto& factors : drawStiffnessFactors(scene_, uncertainty)) {
      models.push_back(std::make_unique<RigidPlanner>(withStiffnessFactors(scene_, factors),
                                                      sim_options_, options_));
      sims.push_back(models.back()->makeSimulation(target));
    }
    const double max_depth = maxScanDepth(target);
    auto evaluate = [&](double y) {
      std::vector<DepthScan> scans(sims.size());
      parallelFor(sims.size(), uncertainty.threads, [&](std::size_t k) {
        scans[k] = models[k]->scan(*sims[k], y, target, max_depth);
      });
      plan.simulations += static_cast<int>(sims.size());
      // The depth minimising the quantile of the error over the samples, on the first sample's
      // depth grid with every sample interpolated there.
      HeightResult best{1e300, 0.0, Point2::Zero()};
      std::vector<double> errors(scans.size());
      for (double z : scans.front().depth_m) {
        Point2 mean_implant = Point2::Zero();
        for (std::size_t k = 0; k < scans.size(); ++k) {
          const Point2 p = scans[k].implantAt(z);
          errors[k] = (p - target).norm();
          mean_implant += p / static_cast<double>(scans.size());
        }
        const double objective = report::quantile(errors, uncertainty.quantile);
        if (objective < best.error_m) {
          best = {objective, z, mean_implant};
        }
      }
      return best;
    };
    if (uncertainty.search_height) {
      searchHeights(plan, evaluate, /*early_stop=*/false, target, 0.0);
    } else {
      const RigidPlan nominal = this->plan(target);  // its height; depth is where stiffness acts
      if (!nominal && nominal.code != PlanCode::kOutOfTolerance) {
        throw std::runtime_error(nominal.message);
      }
      plan.simulations += nominal.simulations;
      const HeightResult r = evaluate(nominal.release.y());
      plan.release = Point2(r.depth_m, nominal.release.y());
      plan.predicted_implant = r.implant;
      plan.predicted_error_m = r.error_m;
      plan.message = "ok";
    }
  });
}

DepthScan RigidPlanner::scanHeight(const Point2& target, double height_m) const {
  const RigidPlan feasible = check(target);
  if (!feasible) {
    throw std::invalid_argument(feasible.message);
  }
  const std::unique_ptr<tissue::TissueSimulation> sim = makeSimulation(target);
  return scan(*sim, height_m, target, maxScanDepth(target));
}

RigidPlan RigidPlanner::planDepthOnly(const Point2& target) const {
  return timed(target, [&](RigidPlan& plan) {
    const std::unique_ptr<tissue::TissueSimulation> sim = makeSimulation(target);
    plan.scans.push_back(scan(*sim, target.y(), target, maxScanDepth(target)));
    plan.simulations = 1;
    const DepthScan& s = plan.scans.back();
    plan.release = Point2(s.best_depth_m, target.y());
    plan.predicted_implant = s.best_implant;
    plan.predicted_error_m = s.best_error_m;
  });
}

RigidPlan RigidPlanner::unplanned(const Point2& target) const {
  RigidPlan plan = planDepthOnly(target);  // one scan at the target height
  if (plan) {
    plan.release = target;
    plan.predicted_implant = plan.scans.back().implantAt(target.x());
    plan.predicted_error_m = (plan.predicted_implant - target).norm();
  }
  return plan;
}

}  // namespace needle_guidance::rigid_planning
