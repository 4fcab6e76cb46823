#include "needle_guidance/robot/steerable_needle.h"
#include "needle_guidance/math.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <iomanip>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/format.h"

namespace needle_guidance::robot {
namespace {

using needle_model::ArcOutcome;
using needle_model::Bevel;
using needle_model::Control;
using needle_model::TipPose;

constexpr double kHalfPi = 0.5 * kPi;

std::string meters(double value) {
  return formatNumber(value) + " m";
}

std::string point(const geometry::Point2& p) {
  std::ostringstream out;
  out << std::setprecision(6) << '(' << p.x() << ", " << p.y() << ") m";
  return out.str();
}

void requireFiniteNonNegative(double value, const char* name) {
  if (!std::isfinite(value) || value < 0.0) {
    throw std::invalid_argument(std::string("SteerableNeedle: ") + name + " " +
                                std::to_string(value) + " must be finite and >= 0");
  }
}

}  // namespace

std::string NeedleContact::toString() const {
  switch (outcome) {
    case ArcOutcome::kObstacle:
      return "obstacle '" + obstacle + "' at " + point(pose.p_SceneTip);
    case ArcOutcome::kLeftWorkspace:
      return "left the workspace at " + point(pose.p_SceneTip);
    default:
      return "no contact";
  }
}

SteerableNeedle::SteerableNeedle(const needle_model::PlanarWorkspace& workspace,
                                 const SteerableNeedleConfig& config, const EntryPose& entry)
    : config_(config), rng_(config.seed) {
  requireFiniteNonNegative(config.sigma_insert_rad, "sigma_insert_rad");
  requireFiniteNonNegative(config.sigma_flip_rad, "sigma_flip_rad");
  if (!std::isfinite(config.start_x_m)) {
    throw std::invalid_argument("SteerableNeedle: start_x_m " + std::to_string(config.start_x_m) +
                                " is not finite");
  }
  if (!std::isfinite(config.min_height_m) || !std::isfinite(config.max_height_m) ||
      config.min_height_m > config.max_height_m) {
    throw std::invalid_argument("SteerableNeedle: entry height range [" +
                                meters(config.min_height_m) + ", " + meters(config.max_height_m) +
                                "] is empty or not finite");
  }
  world_ = std::make_unique<needle_model::PlanarWorld>(workspace, config.chord_tolerance_m);
  radius_m_ = workspace.radius_m;
  const CommandStatus ok = checkEntry(entry);
  if (!ok) {
    throw std::invalid_argument("SteerableNeedle: initial entry refused: " + ok.toString());
  }
  entry_ = entry;
  bevel_ = entry.bevel;
}

geometry::Point2 SteerableNeedle::entryPoint() const {
  return {config_.start_x_m, entry_.height_m};
}

CommandStatus SteerableNeedle::checkEntry(const EntryPose& entry) const {
  if (!std::isfinite(entry.height_m) || !std::isfinite(entry.angle_rad)) {
    return CommandStatus::refused("entry height and angle must be finite numbers");
  }
  if (length_m_ > 0.0) {
    return CommandStatus::refused("the needle is in tissue (inserted length " + meters(length_m_) +
                                  "); retract to 0 before moving the entry");
  }
  if (entry.angle_rad < -kHalfPi || entry.angle_rad > kHalfPi) {
    std::ostringstream out;
    out << "entry angle " << std::setprecision(6) << entry.angle_rad
        << " rad is outside [-pi/2, pi/2]";
    return CommandStatus::refused(out.str());
  }
  if (entry.height_m < config_.min_height_m || entry.height_m > config_.max_height_m) {
    return CommandStatus::refused(
        "entry height " + meters(entry.height_m) + " is outside the scene's needle height range [" +
        meters(config_.min_height_m) + ", " + meters(config_.max_height_m) + "]");
  }
  return CommandStatus::accepted();
}

CommandStatus SteerableNeedle::setEntry(const EntryPose& entry) {
  const CommandStatus ok = checkEntry(entry);
  if (!ok) {
    record("set_entry", false, ok.toString());
    return CommandStatus::refused("set entry refused: " + ok.toString());
  }
  entry_ = entry;
  bevel_ = entry.bevel;
  segments_.clear();
  length_m_ = 0.0;
  insertion_open_ = false;
  flip_pending_ = false;
  contact_ = NeedleContact{};
  std::ostringstream out;
  out << std::setprecision(6) << "entry at " << point(entryPoint()) << ", angle " << entry.angle_rad
      << " rad, bevel " << needle_model::toString(entry.bevel);
  record("set_entry", true, out.str());
  return CommandStatus::accepted();
}

CommandStatus SteerableNeedle::reseed(std::uint64_t seed) {
  rng_.seed(seed);
  draws_ = 0;
  record("reseed", true, "deflection stream restarted from seed " + std::to_string(seed));
  return CommandStatus::accepted();
}

CommandStatus SteerableNeedle::flip() {
  bevel_ = needle_model::flipped(bevel_);
  flip_pending_ = true;
  insertion_open_ = false;
  record("flip", true, "bevel " + needle_model::toString(bevel_));
  return CommandStatus::accepted();
}

double SteerableNeedle::drawStandardNormal() {
  // Box-Muller on two 53-bit uniforms: u1 in (0, 1] (log finite), u2 in [0, 1). Written out
  // rather than std::normal_distribution so that draw k always uses engine outputs 2k, 2k + 1
  // and gives the same value with every standard library.
  constexpr double kTwoPow53 = 9007199254740992.0;
  const double u1 = (static_cast<double>(rng_() >> 11) + 1.0) / kTwoPow53;
  const double u2 = static_cast<double>(rng_() >> 11) / kTwoPow53;
  ++draws_;
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * kPi * u2);
}

