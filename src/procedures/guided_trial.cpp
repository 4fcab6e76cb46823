// The steerable trial loop on in-process devices (see guided_trial.h).
#include "needle_guidance/procedures/guided_trial.h"

#include <stdexcept>

namespace needle_guidance::procedures {

InProcessSteerableDevices::InProcessSteerableDevices(robot::SteerableNeedle& needle,
                                                     const steering::PolicyTable& table,
                                                     const imaging::FrameRenderer* renderer,
                                                     imaging::TipTracker* tracker,
                                                     std::uint64_t& frame_index,
                                                     const GuidedTrialOptions& options)
    : needle_(needle),
      table_(table),
      renderer_(renderer),
      tracker_(tracker),
      frame_index_(frame_index),
      options_(options) {
  if ((renderer == nullptr) != (tracker == nullptr)) {
    throw std::invalid_argument(
        "InProcessSteerableDevices: give both a renderer and a tracker, or neither");
  }
}

SteerableTip InProcessSteerableDevices::trueTip() const {
  return {needle_.tip(), needle_.insertedLength_m(), "ground_truth", true};
}

bool InProcessSteerableDevices::placeAtEntry(const steering::TipPose& start, std::uint64_t seed,
                                             bool reseed, std::string& why_not) {
  if (needle_.insertedLength_m() > 0.0) {
    needle_.retractTo(0.0);
  }
  const robot::EntryPose entry{start.p_SceneTip.y(), start.theta_rad, start.bevel};
  if (const robot::CommandStatus placed = needle_.setEntry(entry); !placed) {
    why_not = "set_entry: " + placed.toString();
    return false;
  }
  if (reseed) {
    needle_.reseed(seed);
  }
  flips_ = 0;
  if (tracker_ != nullptr) {
    tracker_->reset(needle_.tip());
    tracker_->onDrive(0.0, needle_.bevel(), flips_);
  }
  samples_.assign(1, trueTip());
  return true;
}

std::optional<SteerableTip> InProcessSteerableDevices::tip(std::string& /*why_not*/) {
  return trueTip();
}

std::optional<PolicyAnswer> InProcessSteerableDevices::control(std::string& /*why_not*/) {
  PolicyAnswer answer;
  answer.looked_up = needle_.tip();
  if (tracker_ != nullptr) {
    imaging::TipEstimate estimate;
    for (int waited = 0;; ++waited) {
      const imaging::Frame frame =
          renderer_->render(needle_.pathPoints(options_.path_spacing_m), frame_index_++);
      ++frames_;
      estimate = tracker_->onFrame(frame.image);  // a dropped frame is an empty image
      if (estimate.confident || waited >= options_.max_unconfident_frames) {
        break;
      }
    }
    answer.looked_up = estimate.tip;
    answer.source = imaging::toString(estimate.status);
    answer.confident = estimate.confident;
  }
  const steering::ControlLookup lookup = table_.lookup(answer.looked_up);
  answer.usable = true;  // off the grid the policy inserts and the world referees the step
  answer.status = lookup.toString();
  answer.control = lookup.control;
  answer.probability_of_success = lookup.probability_of_success;
  return answer;
}

bool InProcessSteerableDevices::flip(std::string& why_not) {
  const robot::CommandStatus flipped = needle_.flip();
  if (!flipped) {
    why_not = flipped.toString();
    return false;
  }
  ++flips_;
  return true;
}

StepEnd InProcessSteerableDevices::insertTo(double length_m, std::string& message) {
  const robot::MotionStatus moved = needle_.insertTo(length_m);
  if (tracker_ != nullptr) {
    tracker_->onDrive(needle_.insertedLength_m(), needle_.bevel(), flips_);
  }
  samples_.push_back(trueTip());
  switch (moved.outcome()) {
    case robot::MotionOutcome::kContact:
      message = needle_.contact().toString();
      return needle_.contact().outcome == steering::ArcOutcome::kObstacle ? StepEnd::kObstacle
                                                                          : StepEnd::kLeftWorkspace;
    case robot::MotionOutcome::kRefused:
      message = moved.toString();
      return StepEnd::kFailed;
    default:
      return StepEnd::kMoved;
  }
}

std::vector<SteerableTip> InProcessSteerableDevices::takeSamples() {
  return std::move(samples_);
}

std::string InProcessSteerableDevices::leaveSafe() {
  if (needle_.insertedLength_m() <= 0.0) {
    return "";
  }
  needle_.retractTo(0.0);
  return "needle retracted";
}

GuidedTrial runGuidedTrial(robot::SteerableNeedle& needle, const robot::EntryPose& entry,
                           double delta_m, std::uint64_t seed, const steering::PolicyTable& table,
                           const imaging::FrameRenderer* renderer, imaging::TipTracker* tracker,
                           std::uint64_t& frame_index, const GuidedTrialOptions& options) {
  InProcessSteerableDevices devices(needle, table, renderer, tracker, frame_index, options);
  steering::TipPose start;
  start.p_SceneTip = geometry::Point2(0.0, entry.height_m);
  start.theta_rad = entry.angle_rad;
  start.bevel = entry.bevel;
  const SteerableTrialRecord rec =
      runSteerableTrial(devices, needle.world(), delta_m, start, seed, true, options.max_steps);
  GuidedTrial trial;
  switch (rec.outcome) {
    case SteerableOutcome::kReachedTarget:
      trial.outcome = steering::TrialOutcome::kReachedTarget;
      break;
    case SteerableOutcome::kHitObstacle:
      trial.outcome = steering::TrialOutcome::kHitObstacle;
      break;
    case SteerableOutcome::kLeftWorkspace:
      trial.outcome = steering::TrialOutcome::kLeftWorkspace;
      break;
    case SteerableOutcome::kStepLimit:
      trial.outcome = steering::TrialOutcome::kStepLimit;
      break;
    default:
      if (rec.steps == 0) {
        throw std::invalid_argument("runGuidedTrial: " + rec.message);
      }
      throw std::logic_error("runGuidedTrial: the needle refused an insertion: " + rec.message);
  }
  trial.steps = rec.steps;
  trial.flips = rec.flips;
  trial.frames = devices.frames();
  trial.unconfident_decisions = rec.unconfident_decisions;
  for (const SteerableDecision& d : rec.decisions) {
    if (d.answered) {
      trial.tip_errors_m.push_back(d.tipError_m());
      trial.heading_errors_rad.push_back(d.headingError_rad());
    }
  }
  return trial;
}

}  // namespace needle_guidance::procedures
