// The image-guided closed loop of dissertation 5.5 (figure 5.8) in one process: the steerable
// trial loop (steerable_trials.h) driving in-process devices. After every insertion step the
// tip is localised (ground truth, or an imager frame tracked by TipTracker), the policy table
// gives the control for the localised pose, and the simulated needle (the robot's "world": exact
// arcs, seeded deflections) executes it. The steerable_procedure node runs the same loop over
// ROS (steerable_needle.launch tracking:=image); this one lets the benchmark and the tests run
// thousands of trials with identical deflection streams for both kinds of feedback.
#pragma once

#include <cstdint>
#include <vector>

#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/procedures/steerable_trials.h"
#include "needle_guidance/robot/steerable_needle.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/policy_table.h"

namespace needle_guidance::procedures {

struct GuidedTrialOptions {
  int max_steps = 40;  ///< insertions before kStepLimit
  /// Extra frames to wait for a confident tip before acting on an unconfident one.
  int max_unconfident_frames = 10;
  double path_spacing_m = 0.5e-3;  ///< spacing of the needle shape handed to the renderer [m]
};

/// The in-process devices: a simulated needle, a policy table and, for image feedback, a frame
/// renderer and a tracker (both null: the policy sees the true tip). All must outlive it.
class InProcessSteerableDevices : public SteerableDevices {
public:
  /// Throws std::invalid_argument if only one of renderer/tracker is given.
  InProcessSteerableDevices(robot::SteerableNeedle& needle, const steering::PolicyTable& table,
                            const imaging::FrameRenderer* renderer, imaging::TipTracker* tracker,
                            std::uint64_t& frame_index, const GuidedTrialOptions& options = {});

  bool placeAtEntry(const steering::TipPose& start, std::uint64_t seed, bool reseed,
                    std::string& why_not) override;
  std::optional<SteerableTip> tip(std::string& why_not) override;
  std::optional<PolicyAnswer> control(std::string& why_not) override;
  bool flip(std::string& why_not) override;
  StepEnd insertTo(double length_m, std::string& message) override;
  std::vector<SteerableTip> takeSamples() override;
  std::optional<Fault> fault() override { return std::nullopt; }
  std::string leaveSafe() override;

  int frames() const { return frames_; }  ///< frames rendered (dropped ones included)

private:
  SteerableTip trueTip() const;

  robot::SteerableNeedle& needle_;
  const steering::PolicyTable& table_;
  const imaging::FrameRenderer* renderer_;
  imaging::TipTracker* tracker_;
  std::uint64_t& frame_index_;
  GuidedTrialOptions options_;
  std::uint32_t flips_ = 0;
  int frames_ = 0;
  std::vector<SteerableTip> samples_;
};

struct GuidedTrial {
  steering::TrialOutcome outcome = steering::TrialOutcome::kStepLimit;
  int steps = 0;
  int flips = 0;
  int frames = 0;                 ///< frames rendered (dropped ones included)
  int unconfident_decisions = 0;  ///< controls taken on a tip the tracker was not confident of
  /// At every decision: |localised - true| tip position [m] and heading [rad].
  std::vector<double> tip_errors_m;
  std::vector<double> heading_errors_rad;
};

/// One trial of runSteerableTrial on the in-process devices, from `entry` with deflection
/// stream `seed`, one insertion of delta_m [m] per decision. Throws std::invalid_argument if only
/// one of renderer/tracker is given or the needle refuses the entry, std::logic_error if it refuses
/// an insertion.
GuidedTrial runGuidedTrial(robot::SteerableNeedle& needle, const robot::EntryPose& entry,
                           double delta_m, std::uint64_t seed, const steering::PolicyTable& table,
                           const imaging::FrameRenderer* renderer, imaging::TipTracker* tracker,
                           std::uint64_t& frame_index, const GuidedTrialOptions& options = {});

}  // namespace needle_guidance::procedures
