// The closed-loop steerable-needle procedure (dissertation 5.5, figure 5.8), ROS-free: place the
// needle at the best start, then after every insertion step read the tip, take the policy's
// control for it (insert, or flip then insert) and insert one step of delta = 2 pi r / N_c, until
// the true tip reaches the target, the needle touches an obstacle or leaves the workspace, or the
// step limit. N trials give the success rate against the predicted P_s.
//
// The loop drives SteerableDevices: the steerable_procedure node drives the real (simulated)
// robot, policy and tracker over ROS; the bench and tests drive an in-process needle, policy
// table and optional imager + tracker (guided_trial.h). Both run SteerableTrials::run.
#pragma once

#include <cmath>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/procedures/fault.h"
#include "needle_guidance/steering/adaptive_policy.h"
#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/policy_table.h"

namespace needle_guidance::procedures {

/// How one trial ended. kError (a device failed, a node died, no usable control) is reported
/// apart from the misses.
enum class SteerableOutcome {
  kReachedTarget,
  kHitObstacle,
  kLeftWorkspace,
  kStepLimit,
  kNeedleLength,  ///< a miss: the insertion joint's limit came before the target
  kError,
};
/// "reached_target" | "hit_obstacle" | "left_workspace" | "step_limit" | "needle_length" | "error".
const char* toString(SteerableOutcome outcome);

/// A tip as a device reports it (frame scene).
struct SteerableTip {
  steering::TipPose pose;
  double inserted_length_m = 0.0;
  std::string source = "ground_truth";  ///< e.g. ground_truth, image, predicted
  bool confident = true;
};

/// The policy's answer to the tip measured after the last motion.
struct PolicyAnswer {
  /// There is a control to act on (the policy's look-up statuses ok, in_target, in_obstacle,
  /// outside_grid); false for a status without one (e.g. invalid_tip), named in `status`.
  bool usable = false;
  std::string status;
  steering::Control control = steering::Control::kInsert;
  double probability_of_success = 0.0;
  steering::TipPose looked_up;  ///< the pose the policy was given (the tracker's estimate)
  std::string source = "ground_truth";
  bool confident = true;
  /// The noise the answering table assumes [rad] (the scene's until the policy re-solves for
  /// the noise it learned); NaN when the policy does not say.
  double sigma_insert_rad = NAN;
  double sigma_flip_rad = NAN;
};

/// How an insertion step ended.
enum class StepEnd { kMoved, kObstacle, kLeftWorkspace, kJointLimit, kFailed };

/// What the trial loop drives. Every call blocks until it has an answer; a device that sees a
/// fault (a node it depends on died) returns a failure and fault() names it.
class SteerableDevices {
public:
  virtual ~SteerableDevices() = default;
  /// Takes the needle out if it is in, places it at `start` and (with `reseed`) seeds its
  /// deflection stream with `seed`; starts recording tip samples. false with the reason.
  virtual bool placeAtEntry(const steering::TipPose& start, std::uint64_t seed, bool reseed,
                            std::string& why_not) = 0;
  /// The true tip after the last motion (the world's referee), or nullopt with the reason.
  virtual std::optional<SteerableTip> tip(std::string& why_not) = 0;
  /// The policy's answer for the tip after the last motion (with image feedback, the device waits
  /// a bounded number of frames for a confident one), or nullopt with the reason.
  virtual std::optional<PolicyAnswer> control(std::string& why_not) = 0;
  virtual bool flip(std::string& why_not) = 0;
  /// Inserts to `length_m`; on a stop, `message` says what stopped it.
  virtual StepEnd insertTo(double length_m, std::string& message) = 0;
  /// The tip samples recorded since placeAtEntry (stops recording).
  virtual std::vector<SteerableTip> takeSamples() = 0;
  /// The first fault seen, if any; the run then stops.
  virtual std::optional<Fault> fault() = 0;
  /// At the end of the run: leave the needle out of the tissue if the robot can move; what it
  /// did ("" when nothing was needed).
  virtual std::string leaveSafe() = 0;
  /// One line of progress per trial ("trial 3/30: reached_target ..."); a node logs it.
  virtual void progress(const std::string& /*line*/) {}
};

/// One decision point of a trial (figure 5.8: small dots insert, large dots flip).
struct SteerableDecision {
  SteerableTip truth;     ///< the world's tip
  PolicyAnswer answer;    ///< what the policy was told and answered
  bool answered = false;  ///< false for the end-of-trial entries (no control)
  double tipError_m() const;
  double headingError_rad() const;
};

struct SteerableTrialRecord {
  SteerableOutcome outcome = SteerableOutcome::kError;
  std::string message;
  int steps = 0;
  int flips = 0;
  int unconfident_decisions = 0;  ///< controls taken on a tip the tracker was not confident of
  double seconds = 0.0;
  std::vector<SteerableDecision> decisions;
  std::vector<SteerableTip> samples;  ///< every measured tip during the trial
  /// The noise the trial's first answer assumed (see PolicyAnswer), if it said.
  std::optional<steering::TrialNoise> noise;
};

/// The trials that one policy table answered, with that table's own prediction: its P_s of the
/// start and a Monte Carlo in a world with the noise it assumes (after a re-solve the
/// scene's table no longer predicts the run).
struct SteerableTableReport {
  steering::TrialNoise noise;
  std::vector<int> trials;  ///< indices into records
  double predicted_ps = 0.0;
  steering::MonteCarloResult monte_carlo;
};

struct SteerableSettings {
  int trials = 20;
  int max_steps = 40;
  long seed = 1;  ///< trial k's deflection stream is seed * kTrialSeedStride + k; -1: the device's
  std::string feedback = "ground_truth";  ///< label for the report: ground_truth | image
  static constexpr std::uint64_t kTrialSeedStride = 100000;
};

/// Where the run starts, what the policy predicts for it and how the policy verified it
/// (steering/start_verification.h; verification_trials 0 = not verified).
struct SteerableStart {
  steering::TipPose pose;
  double predicted_ps = 0.0;
  double verified_ps = 0.0;  ///< the policy's Monte Carlo of the continuous needle
  steering::Interval verified_ci{0.0, 1.0};
  std::int64_t verification_trials = 0;
  bool confirmed = false;      ///< the policy's verification confirmed the prediction
  double table_best_ps = 0.0;  ///< the table's maximum P_s on the entry line
  /// The P_s the procedure reports at its start: the prediction when the policy's verification
  /// confirmed it (or did not verify), else the verified rate (steering::VerifiedStart::reported).
  double reportedPs() const {
    return verification_trials > 0 && !confirmed ? verified_ps : predicted_ps;
  }
  /// True if the report's own Monte Carlo confirms predicted_ps by the policy's rule:
  /// |predicted - rate| + z SE <= tolerance (steering::verificationConfirms).
  bool confirmedBy(const steering::MonteCarloResult& mc, double tolerance) const;
  /// True if reportedPs() lies within `tolerance` of the report's own Monte Carlo rate.
  bool reportedAgreesWith(const steering::MonteCarloResult& mc, double tolerance) const;
};

/// The run's report: every trial, the prediction, the core Monte Carlo from the same start with
/// the same table, the P_s map of figure 5.7 and the fault if one ended the run.
struct SteerableReport {
  std::string scene;
  steering::SteeringProblem problem;
  SteerableSettings settings;
  SteerableStart start;
  std::string model;         ///< the policy model's description
  std::string policy_table;  ///< loaded | solved
  double estimated_ps_error = 0.0;
  std::vector<SteerableTrialRecord> records;
  std::optional<Fault> fault;
  std::string safe_stop;  ///< what leaveSafe() did
  steering::MonteCarloResult monte_carlo;
  /// Start candidates on the entry line: bevel, y [m], theta [rad], P_s.
  std::vector<steering::StartCandidate> ps_map;
  /// Per table that answered (addTablesUsed); empty when not known.
  std::vector<SteerableTableReport> tables;
  double wall_time_s = 0.0;

