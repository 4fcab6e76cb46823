// The insertion stage driving the steerable needle (see steerable_stage.h).
#include "needle_guidance/robot/steerable_stage.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <sstream>

namespace needle_guidance::robot {

std::string directionRefusal(LinearCommand command, double target_m, double current_m) {
  const std::string target = std::to_string(target_m) + " m is ";
  const std::string depth = " than the current depth " + std::to_string(current_m) + " m; use ";
  if (command == LinearCommand::kInsert && target_m < current_m) {
    return "insert command refused: target depth " + target + "shallower" + depth + "retract";
  }
  if (command == LinearCommand::kRetract && target_m > current_m) {
    return "retract command refused: target depth " + target + "deeper" + depth + "insert";
  }
  return "";
}

std::string companionJournalPath(const std::string& journal_path, bool three_d) {
  const std::string ext = ".csv";
  const std::string suffix = three_d ? "_needle3d.csv" : "_needle.csv";
  if (journal_path.size() > ext.size() &&
      journal_path.compare(journal_path.size() - ext.size(), ext.size(), ext) == 0) {
    return journal_path.substr(0, journal_path.size() - ext.size()) + suffix;
  }
  return journal_path + suffix;
}

SteerableStage::SteerableStage(InsertionStage& stage, SteerableNeedle& needle)
    : stage_(stage), needle_(needle) {}

std::string SteerableStage::refusal(LinearCommand command, double target_m) const {
  const char* name = command == LinearCommand::kHeight   ? "move_to_height"
                     : command == LinearCommand::kInsert ? "insert"
                                                         : "retract";
  std::ostringstream out;
  out << std::setprecision(6) << name << " command refused: ";
  if (command == LinearCommand::kHeight) {
    const SteerableNeedleConfig& c = needle_.config();
    if (target_m < c.min_height_m || target_m > c.max_height_m) {
      out << "height " << target_m << " m is not an entry height of the scene [" << c.min_height_m
          << ", " << c.max_height_m << "] m (steerable mode: the height is the entry height)";
      return out.str();
    }
    return "";
  }
  if (!std::isfinite(target_m)) {
    out << "target " << target_m << " m is not a finite number";
    return out.str();
  }
  if (!(target_m >= 0.0)) {
    out << "target " << target_m << " m is negative; in steerable mode the insertion joint is "
        << "the inserted needle length, 0 at the entry";
    return out.str();
  }
  if (command == LinearCommand::kInsert) {
    if (needle_.inContact()) {
      out << "the needle tip is in contact (" << needle_.contact().toString()
          << "); retract past the contact first";
      return out.str();
    }
    if (!bevelAtEnd()) {
      out << "the bevel is mid-rotation (" << stage_.state().bevel_rad()
          << " rad); finish a flip first";
      return out.str();
    }
  }
  return "";
}

needle_model::Bevel SteerableStage::jointBevel() const {
  const JointLimits& b = stage_.limits()[StageJoint::kBevel];
  return stage_.state().bevel_rad() < 0.5 * (b.lower + b.upper) ? needle_model::Bevel::kLeft
                                                                : needle_model::Bevel::kRight;
}

bool SteerableStage::bevelAtEnd() const {
  const JointLimits& b = stage_.limits()[StageJoint::kBevel];
  const double bevel = stage_.state().bevel_rad();
  return bevel == b.lower || bevel == b.upper;
}

SteerableStage::StepResult SteerableStage::step(
    double dt_s, std::optional<std::pair<double, double>> insertion) {
  const std::size_t depth = static_cast<std::size_t>(StageJoint::kDepth);
  StepResult result;
  if (insertion && stage_.busy() && stage_.activeJoint() == StageJoint::kDepth) {
    const auto [target_m, velocity_m_s] = *insertion;
    // Where this step takes the stage (InsertionStage::step's rule): trace the needle there
    // first, so that on contact the stage can stop exactly at the contact point.
    const double position = stage_.state().position[depth];
    const double remaining = target_m - position;
    const double travel = velocity_m_s * dt_s;
    const double next = std::abs(remaining) <= travel ? target_m : position + travel;
    const MotionStatus motion = next > needle_.insertedLength_m()
                                    ? needle_.advanceTo(next)
                                    : MotionStatus(MotionOutcome::kMoved, "no travel");
    if (motion.outcome() == MotionOutcome::kMoved) {
      stage_.step(dt_s);
      return result;
    }
    // Contact (or an unexpected refusal): move the stage to where the needle stopped, stop.
    const double dt_stop_s =
        velocity_m_s > 0.0
            ? std::clamp((needle_.insertedLength_m() - position) / velocity_m_s, 0.0, dt_s)
            : 0.0;
    stage_.step(dt_stop_s);
    stage_.cancel();
    stage_.step(dt_s - dt_stop_s);
    result.stopped = true;
    result.contact = motion.outcome() == MotionOutcome::kContact;
    result.message = result.contact ? "insert stopped at contact: " + needle_.contact().toString() +
                                          " after " + std::to_string(needle_.insertedLength_m()) +
                                          " m inserted; retract past the contact before "
                                          "inserting again"
                                    : motion.toString();
    return result;
  }
  const double before_m = stage_.state().position[depth];
  stage_.step(dt_s);
  // A retraction pulls the needle back along its path. Only an actual backward motion of the
  // joint does: after a stop at a contact the joint may sit an ulp short of the needle's length,
  // which must not count as retracting past the contact.
  const double after_m = stage_.state().position[depth];
  if (after_m < before_m) {
    const double length_m = std::max(0.0, after_m);
    if (length_m < needle_.insertedLength_m()) {
      needle_.retractTo(length_m);
    }
  }
  // Out of tissue, the needle guide follows the height joint.
  const double height_m = stage_.state().height_m();
  if (needle_.insertedLength_m() == 0.0 && height_m != needle_.entry().height_m) {
    EntryPose entry = needle_.entry();
    entry.height_m = height_m;
    entry.bevel = needle_.bevel();
    if (needle_.setEntry(entry)) {
      countEntry();
    }
  }
  return result;
}

void SteerableStage::finishFlip() {
  if (bevelAtEnd() && jointBevel() != needle_.bevel()) {
    needle_.flip();  // the rotation is complete: the world's bevel turns
    ++flips_since_entry_;
  }
}

CommandStatus SteerableStage::setEntry(const EntryPose& entry,
                                       std::optional<std::uint64_t> reseed) {
  CommandStatus status = needle_.checkEntry(entry);
  if (!status) {
    needle_.setEntry(entry);  // refused again, so that the needle's journal records it
    return status;
  }
  const JointLimits& b = stage_.limits()[StageJoint::kBevel];
  status = stage_.placeGuide(entry.height_m,
                             entry.bevel == needle_model::Bevel::kLeft ? b.lower : b.upper);
  if (status) {
    status = needle_.setEntry(entry);
  }
  if (status) {
    countEntry();
    if (reseed) {
      needle_.reseed(*reseed);
    }
  }
  return status;
}

}  // namespace needle_guidance::robot
