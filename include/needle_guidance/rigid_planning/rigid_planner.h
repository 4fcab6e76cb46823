// Sensorless offset planning for a rigid needle in deformable tissue (dissertation ch. 4): find the
// release point (height, depth) whose seed, once the tissue has relaxed, lands on the target.
#pragma once

#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue/tissue_simulation.h"

namespace needle_guidance::rigid_planning {

using geometry::Point2;

/// One simulated insertion at a fixed height (4.3.2): the implant point p_a for every depth the
/// needle passed, read in O(1) per step from the tip's reference-mesh position (after retraction
/// the elastic tissue returns to its reference state, so a seed released at the tip ends there).
struct DepthScan {
  double height_m = 0.0;
  std::vector<double> depth_m;  ///< needle tip x at each step [m]
  std::vector<Point2> implant;  ///< p_a if released at that depth [m]
  double best_depth_m = 0.0;    ///< z_r*(y_r), interpolated between steps [m]
  Point2 best_implant = Point2::Zero();
  double best_error_m = 0.0;  ///< epsilon(y_r) [m]
  /// Signed distance of the implant curve from the target at the best depth, positive when the
  /// target lies to the left of the curve's direction of travel [m]: ~linear in height, the
  /// secant search drives it to zero.
  double lateral_m = 0.0;
  /// Grid scans of a copyable simulation: the simulation's state at best_depth_m, kept when
  /// best_error_m is within the tolerance. A verification releases from a copy of it instead
  /// of inserting again: the same FEM steps, bit for bit. Null otherwise.
  std::shared_ptr<const tissue::TissueSimulation> release_state;
  /// Solver work of this scan from the entry face (a resumed prefix included).
  double work = 0.0;
  /// The work (or time) budget ran out during this scan: it ends there, short of its planned
  /// depth (never before it has two implant points).
  bool cut_short = false;
  /// p_a and the error if released at depth z (linear between steps); z within the scan.
  Point2 implantAt(double depth_m) const;
};

struct PlannerOptions {
  double height_window_m = 0.002;    ///< search y_t +- this (4.4.3: 0.2 cm) [m]
  double height_tolerance_m = 1e-4;  ///< golden-section stop (4.4.3: 0.01 cm) [m]
  /// dz = v h between simulation steps [m]; with procedure_grid the simulation's depth grid
  /// (the tissue_sim node's default grid is the same 0.1 mm).
  double depth_step_m = 1e-4;
  /// Steps of the scan farther than approach_zone_m before the target depth use this larger dz
  /// (0: depth_step_m all the way). The cuts, not the steps, dominate a scan's cost, so this
  /// saves ~20 % of the planning time for ~0.02 mm of error (bench rigid, speed_vs_error) [m]
  double approach_step_m = 5e-4;
  double approach_zone_m = 0.005;  ///< fine steps within this of the target depth [m]
  double velocity_m_s = 0.005;     ///< v (4.4: 0.5 cm/s) [m/s]
  double depth_margin_m = 0.005;   ///< scan to target depth + margin (<= max depth) [m]
  int grid_points = 5;             ///< coarse heights that detect a non-unimodal error
  int secant_iterations = 6;       ///< secant steps on the lateral offset before the grid (0 = off)
  /// Stop searching heights once a scan's best error is below this (the target height is scanned
  /// first) [m]; 0: at 0.9 of the tolerance (stop at the scene's tolerance, not at a
  /// fixed floor).
  double error_goal_m = 0.0;
  /// Placement tolerance [m]; 0: the scene's needle.placement_tolerance_m.
  double tolerance_m = 0.0;
  /// Verify every plan with a full insert-release-retract simulation on the procedure's step
  /// schedule (below) and correct it on the verified error when the two disagree.
  bool verify = true;
  /// Scans on the depth grid (TissueSimulation::advance, release on a grid depth): the O(1)
  /// prediction then reads the very tip node a verification, and the live loop, release at (no
  /// interpolation between steps). false: the dissertation's scans (interpolated release, the
  /// approach steps below).
  bool procedure_grid = true;
  int max_corrections = 3;  ///< re-plans on the verified error after the first verification
  /// Work budget per plan, in solver work (tissue::TissueSimulation::solverWork(): millions of
  /// factor entries touched by solves, factor modifications and factorisations; 0: none), over
  /// scans and verifications. It is checked after every FEM step: a scan in progress stops
  /// where the budget runs out, and the best release found so far is verified (from its scan's
  /// state when within the tolerance; a full simulation only if the budget still covers it).
  /// The plan is placed only if its verified error is within the tolerance, else refused
  /// ("budget exhausted"). A count, so what is refused does not depend on the machine's load;
  /// weighted by what each operation costs, so it bounds the time on any mesh. A safety net
  /// about three times what the costliest plan of the bench's scenes needs with event-located
  /// interaction (6800 units, a deep target in the 10x bean-shaped gland; a unit took
  /// 1.0-1.75 ms of CPU on the 2-core development machine), so it is not what refuses a
  /// reachable target there.
  double work_budget = 20000.0;
  /// Wall-time budget per plan [s] (0: none), on top of work_budget: a plan that must answer
  /// in time. Outcomes then depend on the machine's load.
  double time_budget_s = 0.0;
  /// A plan whose verified error exceeds the tolerance is refused (kOutOfTolerance:
  /// every target placed within the tolerance or refused with a reason); false: returned as ok
  /// with within_tolerance false.
  bool refuse_over_tolerance = true;
};

/// How a full insert-release-retract simulation commands the needle (the procedure's motion): the
/// tip starts at start_x_m outside the tissue and is commanded in samples of sample_m to the
/// release depth, the seed is released, the tip is commanded back to start_x_m, and the tissue
/// is stepped with the needle out until the seed is at rest. TissueSimulation::advance() puts
/// every command on the scene's depth grid, so the seed does not depend on sample_m or start_x_m:
/// the live loop's 0.05 mm samples from -5 mm land where the planner's did.
struct ImplantSchedule {
  double start_x_m = -0.001;  ///< tip x before and after the insertion (outside the tissue) [m]
  double sample_m = 1e-4;     ///< commanded depth change per sample [m], > 0
  double dt_s = 0.01;         ///< time per sample (dynamic models only) [s]
  int max_rest_steps = 200;   ///< steps with the needle out, until the seed moves < 1 nm
};

/// A full insert-release-retract simulation (4.3.2 without the O(1) shortcut) on `sim` (reset
/// first), commanded as `schedule` says and advanced on the depth grid: the seed's final
/// position after retraction and rest [m]. Throws std::runtime_error if a step is refused or the
/// seed cannot be released, std::invalid_argument for sample_m <= 0.
Point2 simulateImplant(tissue::TissueSimulation& sim, const Point2& release,
                       const ImplantSchedule& schedule);

/// Stiffness uncertainty for robust planning: every material's Young's modulus is scaled by a
/// factor in [1 - u, 1 + u], independently per material, K times (fixed seed); optionally the
/// corners of that box come first.
struct StiffnessUncertainty {
  double relative = 0.3;       ///< u (0.3 = +-30 %)
  int samples = 16;            ///< K models planned against
  unsigned seed = 1;           ///< generator seed
  bool corners_first = false;  ///< start with the 2^materials corners of the box (if K allows)
  /// The plan minimises this quantile of the error over the samples: 1 = worst case, 0.95 = the
  /// 95th percentile. Compression ahead of the needle grows like 1/E (convex), so softer-than-
  /// modelled tissue costs more than stiffer saves; a quantile plan leans deeper than the nominal
  /// one. With independent materials most patients sit near the nominal model, so a minimax plan
  /// over the box corners over-hedges (measured: worse p95 than nominal).
  double quantile = 0.95;
  bool search_height =
      false;        ///< also search height (K x more simulations); else the nominal plan's
  int threads = 0;  ///< samples simulated at a time (<= 0: one per core)
};

/// `scene` with every material's Young's modulus scaled by its factor (one per material).
scene::Scene withStiffnessFactors(const scene::Scene& scene, const std::vector<double>& factors);
/// K sets of per-material factors drawn from `u` (deterministic for its seed).
std::vector<std::vector<double>> drawStiffnessFactors(const scene::Scene& scene,
                                                      const StiffnessUncertainty& u);

/// Why a plan failed, or kOk.
enum class PlanCode {
  kOk,
  kTargetNotFinite,  ///< a NaN or infinite target coordinate
  kTargetOutsideTissue,
  kHeightOutOfRange,
  kBeyondMaxDepth,
  kSimulationFailed,
  /// No release point whose verified seed lands within the tolerance was found (in the budget):
  /// the target is refused with the best verified error; release and verified_* still say where
  /// the best plan would put the seed, for a caller that accepts it.
  kOutOfTolerance,
  /// On the embedded track, whose seed lands on the needle's own line: at the target's height the
  /// cut front jumps over the target (the tip force stays above the cutting force across the
  /// stretch), so no tip ever rests near it and no depth reaches it.
  kUnstableCut
};

/// A plan: release point, predicted error, and what it cost.
struct RigidPlan {
  PlanCode code = PlanCode::kOk;
  std::string message;
  Point2 target = Point2::Zero();
  Point2 release = Point2::Zero();            ///< (depth x, height y) to release the seed [m]
  Point2 predicted_implant = Point2::Zero();  ///< where the seed is predicted to end [m]
  double predicted_error_m = 0.0;
  bool unimodal = true;  ///< false: the coarse grid found several minima (grid fallback)
  /// The secant search on the lateral offset met the goal, or bracketed the offset's zero to the
  /// mesh's resolution in height (a tenth of the height tolerance) with an error below 10x the
  /// goal.
  bool secant = false;
  int simulations = 0;           ///< insertions simulated: scans + verifications
  double seconds = 0.0;          ///< wall time [s]
  double cpu_seconds = 0.0;      ///< CPU time of the planning thread [s] (less load-dependent)
  std::vector<DepthScan> scans;  ///< every height simulated, in evaluation order
  /// Full insert-release-retract simulation of the plan (PlannerOptions::verify).
  bool verified = false;
  Point2 verified_implant = Point2::Zero();  ///< seed after the verifying simulation [m]
  double verified_error_m = NAN;             ///< |verified implant - target| [m]
  int verifications = 0;                     ///< full simulations among `simulations`
  int corrections = 0;                       ///< re-plans on the verified error
  /// FEM steps this plan stands for: every scan counted from the
  /// entry face, also when it resumed a cached insertion (so outcomes do not depend on what
  /// earlier plans cached).
  long fem_steps = 0;
  /// Of fem_steps: steps of cached insertion prefixes at the same height that this plan's scans
  /// resumed instead of solving again (scans of the scene's own targets; fem_steps - this were
  /// solved).
  long fem_steps_reused = 0;
  /// Solver work this plan stands for (PlannerOptions::work_budget), counted like fem_steps.
  double solver_work = 0.0;
  double tolerance_m = 0.0;       ///< placement tolerance the plan was held to [m]
  bool within_tolerance = false;  ///< verified (or, unverified, predicted) error <= tolerance
  bool budget_expired = false;    ///< the work (or time) budget ended the search
  explicit operator bool() const { return code == PlanCode::kOk; }
  const std::string& toString() const { return message; }
};

/// Plans with an in-process FEM model of the scene (the simulator of ch. 2). Thread-compatible:
/// plan() builds its own simulation.
class RigidPlanner {
public:
  /// Throws std::invalid_argument for a scene without tissue or invalid options.
  RigidPlanner(scene::Scene scene, tissue::TissueSimOptions sim_options, PlannerOptions options);
  RigidPlanner(const scene::Scene& scene, PlannerOptions options)
      : RigidPlanner(scene, tissue::optionsFromScene(scene), options) {}

