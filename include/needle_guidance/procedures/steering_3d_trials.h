// The ROS-free part of the 3-D steerable-needle procedure (node steerable_procedure_3d):
// the simulated world of one trial driven by controls that come from outside (the
// steering_planner_3d node), and the report of N trials. The world is the core's noisy needle
// (needle_3d.h) stepped and refereed exactly as in runTrial3 (closed_loop_3d.h: executeStep3,
// finishTrial3), so a trial's outcome means the same in the bench and in the ROS loop.
#pragma once

#include <cstdint>
#include <deque>
#include <functional>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/imaging/biplane_views.h"
#include "needle_guidance/steering_3d/closed_loop_3d.h"

namespace needle_guidance::procedures {

/// Where the planner's tip comes from.
enum class TipSource3 {
  kTruth,    ///< the world's true tip
  kBiplane,  ///< two rendered fluoroscopy views, detected and triangulated (biplane_views.h)
};
/// "truth" | "biplane"; nullopt for anything else.
std::optional<TipSource3> tipSource3FromString(const std::string& name);
/// As tipSource3FromString; throws std::runtime_error naming the parameter `where` otherwise.
TipSource3 tipSource3OrThrow(const std::string& name, const std::string& where);

/// One trial's world: the true tip, its noisy needle and the outcome so far.
class SteeringTrial3 {
public:
  /// The scene and world must outlive it; `seed` seeds the needle's noise.
  SteeringTrial3(const needle_model::Scene3d& scene, const needle_model::CollisionWorld3& world,
                 const needle_model::NoiseParams3& noise, std::uint64_t seed, int max_steps);

  /// The world's answer to one control: moves `tip`, counts the step in `result`, appends its
  /// path and, on a contact, sets result.contact / obstacle / message and returns false (the
  /// contract of closed_loop_3d's executeStep3). Throws std::runtime_error on a fault of the
  /// device (the trial is then aborted by the caller).
  using WorldStep3 =
      std::function<bool(const needle_model::Control3& control, needle_model::TipPose3& tip,
                         steering_3d::TrialResult3& result)>;
  /// Replaces the in-process noisy needle by another world (e.g. the insertion robot's 3-D mode).
  void setWorld(WorldStep3 world) { world_step_ = std::move(world); }

  /// What sees the needle after a step: the two views' observation of the trial's true needle
  /// `path` (entry -> tip) given the `predicted` tip (its bevel) and a frame `index` unique to the
  /// step. Throws std::runtime_error on a fault of the device (e.g. no frame came).
  using Observe3 = std::function<imaging::BiplaneObservation3(
      const std::vector<needle_model::Vector3>& path, const needle_model::TipPose3& predicted,
      std::uint64_t index)>;
  /// Images the needle after every step with `observe` (empty: the truth): observedTip() is
  /// then the fused estimate or, after a dropped or gated pair, the previous estimate advanced by
  /// the control (as runTrial3's biplane option); the result counts the pairs fused, dropped and
  /// gated and the largest estimate error.
  void setObserver(Observe3 observe) { observe_ = std::move(observe); }
  /// setObserver with `views` rendering in process (not owned, must outlive the trial; null: the
  /// truth).
  void setViews(const imaging::BiplaneViews3* views);
  /// The tip the planner is given: the truth, or the biplane estimate with an observer.
  const needle_model::TipPose3& observedTip() const { return observe_ ? estimate_ : tip_; }
  /// The covariance of observedTip()'s position [m^2]: the fused views' with setViews and a
  /// fused pair, else sigma_m^2 I (the truth's configured sigma, or after a dropped/gated pair).
  needle_model::Matrix3 observedCovariance_m2(double sigma_m) const;
  /// The last biplane observation (frames, detections, fusion), with an observer.
  const imaging::BiplaneObservation3& lastObservation() const { return observation_; }

  /// Places the tip at the entry plan's start (no motion yet).
  void start(const needle_model::TipPose3& entry, double predicted_p_success,
             double initial_plan_s);
  /// Ends the trial without a start (the entry plan failed).
  void refuseStart(steering_3d::PlanCode code, const std::string& message);
  /// Replaces the plan being followed (controls from the current tip, as Plan3::controls).
  void setPlan(const std::vector<needle_model::Control3>& controls);
  /// Executes the plan's next control for at most one step (scene step_length_m), as runTrial3:
  /// the trial ends when the plan is used up (the tip is refereed against the target ball), the
  /// path touches an obstacle or leaves the tissue, or after max_steps; with no plan left it ends
  /// where the tip is. Returns false once the trial has ended.
  bool step();
  /// Ends a trial that stopped early (e.g. no control came): refereed where the tip is, with
  /// `message` as the reason.
  void abort(const std::string& message);
  /// The insertion joint's travel [m] (default: unlimited): a step that would insert the needle
  /// beyond it is not executed; the trial ends there, a failure whose message names the travel
  /// (the needle stays where it is, in the tissue, until the next placement retracts it).
  void setTravel(double travel_m) { travel_m_ = travel_m; }
  /// Arc length inserted so far in this trial [m].
  double insertedLength_m() const { return inserted_m_; }
  /// The planner's answer to the last tip (SteeringControl3's status): "ok" records the replan
  /// time and follows `controls`; "bad_input" aborts the trial ("the planner refused the tip: "
  /// + message) and returns false (a fault); any other status records the time and keeps the
  /// previous plan (as runTrial3 does when a replan finds none).
  bool followAnswer(const std::string& status, const std::string& message, double plan_seconds,
                    const std::vector<needle_model::Control3>& controls);
  /// Records one replan's planner time [s].
  void recordReplan(double seconds) { result_.replan_s.push_back(seconds); }

