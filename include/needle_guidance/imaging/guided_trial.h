// The image-guided closed loop of dissertation 5.5 (figure 5.8) in one process: after every
// insertion step the tip is localised (ground truth, or an imager frame tracked by TipTracker),
// the policy table gives the control for the localised pose, and the simulated needle (robot's
// "world": exact arcs, seeded deflections) executes it. The nodes do the same over ROS
// (steerable_needle.launch tracking:=image); this loop lets the benchmark and the tests run
// thousands of trials with identical deflection streams for both kinds of feedback.
#pragma once

#include <cstdint>
#include <vector>

#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/robot/steerable_needle.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/policy_table.h"

namespace needle_guidance::imaging {

struct GuidedTrialOptions {
  int max_steps = 40;  ///< insertions before kStepLimit
  /// Extra frames to wait for a confident tip before acting on an unconfident one.
  int max_unconfident_frames = 10;
  double path_spacing_m = 0.5e-3;  ///< spacing of the needle shape handed to the renderer [m]
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

/// One trial: the needle is placed at `entry` with deflection stream `seed`, then stepped by
/// insertion distance delta = 2 pi r / N_c of `table`'s problem until the true tip (checked
/// after each step, as the ROS procedure does) is in the target, an arc touches an obstacle or
/// leaves the workspace, or max_steps. With `renderer` and `tracker` null the policy sees the
/// true tip; otherwise each decision renders frames (indices from `frame_index`, advanced) and
/// uses the tracker's estimate. Throws std::invalid_argument if only one of renderer/tracker is
/// given or the needle refuses the entry.
GuidedTrial runGuidedTrial(robot::SteerableNeedle& needle, const robot::EntryPose& entry,
                           std::uint64_t seed, const steering::PolicyTable& table,
                           const FrameRenderer* renderer, TipTracker* tracker,
                           std::uint64_t& frame_index, const GuidedTrialOptions& options = {});

}  // namespace needle_guidance::imaging