  /// The noise of the trials whose answers said it, in order; `record_index` gets their indices
  /// into records.
  std::vector<steering::TrialNoise> trialNoises(std::vector<int>& record_index) const;
  /// Fills `tables` from steering::tablesUsed(...) of trialNoises(record_index): each table's
  /// P_s of the start and a Monte Carlo of monteCarloTrials(its P_s, the tolerance) in its own
  /// problem's world.
  void addTablesUsed(const std::vector<steering::TableUsed>& used,
                     const std::vector<int>& record_index);

  int successes() const;
  int errored() const;
  /// Trials that ran to an outcome (errored ones excluded).
  int counted() const;
  steering::Interval successInterval() const;
  /// Every requested trial ran to an outcome, no fault, and with ground-truth feedback the
  /// success rate's 95 % interval reaches the prediction or lies above it (the prediction
  /// assumes an exactly localised tip; with images a lower rate is the measured cost of
  /// tracking, reported as predicted_within_ci, not a failure).
  bool success() const;
  /// trials.csv, paths.csv, decisions.csv, ps_map.csv, obstacles.csv, summary.json, summary.md,
  /// paths.png (figure 5.8) and ps_map.png (figure 5.7 with its colour key) in `dir`.
  void write(const std::string& dir) const;
  std::string summaryJson() const;
  std::string summaryMarkdown() const;
  /// Console summary.
  std::string text() const;
};

/// One trial of the loop: the needle is placed at `start` with deflection stream `seed` (when
/// `reseed`), then stepped by delta_m (2 pi r / N_c of the steering problem) until the true tip
/// (checked after each step) is in the target, a step stops (obstacle, workspace, joint limit,
/// failure), a device fails, or max_steps. Never throws for device failures (kError).
SteerableTrialRecord runSteerableTrial(SteerableDevices& devices,
                                       const needle_model::PlanarWorld& world, double delta_m,
                                       const steering::TipPose& start, std::uint64_t seed,
                                       bool reseed, int max_steps);

class SteerableTrials {
public:
  /// `table` is the policy the report's Monte Carlo and P_s map (over the start states of
  /// `starts`) use: the one the policy node answers from; it must outlive the object. Throws
  /// std::invalid_argument for bad settings.
  SteerableTrials(std::string scene_name, const steering::SteeringProblem& problem,
                  const steering::PolicyTable& table, const steering::StartOptions& starts,
                  SteerableSettings settings);
  /// Runs the trials from `start` until done or a fault, then leaves the needle safe and fills
  /// the report (Monte Carlo of monteCarloTrials(reported P_s, tolerance), P_s map). Never
  /// throws for device failures.
  SteerableReport run(SteerableDevices& devices, const SteerableStart& start) const;
  /// The report's own Monte Carlo of a start whose P_s is about `ps`: enough trials that 1.96
  /// standard errors are at most tolerance / 2 (steering::verificationCap: 38,415 at P_s 0.5 and
  /// tolerance 0.01, 149,700 at 0.58 and 0.005), so the report can tell a P_s off by the
  /// tolerance from its own noise; within [kMinMonteCarloTrials, kMaxMonteCarloTrials].
  static std::int64_t monteCarloTrials(double ps, double tolerance);
  static constexpr std::int64_t kMinMonteCarloTrials = 10000;
  static constexpr std::int64_t kMaxMonteCarloTrials = 200000;
  static constexpr std::uint64_t kMonteCarloSeed = 11;

private:
  std::string scene_name_;
  steering::SteeringProblem problem_;
  steering::ContinuousWorkspace world_;
  const steering::PolicyTable& table_;
  steering::StartOptions starts_;
  SteerableSettings settings_;
};

}  // namespace needle_guidance::procedures