  /// Golden-section search over height around the target (after a coarse grid that detects a
  /// non-unimodal error and then brackets the best grid point), each height scanned over depth.
  /// Then verifies the plan with a full simulation; if it misses by more than the tolerance and
  /// disagrees with the prediction, re-plans for the target shifted by the disagreement (a
  /// fixed-point step on the verified error) until within tolerance, max_corrections or the
  /// time budget. `first_height_offset_m` (warm start, e.g. the previous target's release height
  /// minus its target height) is tried right after the target height.
  RigidPlan plan(const Point2& target, double first_height_offset_m = 0.0) const;
  /// How verifications command the needle (the grid, not this, fixes the FEM steps).
  ImplantSchedule schedule() const;
  /// The simulation options plans use: the scene's, with depth_step_m as the depth grid when
  /// procedure_grid (the live tissue_sim must use the same grid for plans to hold).
  const tissue::TissueSimOptions& simOptions() const { return sim_options_; }
  /// A simulation of the scene meshed as the live tissue_sim meshes it, refined along the path
  /// to `target` too when the target is not one of the scene's (else a copy of one built once).
  std::unique_ptr<tissue::TissueSimulation> makeSimulation(const Point2& target) const;
  /// The tolerance plans are held to [m].
  double tolerance() const;
  /// One insertion at `height_m` scanned over depth for `target` (figures 4.5, 4.6). Throws
  /// std::invalid_argument for an infeasible target.
  DepthScan scanHeight(const Point2& target, double height_m) const;
  /// plan() for every target, `threads` plans at a time (each builds its own simulation, so the
  /// results equal sequential plans); in the order of `targets`. threads <= 0: one per core.
  std::vector<RigidPlan> planAll(const std::vector<Point2>& targets, int threads = 0) const;
  /// Depth only: the needle at the target's height, best depth (4.4.2).
  RigidPlan planDepthOnly(const Point2& target) const;
  /// No planning: release at the target (p_r = p_t); the predicted error is what deformation
  /// does to a naive insertion.
  RigidPlan unplanned(const Point2& target) const;
  /// Robust plan (beyond the dissertation): the release point minimising the mean (or worst)
  /// error over K stiffness samples of the tissue; predicted_error_m is that objective.
  RigidPlan planRobust(const Point2& target, const StiffnessUncertainty& uncertainty) const;

