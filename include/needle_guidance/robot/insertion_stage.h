// Simulated needle insertion stage: height (y), insertion depth (x) and bevel rotation about the
// needle axis, moved at commanded constant velocities within joint, velocity and scene limits.
// The device model behind the insertion_robot node; no ROS here.
#pragma once

#include <array>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/status.h"

namespace needle_guidance::robot {

/// The stage's joints, in the order of arrays indexed by joint. kLateral (z) is the lateral
/// axis of the x-y stage of the 3-D tissue procedures; a URDF without a "lateral" joint has
/// none (its limits stay [0, 0] and it never moves).
enum class StageJoint { kHeight = 0, kDepth = 1, kBevel = 2, kLateral = 3 };
constexpr std::size_t kStageJointCount = 4;

/// Joint name in the URDF and on measured_js ("height", "insertion", "bevel", "lateral").
const char* jointName(StageJoint joint);

/// Position and velocity limits of one joint [m, m/s] or [rad, rad/s].
struct JointLimits {
  double lower = 0.0;
  double upper = 0.0;
  double max_velocity = 0.0;  ///< > 0
};

/// Hardware limits of the stage, read from its URDF.
struct StageLimits {
  std::array<JointLimits, kStageJointCount> joints;
  bool has_lateral = false;      ///< the URDF has the "lateral" joint (z of the x-y stage)
  double needle_length_m = 0.0;  ///< needle hub to tip [m]
  /// Velocity limit of the continuous joint "axial_rotation" (the needle spun about its axis in
  /// 3-D steerable mode) [rad/s]; 0 if the URDF has none.
  double spin_rate_max_rad_s = 0.0;
  const JointLimits& operator[](StageJoint j) const { return joints[static_cast<std::size_t>(j)]; }
};

/// Reads joint limits of "height", "insertion", "bevel" (and "lateral" when present) and the needle
/// length (the origin of fixed joint "needle_tip_joint", if present, else the `needle_length_m`
/// argument) from URDF text with urdfdom, and the velocity limit of "axial_rotation" when present.
/// Throws std::invalid_argument naming the joint for a missing joint, a joint without limits,
/// non-positive velocity limits or lower >= upper.
StageLimits parseStageLimits(const std::string& urdf_xml);

/// Procedure limits a scene adds on top of the hardware: the needle may enter tissue only
/// between these heights (and lateral positions) and up to this depth.
struct SceneLimits {
  double min_height_m = 0.0;
  double max_height_m = 0.0;
  double max_depth_m = 0.0;
  double entry_x_m = 0.0;      ///< the tissue's entry face is the plane x = entry_x_m [m]
  double min_lateral_m = 0.0;  ///< lateral (z) range of entry; [0, 0] without a lateral stage
  double max_lateral_m = 0.0;
};

/// Joint positions [m, m, rad, m] and velocities of the stage.
struct StageState {
  std::array<double, kStageJointCount> position{0.0, 0.0, 0.0, 0.0};
  std::array<double, kStageJointCount> velocity{0.0, 0.0, 0.0, 0.0};
  double time_s = 0.0;  ///< simulated time since construction [s]
  double height_m() const { return position[0]; }
  double depth_m() const { return position[1]; }
  double bevel_rad() const { return position[2]; }
  double lateral_m() const { return position[3]; }
};

/// CRTK operating states used by the stage.
enum class OperatingState { kEnabled, kEstopped };
const char* toString(OperatingState state);

/// Outcome of a command: accepted or refused with a reason (status.h).
using needle_guidance::CommandStatus;

/// One line of the stage's journal: every command (accepted or refused) and every end of a
/// motion (reached, cancelled, e-stop).
struct JournalEntry {
  double time_s = 0.0;
  std::string event;  ///< "command", "reached", "cancelled", "estop", "estop_reset", "place"
  std::string joint;  ///< joint name or ""
  double target = 0.0;
  double velocity = 0.0;
  bool accepted = true;
  std::string message;
  StageState state;  ///< state when the entry was written
};

/// The simulated insertion stage. Moves one joint at a time at constant speed. Refuses (and
/// leaves everything unchanged) commands that are non-finite, outside the hardware or scene
/// limits, faster than the joint's velocity limit, issued while another motion is running or
/// while e-stopped, or that change height or lateral position while the needle tip is in tissue.
class InsertionStage {
public:
  /// @param[in] limits hardware limits; @param[in] scene procedure limits (must lie inside the
  /// hardware limits); @param[in] initial start position (within limits, tip out of tissue or
  /// in tissue at a valid height). Throws std::invalid_argument on inconsistent input.
  InsertionStage(const StageLimits& limits, const SceneLimits& scene,
                 const std::array<double, kStageJointCount>& initial);

