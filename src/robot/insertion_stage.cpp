#include "needle_guidance/robot/insertion_stage.h"

#include <urdf_parser/urdf_parser.h>

#include <cmath>
#include <fstream>
#include <iomanip>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/format.h"

namespace needle_guidance::robot {
namespace {

constexpr std::array<const char*, kStageJointCount> kJointNames{"height", "insertion", "bevel",
                                                                "lateral"};
constexpr std::array<const char*, kStageJointCount> kJointUnits{"m", "m", "rad", "m"};

std::string describe(double value, const char* unit) {
  return formatNumber(value) + ' ' + unit;
}

}  // namespace

const char* jointName(StageJoint joint) {
  return kJointNames[static_cast<std::size_t>(joint)];
}

const char* toString(OperatingState state) {
  return state == OperatingState::kEnabled ? "ENABLED" : "ESTOP";
}

StageLimits parseStageLimits(const std::string& urdf_xml) {
  const urdf::ModelInterfaceSharedPtr model = urdf::parseURDF(urdf_xml);
  if (!model) {
    throw std::invalid_argument("parseStageLimits: the robot description is not valid URDF");
  }
  StageLimits limits;
  for (std::size_t i = 0; i < kStageJointCount; ++i) {
    const std::string name = kJointNames[i];
    const urdf::JointConstSharedPtr joint = model->getJoint(name);
    if (!joint && static_cast<StageJoint>(i) == StageJoint::kLateral) {
      continue;  // a stage without the lateral axis
    }
    if (!joint) {
      throw std::invalid_argument("parseStageLimits: URDF has no joint '" + name + "'");
    }
    if (!joint->limits) {
      throw std::invalid_argument("parseStageLimits: joint '" + name + "' has no <limit>");
    }
    JointLimits& out = limits.joints[i];
    out.lower = joint->limits->lower;
    out.upper = joint->limits->upper;
    out.max_velocity = joint->limits->velocity;
    if (!(out.lower < out.upper) || !std::isfinite(out.lower) || !std::isfinite(out.upper)) {
      throw std::invalid_argument("parseStageLimits: joint '" + name + "' has lower " +
                                  std::to_string(out.lower) + " >= upper " +
                                  std::to_string(out.upper));
    }
    if (!(out.max_velocity > 0.0) || !std::isfinite(out.max_velocity)) {
      throw std::invalid_argument("parseStageLimits: joint '" + name + "' has velocity limit " +
                                  std::to_string(out.max_velocity) + " (must be > 0)");
    }
  }
  limits.has_lateral = static_cast<bool>(model->getJoint(jointName(StageJoint::kLateral)));
  if (const urdf::JointConstSharedPtr spin = model->getJoint("axial_rotation");
      spin && spin->limits) {
    limits.spin_rate_max_rad_s = spin->limits->velocity;
    if (!(limits.spin_rate_max_rad_s > 0.0) || !std::isfinite(limits.spin_rate_max_rad_s)) {
      throw std::invalid_argument("parseStageLimits: joint 'axial_rotation' has velocity limit " +
                                  std::to_string(limits.spin_rate_max_rad_s) + " (must be > 0)");
    }
  }
  const urdf::JointConstSharedPtr tip = model->getJoint("needle_tip_joint");
  if (!tip) {
    throw std::invalid_argument("parseStageLimits: URDF has no joint 'needle_tip_joint'");
  }
  limits.needle_length_m = tip->parent_to_joint_origin_transform.position.x;
  if (!(limits.needle_length_m > 0.0)) {
    throw std::invalid_argument("parseStageLimits: needle_tip_joint origin x " +
                                std::to_string(limits.needle_length_m) +
                                " m is not a positive needle length");
  }
  return limits;
}

namespace {

/// Throws unless the scene's range [lower_m, upper_m] of `joint_name` lies inside the joint's
/// limits.
void requireRangeInside(const char* joint_name, double lower_m, double upper_m,
                        const JointLimits& joint) {
  if (!(lower_m <= upper_m) || lower_m < joint.lower || upper_m > joint.upper) {
    throw std::invalid_argument(
        std::string("InsertionStage: scene ") + joint_name + " range [" + describe(lower_m, "m") +
        ", " + describe(upper_m, "m") + "] is not inside the stage's " + joint_name + " limits [" +
        describe(joint.lower, "m") + ", " + describe(joint.upper, "m") + "]");
  }
}

}  // namespace

InsertionStage::InsertionStage(const StageLimits& limits, const SceneLimits& scene,
                               const std::array<double, kStageJointCount>& initial)
    : limits_(limits), scene_(scene) {
  const JointLimits& height = limits_[StageJoint::kHeight];
  const JointLimits& depth = limits_[StageJoint::kDepth];
  requireRangeInside("height", scene.min_height_m, scene.max_height_m, height);
  if (!(scene.max_depth_m > scene.entry_x_m) || scene.max_depth_m > depth.upper ||
      scene.entry_x_m < depth.lower) {
    throw std::invalid_argument("InsertionStage: scene max depth " +
                                describe(scene.max_depth_m, "m") + " is not in (entry x " +
                                describe(scene.entry_x_m, "m") + ", stage insertion limit " +
                                describe(depth.upper, "m") + "]");
  }
  requireRangeInside("lateral", scene.min_lateral_m, scene.max_lateral_m,
                     limits_[StageJoint::kLateral]);
  for (std::size_t i = 0; i < kStageJointCount; ++i) {
    const JointLimits& joint = limits_.joints[i];
    if (!std::isfinite(initial[i]) || initial[i] < joint.lower || initial[i] > joint.upper) {
      throw std::invalid_argument(std::string("InsertionStage: initial ") + kJointNames[i] + " " +
                                  describe(initial[i], kJointUnits[i]) + " is outside its limits");
    }
  }
  state_.position = initial;
}

std::optional<StageJoint> InsertionStage::activeJoint() const {
  if (!active_) {
    return std::nullopt;
  }
  return active_->joint;
}

CommandStatus InsertionStage::command(StageJoint joint, double target, double velocity) {
  const std::size_t j = static_cast<std::size_t>(joint);
  const JointLimits& lim = limits_.joints[j];
  const char* unit = kJointUnits[j];
  if (!std::isfinite(target) || !std::isfinite(velocity)) {
    return refuse(joint, target, velocity, "target and velocity must be finite numbers");
  }
  if (operating_state_ == OperatingState::kEstopped) {
    return refuse(joint, target, velocity, "emergency stop is active; reset it first");
  }
  if (active_) {
    return refuse(joint, target, velocity,
                  std::string("busy: joint '") +
                      kJointNames[static_cast<std::size_t>(active_->joint)] + "' is still moving");
  }
  if (joint == StageJoint::kLateral && !limits_.has_lateral) {
    return refuse(joint, target, velocity, "this stage has no lateral axis");
  }
  if (!(velocity > 0.0) || velocity > lim.max_velocity) {
    return refuse(joint, target, velocity,
                  "velocity " + describe(velocity, unit) + "/s is not in (0, " +
                      describe(lim.max_velocity, unit) + "/s]");
  }
  if (target < lim.lower || target > lim.upper) {
    return refuse(joint, target, velocity,
                  "target " + describe(target, unit) + " is outside the joint limits [" +
                      describe(lim.lower, unit) + ", " + describe(lim.upper, unit) + "]");
  }
  if ((joint == StageJoint::kHeight || joint == StageJoint::kLateral) && tipInTissue() &&
      target != state_.position[j]) {
    return refuse(joint, target, velocity,
                  "needle tip is in tissue (depth " + describe(state_.depth_m(), "m") +
                      "); retract out of tissue before changing " + kJointNames[j]);
  }
  if (joint == StageJoint::kDepth && target > scene_.entry_x_m + kTissueEntryTol_m) {
    if (target > scene_.max_depth_m) {
      return refuse(joint, target, velocity,
                    "depth " + describe(target, "m") + " is beyond the scene's max depth " +
                        describe(scene_.max_depth_m, "m"));
    }
    const double height = state_.height_m();
    if (height < scene_.min_height_m || height > scene_.max_height_m) {
      return refuse(joint, target, velocity,
                    "height " + describe(height, "m") + " is outside the scene's entry range [" +
                        describe(scene_.min_height_m, "m") + ", " +
                        describe(scene_.max_height_m, "m") + "]; the needle may not enter here");
    }
    const double lateral = state_.lateral_m();
    if (lateral < scene_.min_lateral_m || lateral > scene_.max_lateral_m) {
      return refuse(joint, target, velocity,
                    "lateral position " + describe(lateral, "m") +
                        " is outside the scene's entry range [" +
                        describe(scene_.min_lateral_m, "m") + ", " +
                        describe(scene_.max_lateral_m, "m") + "]; the needle may not enter here");
    }
  }
  active_ = Motion{joint, target, velocity};
  record("command", kJointNames[j], target, velocity, true, "accepted");
  if (target == state_.position[j]) {
    active_.reset();
    record("reached", kJointNames[j], target, velocity, true, "already there");
  }
  return CommandStatus::accepted();
}

CommandStatus InsertionStage::flipBevel(double velocity_rad_s) {
  const JointLimits& lim = limits_[StageJoint::kBevel];
  const double middle = 0.5 * (lim.lower + lim.upper);
  const double target = state_.bevel_rad() < middle ? lim.upper : lim.lower;
  return command(StageJoint::kBevel, target, velocity_rad_s);
}

CommandStatus InsertionStage::placeGuide(double height_m, double bevel_rad) {
  const JointLimits& h = limits_[StageJoint::kHeight];
  const JointLimits& b = limits_[StageJoint::kBevel];
  std::string reason;
  if (!std::isfinite(height_m) || !std::isfinite(bevel_rad)) {
    reason = "height and bevel must be finite numbers";
  } else if (operating_state_ == OperatingState::kEstopped) {
    reason = "emergency stop is active; reset it first";
  } else if (active_) {
    reason = std::string("busy: joint '") + kJointNames[static_cast<std::size_t>(active_->joint)] +
             "' is still moving";
  } else if (tipInTissue()) {
    reason = "needle tip is in tissue (depth " + describe(state_.depth_m(), "m") +
             "); retract out of tissue first";
  } else if (height_m < h.lower || height_m > h.upper) {
    reason = "height " + describe(height_m, "m") + " is outside the joint limits [" +
             describe(h.lower, "m") + ", " + describe(h.upper, "m") + "]";
  } else if (bevel_rad < b.lower || bevel_rad > b.upper) {
    reason = "bevel " + describe(bevel_rad, "rad") + " is outside the joint limits [" +
             describe(b.lower, "rad") + ", " + describe(b.upper, "rad") + "]";
  }
  if (!reason.empty()) {
    record("place", "", 0.0, 0.0, false,
           reason + " (requested height " + describe(height_m, "m") + ", bevel " +
               describe(bevel_rad, "rad") + ")");
    return CommandStatus::refused("place guide refused: " + reason);
  }
  state_.position[static_cast<std::size_t>(StageJoint::kHeight)] = height_m;
  state_.position[static_cast<std::size_t>(StageJoint::kBevel)] = bevel_rad;
  state_.velocity.fill(0.0);
  record("place", "", 0.0, 0.0, true,
         "guide placed at height " + describe(height_m, "m") + ", bevel " +
             describe(bevel_rad, "rad"));
  return CommandStatus::accepted();
}

void InsertionStage::cancel() {
  if (!active_) {
    return;
  }
  const Motion motion = *active_;
  active_.reset();
  state_.velocity.fill(0.0);
  record("cancelled", kJointNames[static_cast<std::size_t>(motion.joint)], motion.target,
         motion.velocity, true, "motion stopped before its target");
}

void InsertionStage::estop(const std::string& reason) {
  active_.reset();
  state_.velocity.fill(0.0);
  operating_state_ = OperatingState::kEstopped;
  record("estop", "", 0.0, 0.0, true, reason);
}

CommandStatus InsertionStage::resetEstop() {
  if (operating_state_ != OperatingState::kEstopped) {
    return CommandStatus::refused("emergency stop is not active");
  }
  operating_state_ = OperatingState::kEnabled;
  record("estop_reset", "", 0.0, 0.0, true, "enabled");
  return CommandStatus::accepted();
}

void InsertionStage::step(double dt_s) {
  if (!std::isfinite(dt_s) || dt_s < 0.0) {
    throw std::invalid_argument("InsertionStage::step: dt " + std::to_string(dt_s) +
                                " s must be finite and >= 0");
  }
  state_.time_s += dt_s;
  state_.velocity.fill(0.0);
  if (!active_) {
    return;
  }
  const std::size_t j = static_cast<std::size_t>(active_->joint);
  double& position = state_.position[j];
  const double remaining = active_->target - position;
  const double travel = active_->velocity * dt_s;
  if (std::abs(remaining) <= travel) {
    state_.velocity[j] = dt_s > 0.0 ? remaining / dt_s : 0.0;
    position = active_->target;
    const Motion motion = *active_;
    active_.reset();
    record("reached", kJointNames[j], motion.target, motion.velocity, true, "target reached");
  } else {
    const double direction = remaining > 0.0 ? 1.0 : -1.0;
    position += direction * travel;
    state_.velocity[j] = direction * active_->velocity;
  }
}

CommandStatus InsertionStage::refuse(StageJoint joint, double target, double velocity,
                                     std::string reason) {
  record("command", kJointNames[static_cast<std::size_t>(joint)], target, velocity, false, reason);
  return CommandStatus::refused(std::string(kJointNames[static_cast<std::size_t>(joint)]) +
                                " command refused: " + reason);
}

void InsertionStage::record(const std::string& event, const std::string& joint, double target,
                            double velocity, bool accepted, const std::string& message) {
  JournalEntry entry;
  entry.time_s = state_.time_s;
  entry.event = event;
  entry.joint = joint;
  entry.target = target;
  entry.velocity = velocity;
  entry.accepted = accepted;
  entry.message = message;
  entry.state = state_;
  journal_.push_back(entry);
  if (sink_) {
    sink_(journal_.back());
  }
}

struct JournalFile::Impl {
  std::ofstream out;
};

JournalFile::JournalFile(const std::string& path) : impl_(std::make_unique<Impl>()) {
  const bool existed = std::ifstream(path).good();
  impl_->out.open(path, std::ios::app);
  if (!impl_->out) {
    throw std::runtime_error("JournalFile: cannot open '" + path + "' for appending");
  }
  if (!existed) {
    impl_->out << header() << '\n' << std::flush;
  }
}

JournalFile::~JournalFile() = default;

const char* JournalFile::header() {
  return "time_s,event,joint,target,velocity,accepted,height_m,depth_m,bevel_rad,message";
}

void JournalFile::write(const JournalEntry& e) {
  std::string message = e.message;
  for (char& c : message) {
    if (c == '"') {
      c = '\'';
    }
  }
  impl_->out << std::setprecision(10) << e.time_s << ',' << e.event << ',' << e.joint << ','
             << e.target << ',' << e.velocity << ',' << (e.accepted ? 1 : 0) << ','
             << e.state.height_m() << ',' << e.state.depth_m() << ',' << e.state.bevel_rad()
             << ",\"" << message << "\"\n"
             << std::flush;
}

}  // namespace needle_guidance::robot