CommandStatus SteerableNeedle::beginInsertion() {
  if (contact_) {
    const std::string reason = "the tip is in contact (" + contact_.toString() + "); retract first";
    record("insert", false, reason);
    return CommandStatus::refused("insert refused: " + reason);
  }
  NeedleSegment segment;
  segment.control = flip_pending_ ? Control::kFlip : Control::kInsert;
  segment.sigma_rad = flip_pending_ ? config_.sigma_flip_rad : config_.sigma_insert_rad;
  segment.draw_index = draws_;
  segment.beta_rad = segment.sigma_rad * drawStandardNormal();
  segment.start = tip();
  // The deflection turns the tip before it moves, as in advanceTip (5.3).
  segment.start.theta_rad = segment.start.theta_rad + segment.beta_rad;
  segment.start.bevel = bevel_;
  segment.start_length_m = length_m_;
  segment.length_m = 0.0;
  segments_.push_back(segment);
  insertion_open_ = true;
  flip_pending_ = false;
  std::ostringstream out;
  out << std::setprecision(6) << "insertion from " << length_m_ << " m ("
      << needle_model::toString(segment.control) << "), beta " << segment.beta_rad << " rad";
  record("insert", true, out.str(), &segments_.back());
  return CommandStatus::accepted();
}

MotionStatus SteerableNeedle::advanceTo(double length_m) {
  if (!std::isfinite(length_m)) {
    return refuseMotion("advance", "target length must be a finite number");
  }
  if (contact_) {
    return refuseMotion("advance",
                        "the tip is in contact (" + contact_.toString() + "); retract first");
  }
  if (!insertion_open_) {
    return refuseMotion("advance", "no insertion command is open (beginInsertion first)");
  }
  if (length_m < length_m_) {
    return refuseMotion("advance", "target length " + meters(length_m) +
                                       " is shorter than the inserted length " + meters(length_m_) +
                                       "; retract instead");
  }
  NeedleSegment& segment = segments_.back();
  const needle_model::ArcTrace trace =
      world_->traceArc(tip(), Control::kInsert, 0.0, length_m - length_m_);
  if (trace.outcome == ArcOutcome::kFree) {
    length_m_ = length_m;
    segment.length_m = length_m_ - segment.start_length_m;
    record("advance", true, "advanced to " + meters(length_m_));
    return {MotionOutcome::kMoved, "advanced to " + meters(length_m_)};
  }
  length_m_ = length_m_ + std::clamp(trace.free_length_m, 0.0, length_m - length_m_);
  segment.length_m = length_m_ - segment.start_length_m;
  insertion_open_ = false;
  contact_.outcome = trace.outcome;
  contact_.obstacle = trace.obstacle;
  contact_.length_m = length_m_;
  contact_.pose = tip();
  const std::string message =
      "stopped at contact: " + contact_.toString() + " after " + meters(length_m_) + " inserted";
  record("contact", true, message);
  return {MotionOutcome::kContact, message};
}

MotionStatus SteerableNeedle::insertTo(double length_m) {
  if (!std::isfinite(length_m)) {
    return refuseMotion("insert", "target length must be a finite number");
  }
  if (contact_) {
    return refuseMotion("insert",
                        "the tip is in contact (" + contact_.toString() + "); retract first");
  }
  if (!(length_m > length_m_)) {
    return refuseMotion("insert", "target length " + meters(length_m) +
                                      " is not beyond the inserted length " + meters(length_m_));
  }
  beginInsertion();
  return advanceTo(length_m);
}

MotionStatus SteerableNeedle::retractTo(double length_m) {
  if (!std::isfinite(length_m) || length_m < 0.0 || length_m > length_m_) {
    return refuseMotion("retract", "target length " + meters(length_m) + " is not in [0, " +
                                       meters(length_m_) + "]");
  }
  // Keep the segments that begin before the new length; the last one ends there.
  while (!segments_.empty() && !(segments_.back().start_length_m < length_m)) {
    segments_.pop_back();
  }
  if (!segments_.empty()) {
    segments_.back().length_m = length_m - segments_.back().start_length_m;
  }
  length_m_ = length_m;
  insertion_open_ = false;
  record("retract", true, "retracted to " + meters(length_m_));
  if (contact_ && length_m_ < contact_.length_m) {
    const std::string cleared = "contact cleared (" + contact_.toString() + ")";
    contact_ = NeedleContact{};
    record("contact_cleared", true, cleared);
  }
  return {MotionOutcome::kMoved, "retracted to " + meters(length_m_)};
}

