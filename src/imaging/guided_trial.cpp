// The image-guided closed loop in one process (see guided_trial.h).
#include "needle_guidance/imaging/guided_trial.h"

#include <cmath>
#include <stdexcept>

namespace needle_guidance::imaging {
namespace {
constexpr double kPi = 3.14159265358979323846;
}  // namespace

GuidedTrial runGuidedTrial(robot::SteerableNeedle& needle, const robot::EntryPose& entry,
                           std::uint64_t seed, const steering::PolicyTable& table,
                           const FrameRenderer* renderer, TipTracker* tracker,
                           std::uint64_t& frame_index, const GuidedTrialOptions& options) {
  if ((renderer == nullptr) != (tracker == nullptr)) {
    throw std::invalid_argument("runGuidedTrial: give both a renderer and a tracker, or neither");
  }
  if (needle.insertedLength_m() > 0.0) {
    needle.retractTo(0.0);
  }
  if (const robot::CommandStatus placed = needle.setEntry(entry); !placed) {
    throw std::invalid_argument("runGuidedTrial: " + placed.toString());
  }
  needle.reseed(seed);
  const steering::ContinuousWorkspace& world = needle.world();
  const steering::SteeringParams& params = world.problem().params;
  const double delta_m = 2.0 * kPi * params.radius_m / params.orientations;
  std::uint32_t flips = 0;
  if (tracker != nullptr) {
    tracker->reset(needle.tip());
    tracker->onDrive(0.0, needle.bevel(), flips);
  }

  GuidedTrial trial;
  for (;;) {
    const steering::TipPose truth = needle.tip();
    if (world.inTarget(truth.p_SceneTip)) {
      trial.outcome = steering::TrialOutcome::kReachedTarget;
      return trial;
    }
    if (trial.steps >= options.max_steps) {
      trial.outcome = steering::TrialOutcome::kStepLimit;
      return trial;
    }
    steering::TipPose localised = truth;
    if (tracker != nullptr) {
      TipEstimate estimate;
      for (int waited = 0;; ++waited) {
        const Frame frame =
            renderer->render(needle.pathPoints(options.path_spacing_m), frame_index++);
        ++trial.frames;
        estimate = tracker->onFrame(frame.image);  // a dropped frame is an empty image
        if (estimate.confident || waited >= options.max_unconfident_frames) {
          break;
        }
      }
      trial.unconfident_decisions += estimate.confident ? 0 : 1;
      localised = estimate.tip;
    }
    trial.tip_errors_m.push_back((localised.p_SceneTip - truth.p_SceneTip).norm());
    trial.heading_errors_rad.push_back(
        std::abs(std::remainder(localised.theta_rad - truth.theta_rad, 2.0 * kPi)));

    const steering::ControlLookup lookup = table.lookup(localised);
    if (lookup.control == steering::Control::kFlip) {
      needle.flip();
      ++flips;
      ++trial.flips;
    }
    ++trial.steps;
    const robot::MotionStatus moved = needle.insertTo(needle.insertedLength_m() + delta_m);
    if (tracker != nullptr) {
      tracker->onDrive(needle.insertedLength_m(), needle.bevel(), flips);
    }
    if (moved.outcome() == robot::MotionOutcome::kContact) {
      trial.outcome = needle.contact().outcome == steering::ArcOutcome::kObstacle
                          ? steering::TrialOutcome::kHitObstacle
                          : steering::TrialOutcome::kLeftWorkspace;
      return trial;
    }
    if (moved.outcome() == robot::MotionOutcome::kRefused) {
      throw std::logic_error("runGuidedTrial: the needle refused an insertion: " +
                             moved.toString());
    }
  }
}

}  // namespace needle_guidance::imaging
