// The insertion stage in 3-D steerable mode, ROS-free: the stage's insertion joint
// drives the 3-D bevel-tip needle of steering_3d/needle_3d.h ("the world", seeded noise), and an
// axial rotation joint turns the needle about its axis, both for a commanded bevel rotation and
// for duty-cycled spinning during an insertion. A command (Steer3Command) rotates the bevel at a
// commanded rate, then inserts a length at a commanded velocity; the world's outcome of the
// whole command is drawn when it is accepted (one noise draw per scene step_length_m, as
// closed_loop_3d's executeStep3), checked against the scene's meshes and then replayed in time
// by the stage: an insertion stops exactly at a contact. Unsafe commands are refused and leave
// everything unchanged: a rotation faster than the spin-rate limit, an insertion whose duty cycle
// would spin faster than it, a curvature outside [0, kappa_max], a length beyond the insertion
// joint's travel, a velocity over its limit, any command from a contact, while a motion runs or
// while e-stopped. Every command, refusal and end of a motion is journalled. The insertion_robot
// node (~mode steerable_3d) wraps it; a test can drive it directly.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/needle_model/scene_3d.h"
#include "needle_guidance/robot/insertion_stage.h"
#include "needle_guidance/robot/steerable_stage.h"

namespace needle_guidance::robot {

/// One 3-D command: rotate the bevel by control.rotate_rad at spin_rate_rad_s, then insert
/// control.length_m at velocity_m_s with duty-cycled spinning for control.curvature_per_m.
struct Steer3Command {
  needle_model::Control3 control;
  double spin_rate_rad_s = 0.0;  ///< > 0 when rotating [rad/s]
  double velocity_m_s = 0.0;     ///< > 0 [m/s]
};

/// One line of the 3-D journal.
struct Journal3Entry {
  double time_s = 0.0;  ///< the stage's simulated time [s]
  /// "entry", "steer" (a command, accepted or refused), "rotated", "inserted", "saturated",
  /// "contact", "stopped" (cancelled or e-stopped), "retracted"
  std::string event;
  bool accepted = true;
  std::string message;
  double inserted_m = 0.0;  ///< inserted length when written [m]
  double spin_rad = 0.0;    ///< axial rotation joint [rad]
  needle_model::Vector3 tip = needle_model::Vector3::Zero();
};

/// Writes Journal3Entry lines as CSV, flushed per line. Throws std::runtime_error if the file
/// cannot be opened.
class Journal3File {
public:
  explicit Journal3File(const std::string& path);
  ~Journal3File();
  Journal3File(const Journal3File&) = delete;
  Journal3File& operator=(const Journal3File&) = delete;
  void write(const Journal3Entry& entry);
  static const char* header();

private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

class SteerableStage3d {
public:
  /// `stage` (its insertion joint is the inserted arc length, 0 at the entry; its scene limits'
  /// max_depth_m the travel) and `scene` must outlive it. The needle spins at most at the smaller
  /// of spin_rate_limit_rad_s (the axial rotation joint's limit) and the scene's limit. The
  /// needle starts at the centre of the scene's entry disc, along its direction.
  SteerableStage3d(InsertionStage& stage, const needle_model::Scene3d& scene,
                   const needle_model::NoiseParams3& noise, double spin_rate_limit_rad_s,
                   std::uint64_t seed);
  ~SteerableStage3d();

  /// Places the guide at `entry` (a setup step, not a motion); with `reseed` a new noise stream.
  /// Refused (journalled) with the tip in tissue, while a motion runs or e-stopped, for a
  /// non-finite pose or one outside the scene's entry disc and cone.
  CommandStatus setEntry(const needle_model::TipPose3& entry, std::optional<std::uint64_t> reseed);
  /// Starts a command (see the file comment for the refusals).
  CommandStatus steer(const Steer3Command& command);
  /// Why a linear goal of the stage is refused in this mode ("" if it may): the height is set
  /// by setEntry, insertions are steer commands, a retraction needs a finite target >= 0.
  std::string linearRefusal(LinearCommand command, double target_m) const;

  /// How a control step ended a running steer command.
  struct StepResult {
    bool ended = false;    ///< the steer command ended in this step
    bool success = false;  ///< ... having inserted its whole length
    std::string message;
  };
  /// Advances dt_s simulated seconds: the running steer command, or the stage's own motion (a
  /// retraction pulls the tip back along the needle's path).
  StepResult step(double dt_s);
  /// Stops a running steer command where it is (journalled); the stage's motion too.
  void cancel(const std::string& why);

  bool busy() const { return motion_ != nullptr || stage_.busy(); }
  const needle_model::TipPose3& tip() const { return tip_; }
  const needle_model::TipPose3& entry() const { return entry_; }
  double insertedLength_m() const { return stage_.state().depth_m(); }
  double spin_rad() const { return spin_rad_; }
  needle_model::Contact3 contact() const { return contact_; }
  const std::string& contactObstacle() const { return obstacle_; }
  /// The inserted needle: tip positions from the entry [m].
  const std::vector<needle_model::Vector3>& path() const { return path_; }
  /// The last command's duty cycle (the first step's).
  const needle_model::DutyCycle& lastCycle() const { return last_cycle_; }
  double spinRateLimit_rad_s() const { return params_.spin_rate_max_rad_s; }
  /// Positions of the last command's insertion (its start included) [m].
  const std::vector<needle_model::Vector3>& lastPath() const { return last_path_; }

  const std::vector<Journal3Entry>& journal() const { return journal_; }
  void setJournalSink(std::function<void(const Journal3Entry&)> sink) { sink_ = std::move(sink); }

private:
  struct Motion;
  std::string refusal(const Steer3Command& command) const;
  /// The insertion joint target at the end of `m`, at most the joint's upper limit.
  double depthTarget(const Motion& m) const;
  StepResult stepInsertion(double dt_s);
  void placeTipAt(double inserted_m);
  void endMotion(const std::string& event, const std::string& message);
  void record(const std::string& event, bool accepted, const std::string& message);

  InsertionStage& stage_;
  const needle_model::Scene3d& scene_;
  needle_model::CollisionWorld3 world_;
  needle_model::NeedleParams3 params_;
  needle_model::NoiseParams3 noise_;
  std::unique_ptr<needle_model::NoisyNeedle3> needle_;
  needle_model::TipPose3 entry_;
  needle_model::TipPose3 tip_;
  double spin_rad_ = 0.0;
  needle_model::Contact3 contact_ = needle_model::Contact3::kFree;
  std::string obstacle_;
  std::vector<needle_model::Vector3> path_;  ///< the inserted needle, from the entry
  std::vector<double> path_s_;               ///< arc length at each point of path_ [m]
  std::vector<needle_model::Vector3> last_path_;
  needle_model::DutyCycle last_cycle_;
  std::unique_ptr<Motion> motion_;
  std::vector<Journal3Entry> journal_;
  std::function<void(const Journal3Entry&)> sink_;
};

}  // namespace needle_guidance::robot