TipPose SteerableNeedle::segmentPose(const NeedleSegment& segment, double along_m) const {
  if (along_m <= 0.0) {
    return segment.start;
  }
  return needle_model::advanceTip(segment.start, Control::kInsert, 0.0, along_m, radius_m_);
}

TipPose SteerableNeedle::tipAt(double length_m) const {
  if (!(length_m >= 0.0 && length_m <= length_m_)) {
    throw std::out_of_range("SteerableNeedle::tipAt: length " + meters(length_m) +
                            " is not in [0, " + meters(length_m_) + "]");
  }
  TipPose pose;
  pose.p_SceneTip = entryPoint();
  pose.theta_rad = entry_.angle_rad;
  pose.bevel = segments_.empty() ? bevel_ : segments_.front().start.bevel;
  if (length_m == 0.0) {
    return pose;
  }
  // The last segment that begins before length_m holds it.
  for (auto it = segments_.rbegin(); it != segments_.rend(); ++it) {
    if (it->start_length_m < length_m) {
      return segmentPose(*it, std::min(length_m - it->start_length_m, it->length_m));
    }
  }
  return pose;
}

TipPose SteerableNeedle::tip() const {
  TipPose pose;
  if (segments_.empty()) {
    pose.p_SceneTip = entryPoint();
    pose.theta_rad = entry_.angle_rad;
  } else {
    pose = segmentPose(segments_.back(), segments_.back().length_m);
  }
  pose.bevel = bevel_;
  return pose;
}

std::vector<geometry::Point2> SteerableNeedle::pathPoints(double max_spacing_m) const {
  if (!(max_spacing_m > 0.0) || !std::isfinite(max_spacing_m)) {
    throw std::invalid_argument("SteerableNeedle::pathPoints: spacing " + meters(max_spacing_m) +
                                " must be finite and > 0");
  }
  std::vector<geometry::Point2> points{entryPoint()};
  for (const NeedleSegment& segment : segments_) {
    if (segment.length_m <= 0.0) {
      continue;
    }
    const int n = std::max(1, static_cast<int>(std::ceil(segment.length_m / max_spacing_m)));
    for (int i = 1; i <= n; ++i) {
      points.push_back(segmentPose(segment, segment.length_m * i / n).p_SceneTip);
    }
  }
  return points;
}

MotionStatus SteerableNeedle::refuseMotion(const std::string& event, const std::string& reason) {
  record(event, false, reason);
  return {MotionOutcome::kRefused, event + " refused: " + reason};
}

void SteerableNeedle::record(const std::string& event, bool accepted, const std::string& message,
                             const NeedleSegment* drawn) {
  NeedleJournalEntry entry;
  entry.sequence = journal_.size();
  entry.event = event;
  entry.accepted = accepted;
  entry.message = message;
  entry.length_m = length_m_;
  entry.tip = tip();
  if (drawn) {
    entry.beta_rad = drawn->beta_rad;
    entry.sigma_rad = drawn->sigma_rad;
    entry.draw_index = static_cast<std::int64_t>(drawn->draw_index);
  }
  journal_.push_back(entry);
  if (sink_) {
    sink_(journal_.back());
  }
}

struct NeedleJournalFile::Impl {
  std::ofstream out;
};

NeedleJournalFile::NeedleJournalFile(const std::string& path) : impl_(std::make_unique<Impl>()) {
  const bool existed = std::ifstream(path).good();
  impl_->out.open(path, std::ios::app);
  if (!impl_->out) {
    throw std::runtime_error("NeedleJournalFile: cannot open '" + path + "' for appending");
  }
  if (!existed) {
    impl_->out << header() << '\n' << std::flush;
  }
}

NeedleJournalFile::~NeedleJournalFile() = default;

const char* NeedleJournalFile::header() {
  return "time_s,sequence,event,accepted,length_m,tip_x_m,tip_y_m,tip_theta_rad,bevel,beta_rad,"
         "sigma_rad,draw_index,message";
}

void NeedleJournalFile::write(const NeedleJournalEntry& e, double time_s) {
  std::string message = e.message;
  std::replace(message.begin(), message.end(), '"', '\'');
  impl_->out << std::setprecision(17) << time_s << ',' << e.sequence << ',' << e.event << ','
             << (e.accepted ? 1 : 0) << ',' << e.length_m << ',' << e.tip.p_SceneTip.x() << ','
             << e.tip.p_SceneTip.y() << ',' << e.tip.theta_rad << ','
             << needle_model::toString(e.tip.bevel) << ',' << e.beta_rad << ',' << e.sigma_rad
             << ',' << e.draw_index << ",\"" << message << "\"\n"
             << std::flush;
}

}  // namespace needle_guidance::robot
