// The rigid seed-implant procedure (dissertation ch. 4), ROS-free: for every target
// plan the release point, move to its height (and, on a 3-D x-y stage, its lateral position),
// insert, implant a seed, retract, measure where the seed came to rest; success means the seed
// landed. Points are 3-D in frame scene; a planar scene's have z = 0 and no lateral move. The node
// drives real (simulated) devices through ROS, a test or a bench through in-process ones: all call
// RigidImplantProcedure::run.
#pragma once

#include <cmath>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/procedures/fault.h"
#include "needle_guidance/scene/scene.h"

namespace needle_guidance::procedures {

using Point3 = Eigen::Vector3d;

/// Per-target outcome: placed within the tolerance, missed (with the error), refused
/// by the planner (with the reason), or error (a move, the implant or a node failed).
enum class TargetOutcome { kPlaced, kMissed, kRefused, kError };
const char* toString(TargetOutcome outcome);

/// One robot move as the device reports it.
struct MoveResult {
  bool ok = false;
  double reached_m = NAN;          ///< joint position at the end [m]
  double duration_s = 0.0;         ///< 0: never started
  double mean_velocity_m_s = 0.0;  ///< over the move [m/s]
  std::string state;               ///< e.g. SUCCEEDED, ABORTED, "stopped: node died"
};

/// A planner's answer for one target.
struct PlanResult {
  bool ok = false;
  bool refused = false;  ///< the target is infeasible (a reason, not a failure)
  /// Refused for a physical reason (outside the tissue, in or behind bone, out of the robot's
  /// reach): a 3-D run succeeds without placing such a target. Never set by the planar planner.
  bool unreachable = false;
  std::string message;
  Point3 release = Point3::Zero();  ///< depth x, height y, lateral z [m]
  double predicted_error_m = NAN;
  double verified_error_m = NAN;   ///< NaN: not verified
  double unplanned_error_m = NAN;  ///< prediction for a release at the target [m]
  double plan_s = NAN;
};

/// What the procedure drives. Moves block until they end; a device that sees a fault during a
/// move stops it and returns ok = false.
class RigidImplantDevices {
public:
  virtual ~RigidImplantDevices() = default;
  virtual bool hasPlanner() const = 0;
  virtual bool hasTissue() const = 0;
  virtual PlanResult plan(const Point3& target) = 0;
  virtual MoveResult moveHeight(double height_m, double velocity_m_s) = 0;
  /// The x-y stage's lateral axis (z) [m]; called only when the settings say lateral_stage.
  virtual MoveResult moveLateral(double /*lateral_m*/, double /*velocity_m_s*/) {
    MoveResult r;
    r.state = "no lateral axis";
    return r;
  }
  /// Insertion (to a deeper x) or retraction (to a shallower x) from from_m [m].
  virtual MoveResult moveDepth(double depth_m, double velocity_m_s, double from_m,
                               bool retract) = 0;
  /// The robot's tip (frame scene) once at rest, if known [m].
  virtual std::optional<Point3> tip() = 0;
  /// Releases a seed at the tip: its id, or nullopt with the reason.
  virtual std::optional<int> implantSeed(std::string& why_not) = 0;
  /// Where seed `id` rests once the needle is out [m].
  virtual std::optional<Point3> seedAtRest(int id) = 0;
  virtual void resetTissue() = 0;
  /// The first fault seen (a dead node), if any; the procedure then stops.
  virtual std::optional<Fault> fault() = 0;
  /// Brings the robot to a safe state after a fault (retract, else emergency stop); what it did.
  virtual std::string safeStop(double retract_depth_m, double velocity_m_s) = 0;
  /// One line of progress per target ("target 3/12 t03: placed, ..."); a node logs it.
  virtual void progress(const std::string& /*line*/) {}
  /// Seconds since the procedure started (the devices' clock).
  virtual double now_s() const = 0;
};

struct RigidImplantSettings {
  double insertion_velocity_m_s = 0.01;
  double retract_velocity_m_s = 0.02;
  double height_velocity_m_s = 0.01;
  double retract_depth_m = -0.005;      ///< tip x between needles (outside the tissue) [m]
  double depth_tolerance_m = 1e-6;      ///< robot depth error still "ok" [m]
  double velocity_tolerance = 0.05;     ///< relative insertion speed error still "ok"
  double placement_tolerance_m = 1e-4;  ///< a seed within this of its target is placed [m]
  int max_targets = 0;                  ///< 0: all
  bool reset_between_needles = true;    ///< each needle meets undisturbed tissue (4.4)
  bool lateral_stage = false;           ///< move the lateral axis (z) before each insertion
};

/// A seed target of the procedure [m], frame scene.
struct ImplantTarget {
  std::string name;
  Point3 position = Point3::Zero();
};

/// One target tried.
struct TargetRecord {
  std::string name;
  Point3 target = Point3::Zero();
  Point3 aim = Point3::Zero();  ///< release point commanded [m]
  PlanResult plan;
  MoveResult height, lateral, insert, retract;
  double tip_error_m = NAN;
  int seed_id = -1;
  Point3 seed{NAN, NAN, NAN};  ///< where the seed rests [m]; NaN: not measured
  std::string status = "ok";   ///< what went wrong with the moves, or ok
  TargetOutcome outcome = TargetOutcome::kError;
  std::string reason;  ///< why refused / missed / error
  bool inserted() const { return insert.ok || insert.duration_s > 0.0; }
  double seedError_m() const { return seed.allFinite() ? (seed - target).norm() : NAN; }
};

/// The procedure's report: every target tried, the headline counts, the fault if one ended it.
struct RigidImplantReport {
  std::string scene;
  bool planned = false, with_tissue = false;
  RigidImplantSettings settings;
  int targets_in_scene = 0;
  std::vector<TargetRecord> records;  ///< targets actually tried, in order
  std::optional<Fault> fault;
  std::string safe_stop;  ///< what the robot did after the fault
  double wall_time_s = 0.0;

  int count(TargetOutcome outcome) const;
  /// Targets refused for a physical reason (PlanResult::unreachable).
  int unreachableCount() const;
  /// Every target of the run tried and, planned, placed or refused as unreachable (unplanned:
  /// every move ok).
  bool success() const;
  /// moves.csv, summary.json, summary.md and seed_errors.png (seed error per target against the
  /// tolerance, coloured by outcome) in `dir`. Throws std::runtime_error if a file fails.
  void write(const std::string& dir) const;
  std::string summaryJson() const;
  std::string summaryMarkdown() const;
  /// Console table.
  std::string text() const;
};

class RigidImplantProcedure {
public:
  /// Throws std::invalid_argument for settings out of range.
  RigidImplantProcedure(const scene::Scene& scene, RigidImplantSettings settings);
  /// Any targets (a 3-D scene's): the entry face is the plane x = entry_x_m.
  RigidImplantProcedure(std::string scene_name, std::vector<ImplantTarget> targets,
                        double entry_x_m, RigidImplantSettings settings);
  /// Runs the targets in order until done or a fault; never throws for device failures (they
  /// are outcomes). On a fault the robot is stopped safely and the report names the fault.
  RigidImplantReport run(RigidImplantDevices& devices) const;

private:
  /// One target: plan, height, insert, implant, retract, measure. false: a fault ended it.
  bool runTarget(RigidImplantDevices& devices, TargetRecord& r, double& depth_now) const;
  void classify(TargetRecord& r, bool with_tissue) const;

  std::string scene_name_;
  std::vector<ImplantTarget> targets_;
  double entry_x_m_ = 0.0;
  RigidImplantSettings settings_;
};

}  // namespace needle_guidance::procedures