  const scene::Scene& scene() const { return scene_; }
  const PlannerOptions& options() const { return options_; }

private:
  /// A refusal for an infeasible target, or kOk.
  RigidPlan check(const Point2& target) const;
  /// One insertion at height_m to max_depth_m; with stop_past_target it ends once the implant
  /// curve has passed the target (a plan needs only the best depth; figures need the whole curve).
  DepthScan scan(tissue::TissueSimulation& sim, double height_m, const Point2& target,
                 double max_depth_m, bool stop_past_target = false) const;
  /// scan() on the simulation's depth grid: one advance() per grid point, best depth on a grid
  /// point (where a verification, and the live loop, release).
  /// With `resume` (a scan on the scene's own mesh): an insertion at the same height that an
  /// earlier scan stopped short of this one's end is continued from a copy of its state, bit for
  /// bit the same scan as from the entry face; `steps` adds the FEM steps the scan stands for
  /// when it ran on a copy (prefix and new steps), `reused` the prefix's.
  /// `out_of_budget(extra)`: whether the plan's budget is spent once `extra` work done on a copy
  /// of the plan's simulation (not yet in the plan's counters) is added; checked after every
  /// step of a scan (empty: no budget).
  struct ResumeCounters {
    bool resume = false;
    long steps = 0;
    long reused = 0;
    double work = 0.0;
    double work_reused = 0.0;
    std::function<bool(double)> out_of_budget;
  };
  DepthScan gridScan(tissue::TissueSimulation& sim, double height_m, const Point2& target,
                     double max_depth_m, bool stop_past_target,
                     ResumeCounters* resume = nullptr) const;
  /// gridScan from a cached insertion prefix at height_m, if one ends short of grid index `last`,
  /// the scan does not end within it and the budget covers it; nullopt otherwise (then a scan
  /// from the entry face, which stops where the budget runs out, as this one would).
  std::optional<DepthScan> resumeScan(double height_m, const Point2& target, long last,
                                      ResumeCounters& counters) const;
  /// Steps `sim` on the grid from its position to `last` (or until the scan passes the target,
  /// or `out_of_budget(work on sim since `work_from`)` says the budget ran out: cut_short),
  /// adding the implant points to `scan`.
  void runGridScan(tissue::TissueSimulation& sim, DepthScan& scan, const Point2& target, long last,
                   bool stop_past_target, const std::function<bool(double)>& out_of_budget = {},
                   double work_from = 0.0) const;
  /// Adds one grid point of an insertion to `scan` (`state`: the simulation there, or null when
  /// replaying a cached prefix); true when the scan may stop (the target is passed).
  bool addGridPoint(DepthScan& scan, double x, const Point2& tip, const Point2& target,
                    const tissue::TissueSimulation* state, bool stop_past_target) const;
  /// Caches `sim`'s state at the end of `scan` as the insertion prefix at its height (if deeper
  /// than the one cached).
  /// `work_from`: sim.solverWork() when the insertion was at the entry face.
  void storePrefix(const tissue::TissueSimulation& sim, const DepthScan& scan,
                   double work_from) const;
  /// The seed after releasing at plan.release and retracting: from the release state of the
  /// scan that found the release when it has one (its error is within the tolerance), else a
  /// full simulation on `sim` if the work budget has `work_left` for it (about the work of the
  /// scan that found the release), else nullopt. Adds the FEM steps and work run on a copy to
  /// plan.fem_steps and plan.solver_work (steps on `sim` count in sim's own counters).
  std::optional<Point2> verify(tissue::TissueSimulation& sim, RigidPlan& plan,
                               double work_left) const;
  /// The plan to return after the verification rounds: `best` (the best verified plan) with
  /// plan's counters and scans, refused (kOutOfTolerance) when over the tolerance.
  void finishVerifiedPlan(RigidPlan& plan, RigidPlan best, long fem_steps, double work) const;
  /// The O(1) height search for `aim` (the target, or the target shifted by a correction).
  void searchPlan(RigidPlan& plan, tissue::TissueSimulation& sim, const Point2& aim,
                  double first_offset_m, const std::function<bool()>& expired,
                  ResumeCounters& resume) const;
  /// One height's result for the search: objective, best depth, predicted implant.
  struct HeightResult {
    double error_m;
    double depth_m;
    Point2 implant;
    double lateral_m = 0.0;  ///< see DepthScan::lateral_m; 0 if unknown
  };
  /// Grid + golden-section search over height of `evaluate`, starting at the target height and
  /// stopping early below error_goal_m when `early_stop`.
  void searchHeights(RigidPlan& plan, const std::function<HeightResult(double)>& evaluate,
                     bool early_stop, const Point2& aim, double goal_m, double first_offset_m = 0.0,
                     const std::function<bool()>& expired = nullptr) const;
  /// Depth to scan to for a target: its depth plus the margin, at most the needle's max depth.
  double maxScanDepth(const Point2& target) const;
  /// check(), then `body` (exceptions become kSimulationFailed), with the wall time recorded.
  RigidPlan timed(const Point2& target, const std::function<void(RigidPlan&)>& body) const;

  scene::Scene scene_;
  tissue::TissueSimOptions sim_options_;
  PlannerOptions options_;
  /// The scene's simulation at rest, built on first use: plans to the scene's own targets (whose
  /// mesh is the scene's) copy it instead of meshing and assembling again. Shared by copies.
  struct SimulationCache;
  std::shared_ptr<SimulationCache> cache_;
};

const char* toString(PlanCode code);
/// True for a refusal the physics explains (outside the tissue or in bone, out of the needle's
/// range, an unstable cut over the target); false for ok, a failed simulation or a miss.
bool isPhysicalRefusal(PlanCode code);

}  // namespace needle_guidance::rigid_planning
