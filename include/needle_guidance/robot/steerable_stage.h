// The insertion stage in steerable mode (dissertation 5.3), ROS-free: the stage's joints
// drive the steerable needle ("the world"). The insertion joint is the inserted arc length; the
// needle is traced ahead of the stage so that an insertion stops exactly at a contact; a
// retraction pulls the needle back along its path; out of tissue the guide follows the height
// joint; a completed rotation of the bevel joint flips the needle's bevel. The insertion_robot
// node wraps it (actions, topics); a test can drive it directly.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "needle_guidance/robot/insertion_stage.h"
#include "needle_guidance/robot/steerable_needle.h"

namespace needle_guidance::robot {

/// The linear motions a client can command.
enum class LinearCommand { kHeight, kInsert, kRetract };

/// Why a linear command goes the wrong way ("" if it may): an insert to a target shallower than
/// `current_m`, a retract to a deeper one [m].
std::string directionRefusal(LinearCommand command, double target_m, double current_m);

/// The steerable needle's journal next to the stage's: "dir/x.csv" -> "dir/x_needle.csv"
/// ("x_needle3d.csv" for the 3-D needle; any other name gets the suffix appended).
std::string companionJournalPath(const std::string& journal_path, bool three_d);

class SteerableStage {
public:
  /// Both must outlive it; the needle's current entry counts as the first.
  SteerableStage(InsertionStage& stage, SteerableNeedle& needle);

  /// Why a linear command to `target_m` cannot start ("" if it may), before the stage's own
  /// checks: a height outside the scene's entry heights, a non-finite or negative length, an
  /// insertion from a contact or with the bevel mid-rotation.
  std::string refusal(LinearCommand command, double target_m) const;

  /// How a control step ended for the running insertion.
  struct StepResult {
    bool stopped = false;  ///< the insertion stopped early (contact or a refusal): end its goal
    bool contact = false;  ///< ... at a contact (else the needle refused a step)
    std::string message;
  };
  /// One control step of dt_s simulated seconds. `insertion`: the running insert goal's target
  /// and velocity [m, m/s], if an insertion runs.
  StepResult step(double dt_s, std::optional<std::pair<double, double>> insertion);

  /// A flip goal ended: when the bevel joint completed its rotation, the needle's bevel turns.
  void finishFlip();
  /// Places the guide (height joint, bevel joint to the bevel's end) and the needle's entry;
  /// with `reseed`, a new deflection stream. Refused with the reason when the needle is in
  /// tissue, the entry is outside the scene or the stage refuses; the refusal is journalled.
  CommandStatus setEntry(const EntryPose& entry, std::optional<std::uint64_t> reseed);

  /// The world's bevel as the stage's bevel joint shows it (left at the lower end).
  needle_model::Bevel jointBevel() const;
  /// True if the bevel joint is at one end of its range (not mid-rotation).
  bool bevelAtEnd() const;
  /// Entries accepted so far (the guide pose's id) and flips since the last one.
  std::uint32_t entryId() const { return entry_id_; }
  std::uint32_t flipsSinceEntry() const { return flips_since_entry_; }

private:
  void countEntry() {
    ++entry_id_;
    flips_since_entry_ = 0;
  }

  InsertionStage& stage_;
  SteerableNeedle& needle_;
  std::uint32_t entry_id_ = 1;
  std::uint32_t flips_since_entry_ = 0;
};

}  // namespace needle_guidance::robot