  bool done() const { return done_; }
  const needle_model::TipPose3& tip() const { return tip_; }
  const steering_3d::TrialResult3& result() const { return result_; }

private:
  void end();
  void observe(const needle_model::Control3& control);

  const needle_model::Scene3d& scene_;
  const needle_model::CollisionWorld3& world_;
  needle_model::NoisyNeedle3 needle_;
  WorldStep3 world_step_;
  Observe3 observe_;
  needle_model::TipPose3 estimate_;
  imaging::BiplaneObservation3 observation_;
  int max_steps_;
  std::uint64_t seed_;
  needle_model::TipPose3 tip_;
  std::deque<needle_model::Control3> plan_;
  steering_3d::TrialResult3 result_;
  double travel_m_ = std::numeric_limits<double>::infinity();
  double inserted_m_ = 0.0;
  bool done_ = false;
};

/// The plan status a planner names ("no_path_within_budget" for any name it does not know).
steering_3d::PlanCode planCodeFromName(const std::string& name);

/// Aggregate of a run's trials.
struct SteeringSummary3 {
  int trials = 0;
  int successes = 0;
  double success_rate = 0.0;
  double success_ci_low = 0.0;  ///< 95 % Wilson interval
  double success_ci_high = 1.0;
  double target_error_mm_median = 0.0;  ///< over trials with a start
  double target_error_mm_max = 0.0;
  double replan_ms_median = 0.0;  ///< planner time of each replan, all trials
  double replan_ms_p95 = 0.0;
  double replan_ms_max = 0.0;
  double initial_plan_s_median = 0.0;
  double predicted_p_success_mean = 0.0;
  int faults = 0;  ///< trials ended by a fault of the loop (no control, timeout), not an outcome
  /// Biplane tip source: view pairs fused, dropped (a view found no tip) and gated (refused as
  /// disagreeing), and the largest estimate-to-true-tip distance [mm]; zero with the truth.
  int views_fused = 0;
  int views_dropped = 0;
  int views_gated = 0;
  double estimate_error_mm_max = 0.0;
};

SteeringSummary3 summarize(const std::vector<steering_3d::TrialResult3>& results,
                           const std::vector<bool>& faulted);

/// One line for a log: a trial's outcome, target error, steps and reason; a run's successes
/// with their interval, median error and replan time, and with biplane views their counts.
std::string describe(const steering_3d::TrialResult3& result);
std::string describe(const SteeringSummary3& summary);

/// The run's outcome ("success" in summary.json): no fault, and the success rate's 95 % interval
/// reaches the mean predicted P(success) (it contains it or lies above it).
bool runSucceeded(const SteeringSummary3& summary);

/// A node the run depended on died (the same report keys as every procedure's: dead_node, cause).
struct NodeDeath3 {
  std::string dead_node;         ///< e.g. /steering_planner_3d; empty: no death
  std::string cause;             ///< one line
  double detected_unix_s = 0.0;  ///< when the death was seen [s since the epoch]
};

/// What the 3-D procedure drives: the node's planner and robot over ROS (or fakes in a test).
class SteeringDevices3 {
public:
  virtual ~SteeringDevices3() = default;
  /// Runs one trial from its entry plan to its end (trial.start / setWorld / setPlan / step).
  /// False, or a throw, is a fault of the loop (the trial is aborted with its reason).
  virtual bool runTrial(SteeringTrial3& trial, std::uint64_t trial_seed) = 0;
  /// The cause of a fault that ends the run (a dead node, a shutdown); nullopt while all is well.
  virtual std::optional<std::string> fault() = 0;
  /// Leaves the robot safe after the last trial or a fault: the needle retracted out of the
  /// tissue if the robot lives. What was done, e.g. "needle retracted", "none possible: ...".
  virtual std::string leaveSafe() = 0;
  /// A progress line for the log.
  virtual void progress(const std::string& line) = 0;
};

/// The trials of one run and how it ended.
struct SteeringRun3 {
  std::vector<steering_3d::TrialResult3> results;
  std::vector<bool> faulted;  ///< per trial: a fault ended it
  std::string safe_stop;      ///< what leaveSafe() did
  /// All `trials` were run and none ended in a fault.
  bool completed(int trials) const;
};

/// Records one step the robot made (its steer result) in `result`, as executeStep3 would:
/// counts it, appends `path` (its first point, the start, left out) and, on contact "obstacle" or
/// "outside_tissue", sets contact / obstacle / message. True: free; false: a contact; nullopt: a
/// fault (the goal failed without a contact).
std::optional<bool> recordRobotStep3(bool succeeded, const std::string& contact,
                                     const std::string& obstacle, const std::string& message,
                                     const std::vector<needle_model::Vector3>& path,
                                     steering_3d::TrialResult3& result);

/// Runs `trials` trials (trial k seeded seed * 100000 + k, the travel set on each) until done or
/// a fault, then always calls devices.leaveSafe() and records what it did.
SteeringRun3 runSteeringTrials3(const needle_model::Scene3d& scene,
                                const needle_model::CollisionWorld3& world,
                                SteeringDevices3& devices, int trials, std::uint64_t seed,
                                int max_steps, double travel_m);

/// Writes summary.json, trials.csv, paths.csv and target_error.png / replan_ms.png to
/// report_dir (which the caller prepared). `round_trip_ms` are the tip-to-control latencies the
/// node measured; with a `death` the status is node_died and the report names the node;
/// summary.json's safe_stop is run.safe_stop. Throws std::runtime_error naming a file it cannot
/// write.
void writeSteeringReport3(const std::string& report_dir, const needle_model::Scene3d& scene,
                          const SteeringRun3& run, const std::vector<double>& round_trip_ms,
                          std::uint64_t seed, const NodeDeath3& death = {});

}  // namespace needle_guidance::procedures