  /// Starts moving `joint` to `target` at `velocity` (> 0, units of the joint).
  CommandStatus command(StageJoint joint, double target, double velocity);
  /// Rotates the bevel by 180 degrees (to the other end of its range) at `velocity` [rad/s].
  CommandStatus flipBevel(double velocity_rad_s);
  /// Places the needle guide: sets height [m] and bevel [rad] at once (a setup step such as
  /// mounting the guide of a steerable needle, not a motion; velocities stay 0). Refused (and
  /// nothing changes) while a motion runs, while e-stopped, with the tip in tissue, or for a
  /// non-finite value or one outside the joint limits. Journaled as event "place".
  CommandStatus placeGuide(double height_m, double bevel_rad);
  /// Stops the running motion where it is (goal preempted). No effect when idle.
  void cancel();
  /// Emergency stop: motion stops at once; every command is refused until resetEstop().
  void estop(const std::string& reason);
  /// Leaves the e-stop state.
  CommandStatus resetEstop();

  /// Advances simulated time by dt_s (>= 0, finite; throws otherwise) [s].
  void step(double dt_s);

  const StageState& state() const { return state_; }
  OperatingState operatingState() const { return operating_state_; }
  bool busy() const { return active_.has_value(); }
  /// The joint being moved, if any.
  std::optional<StageJoint> activeJoint() const;
  const StageLimits& limits() const { return limits_; }
  const SceneLimits& sceneLimits() const { return scene_; }
  /// True if the needle tip is inside tissue (past the entry face).
  bool tipInTissue() const { return state_.depth_m() > scene_.entry_x_m + kTissueEntryTol_m; }
  /// Tip position in frame scene: (depth, height) [m] (rigid needle along +x).
  geometry::Point2 tipPosition() const { return {state_.depth_m(), state_.height_m()}; }

  /// Everything the stage did, in order. `sink`, when set, also receives each entry as it is
  /// written (e.g. to persist it).
  const std::vector<JournalEntry>& journal() const { return journal_; }
  void setJournalSink(std::function<void(const JournalEntry&)> sink) { sink_ = std::move(sink); }

  /// Depth within which the tip counts as out of tissue [m].
  static constexpr double kTissueEntryTol_m = 1e-9;

private:
  struct Motion {
    StageJoint joint;
    double target;
    double velocity;
  };
  CommandStatus refuse(StageJoint joint, double target, double velocity, std::string reason);
  void record(const std::string& event, const std::string& joint, double target, double velocity,
              bool accepted, const std::string& message);

  StageLimits limits_;
  SceneLimits scene_;
  StageState state_;
  OperatingState operating_state_ = OperatingState::kEnabled;
  std::optional<Motion> active_;
  std::vector<JournalEntry> journal_;
  std::function<void(const JournalEntry&)> sink_;
};

/// Writes journal entries as CSV lines to a file, flushed after every line so that nothing is
/// lost if the process dies. Throws std::runtime_error if the file cannot be opened.
class JournalFile {
public:
  explicit JournalFile(const std::string& path);
  ~JournalFile();
  JournalFile(const JournalFile&) = delete;
  JournalFile& operator=(const JournalFile&) = delete;
  void write(const JournalEntry& entry);
  static const char* header();

private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace needle_guidance::robot
