// The insertion stage in 3-D steerable mode (see steerable_stage_3d.h).
#include "needle_guidance/robot/steerable_stage_3d.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <iomanip>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::robot {

namespace sd = needle_model;
using needle_model::Vector3;

namespace {

constexpr double kTwoPi = 6.283185307179586;
constexpr double kRelTol = 1e-9;
/// How far the guide's entry may lie off the scene's entry disc and still be on it [m].
constexpr double kEntryTolerance_m = 1e-6;

/// Index of the segment of a polyline with arc lengths `s` that holds arc length `at`.
std::size_t segmentAt(const std::vector<double>& s, double at) {
  const auto it = std::upper_bound(s.begin(), s.end(), at);
  const std::size_t i = it == s.begin() ? 0 : static_cast<std::size_t>(it - s.begin()) - 1;
  return std::min(i, s.size() >= 2 ? s.size() - 2 : 0);
}

Vector3 pointAt(const std::vector<Vector3>& p, const std::vector<double>& s, double at) {
  if (p.size() < 2) {
    return p.front();
  }
  const std::size_t i = segmentAt(s, at);
  const double len = s[i + 1] - s[i];
  const double u = len > 0.0 ? std::clamp((at - s[i]) / len, 0.0, 1.0) : 1.0;
  return p[i] + u * (p[i + 1] - p[i]);
}

/// The tip at arc length `at` of a polyline: its point, the tangent of its segment, the bevel
/// as close to `bevel_hint` as the tangent allows.
needle_model::TipPose3 poseAt(const std::vector<Vector3>& p, const std::vector<double>& s,
                              double at, const needle_model::TipPose3& hint) {
  const std::size_t i = segmentAt(s, at);
  const Vector3 d = p.size() >= 2 ? Vector3(p[i + 1] - p[i]) : Vector3::Zero();
  const Vector3 tangent = d.norm() > 1e-12 ? Vector3(d.normalized()) : hint.tangent();
  const Vector3 bevel =
      std::abs(hint.bevel().dot(tangent)) < 0.99 ? hint.bevel() : tangent.unitOrthogonal();
  return needle_model::makeTipPose(pointAt(p, s, at), tangent, bevel);
}

std::string csvQuoted(const std::string& text) {
  std::string out = "\"";
  for (char c : text) {
    out += c == '"' ? std::string("\"\"") : std::string(1, c);
  }
  return out + "\"";
}

}  // namespace

/// A running steer command: its rotation, then the replay of the drawn insertion.
struct SteerableStage3d::Motion {
  Steer3Command command;
  bool rotating = false;
  double rotated_rad = 0.0;     ///< of the commanded rotation, so far
  double spin_start_rad = 0.0;  ///< the axial joint when the command began
  double start_m = 0.0;         ///< inserted length when the command began
  double stop_m = 0.0;          ///< insertion length where it ends (a contact or the length)
  std::vector<Vector3> points;  ///< the drawn insertion, from the tip
  std::vector<double> s;        ///< arc length of each point from the tip [m]
  struct Piece {
    double start_m = 0.0;
    double length_m = 0.0;
    double cycle_m = 0.0;
    double spins_before = 0.0;  ///< full duty-cycle turns in earlier pieces
    needle_model::DutyCycle cycle;
  };
  std::vector<Piece> pieces;
  needle_model::TipPose3 rotated;  ///< the tip after the commanded rotation (shown while inserting)
  needle_model::TipPose3 end;      ///< the drawn tip at the end of the whole length
  needle_model::PathCheck check;

  /// The axial joint's duty-cycle turns after `at` metres of this insertion [rad].
  double dutySpin(double at) const {
    for (const Piece& p : pieces) {
      if (at > p.start_m + p.length_m && &p != &pieces.back()) {
        continue;
      }
      const double alpha = p.cycle.spin_fraction;
      if (alpha <= 0.0) {
        return kTwoPi * p.spins_before;
      }
      const double u = std::clamp(at - p.start_m, 0.0, p.length_m);
      const double k = std::floor(u / p.cycle_m + kRelTol);
      const double r = u - k * p.cycle_m;
      const double frac =
          std::clamp((r - (1.0 - alpha) * p.cycle_m) / (alpha * p.cycle_m), 0.0, 1.0);
      return kTwoPi * (p.spins_before + k + frac);
    }
    return 0.0;
  }
};

SteerableStage3d::SteerableStage3d(InsertionStage& stage, const needle_model::Scene3d& scene,
                                   const needle_model::NoiseParams3& noise,
                                   double spin_rate_limit_rad_s, std::uint64_t seed)
    : stage_(stage),
      scene_(scene),
      world_(scene.collisionWorld()),
      params_(scene.needle),
      noise_(noise) {
  if (!(spin_rate_limit_rad_s > 0.0)) {
    throw std::invalid_argument("SteerableStage3d: the axial rotation joint's velocity limit is " +
                                std::to_string(spin_rate_limit_rad_s) +
                                " rad/s (does the URDF have joint 'axial_rotation'?)");
  }
  params_.spin_rate_max_rad_s = std::min(params_.spin_rate_max_rad_s, spin_rate_limit_rad_s);
  params_.validate();
  noise_.validate();
  needle_ = std::make_unique<needle_model::NoisyNeedle3>(params_, noise_, seed);
  const needle_model::EntryRegion3& e = scene.entry;
  entry_ = needle_model::makeTipPose(e.center_m, e.direction, e.direction.unitOrthogonal());
  tip_ = entry_;
  path_.assign(1, entry_.p_SceneTip);
  path_s_.assign(1, 0.0);
}

SteerableStage3d::~SteerableStage3d() = default;

void SteerableStage3d::record(const std::string& event, bool accepted, const std::string& message) {
  Journal3Entry e;
  e.time_s = stage_.state().time_s;
  e.event = event;
  e.accepted = accepted;
  e.message = message;
  e.inserted_m = insertedLength_m();
  e.spin_rad = spin_rad_;
  e.tip = tip_.p_SceneTip;
  journal_.push_back(e);
  if (sink_) {
    sink_(e);
  }
}

CommandStatus SteerableStage3d::setEntry(const needle_model::TipPose3& entry,
                                         std::optional<std::uint64_t> reseed) {
  std::ostringstream why;
  why << std::setprecision(6);
  const Vector3& p = entry.p_SceneTip;
  const bool finite = p.allFinite() && entry.R_SceneTip.allFinite();
  if (stage_.operatingState() == OperatingState::kEstopped) {
    why << "the emergency stop is active";
  } else if (busy()) {
    why << "a motion is running; wait for it to end";
  } else if (insertedLength_m() > 0.0) {
    why << "the needle is in tissue (" << insertedLength_m() << " m inserted); retract first";
  } else if (!finite || !(entry.R_SceneTip.transpose() * entry.R_SceneTip).isIdentity(1e-6)) {
    why << "the entry pose is not finite or its orientation is not a rotation";
  } else if (!scene_.entry.allows(p, entry.tangent(), kEntryTolerance_m)) {
    why << "entry (" << p.x() << ", " << p.y() << ", " << p.z() << ") m with tangent ("
        << entry.tangent().transpose() << ") is outside scene '" << scene_.name
        << "''s entry disc (radius " << scene_.entry.radius_m << " m) or cone ("
        << scene_.entry.cone_half_angle_rad << " rad)";
  }
  if (!why.str().empty()) {
    const CommandStatus refused = CommandStatus::refused("set entry refused: " + why.str());
    record("entry", false, refused.toString());
    return refused;
  }
  entry_ = needle_model::makeTipPose(p, entry.tangent(), entry.bevel());
  tip_ = entry_;
  path_.assign(1, p);
  path_s_.assign(1, 0.0);
  contact_ = needle_model::Contact3::kFree;
  obstacle_.clear();
  if (reseed) {
    needle_ = std::make_unique<needle_model::NoisyNeedle3>(params_, noise_, *reseed);
  }
  std::ostringstream msg;
  msg << std::setprecision(6) << "entry (" << p.transpose() << ") m, tangent ("
      << entry_.tangent().transpose() << ")"
      << (reseed ? ", noise reseeded " + std::to_string(*reseed) : std::string());
  record("entry", true, msg.str());
  return CommandStatus::accepted();
}

std::string SteerableStage3d::refusal(const Steer3Command& c) const {
  std::ostringstream out;
  out << std::setprecision(6);
  const needle_model::Control3& u = c.control;
  const JointLimits& depth = stage_.limits()[StageJoint::kDepth];
  const double travel_m = std::min(stage_.sceneLimits().max_depth_m, depth.upper);
  if (stage_.operatingState() == OperatingState::kEstopped) {
    out << "the emergency stop is active";
  } else if (busy()) {
    out << "a motion is running";
  } else if (contact_ != needle_model::Contact3::kFree) {
    out << "the needle tip is in contact (" << sd::toString(contact_)
        << (obstacle_.empty() ? "" : " " + obstacle_) << "); retract first";
  } else if (!std::isfinite(u.rotate_rad) || !std::isfinite(u.curvature_per_m) ||
             !std::isfinite(u.length_m) || !std::isfinite(c.spin_rate_rad_s) ||
             !std::isfinite(c.velocity_m_s)) {
    out << "a value is not a finite number";
  } else if (std::abs(u.rotate_rad) > kTwoPi) {
    out << "rotation " << u.rotate_rad << " rad is more than one turn";
  } else if (u.rotate_rad != 0.0 &&
             !(c.spin_rate_rad_s > 0.0 && c.spin_rate_rad_s <= params_.spin_rate_max_rad_s)) {
    out << "rotation rate " << c.spin_rate_rad_s << " rad/s is not in (0, "
        << params_.spin_rate_max_rad_s << "] rad/s (the spin-rate limit)";
  } else if (!(u.curvature_per_m >= 0.0 && u.curvature_per_m <= params_.kappa_max_per_m)) {
    out << "curvature " << u.curvature_per_m << " /m is not in [0, " << params_.kappa_max_per_m
        << "] /m";
  } else if (!(u.length_m > 0.0)) {
    out << "length " << u.length_m << " m is not positive";
  } else if (insertedLength_m() + u.length_m > travel_m * (1.0 + kRelTol)) {
    out << "inserting " << u.length_m << " m from " << insertedLength_m()
        << " m goes beyond the insertion joint's travel of " << travel_m << " m";
  } else if (!(c.velocity_m_s > 0.0 && c.velocity_m_s <= depth.max_velocity)) {
    out << "velocity " << c.velocity_m_s << " m/s is not in (0, " << depth.max_velocity << "] m/s";
  } else {
    const double step = std::min(u.length_m, scene_.step_length_m);
    const needle_model::DutyCycle cycle = needle_model::dutyCycleFor(
        u.curvature_per_m, params_, needle_model::cycleLength(step, params_));
    const double rate = cycle.spin_rate_rad_s * c.velocity_m_s / params_.insertion_speed_m_s;
    if (rate > params_.spin_rate_max_rad_s * (1.0 + kRelTol)) {
      out << "duty-cycled spinning for " << cycle.kappa_per_m << " /m at " << c.velocity_m_s
          << " m/s needs " << rate << " rad/s, over the spin-rate limit of "
          << params_.spin_rate_max_rad_s << " rad/s; insert slower";
    }
  }
  return out.str();
}

std::string SteerableStage3d::linearRefusal(LinearCommand command, double target_m) const {
  if (command == LinearCommand::kHeight) {
    return "move_to_height command refused: in 3-D steerable mode the guide is placed with "
           "set_entry_pose_3d";
  }
  if (command == LinearCommand::kInsert) {
    return "insert command refused: in 3-D steerable mode insert with the steer action";
  }
  if (!(std::isfinite(target_m) && target_m >= 0.0)) {
    return "retract command refused: target " + std::to_string(target_m) +
           " m is not a finite inserted length >= 0";
  }
  return motion_ ? "retract command refused: a steer command is running" : "";
}

double SteerableStage3d::depthTarget(const Motion& m) const {
  // refusal() let the end be up to kRelTol beyond the travel (rounding of summed steps); the
  // stage's own limit check is exact, so an end at the travel is commanded at the travel.
  return std::min(m.start_m + m.stop_m, stage_.limits()[StageJoint::kDepth].upper);
}

CommandStatus SteerableStage3d::steer(const Steer3Command& c) {
  if (const std::string why = refusal(c); !why.empty()) {
    const CommandStatus refused = CommandStatus::refused("steer command refused: " + why);
    record("steer", false, refused.toString());
    return refused;
  }
  auto m = std::make_unique<Motion>();
  m->command = c;
  m->spin_start_rad = spin_rad_;
  m->start_m = insertedLength_m();
  m->rotated = needle_model::rotateBevel(tip_, c.control.rotate_rad);
  // The world's outcome, drawn now: one noise draw per scene step, as executeStep3.
  const double step = scene_.step_length_m;
  needle_model::TipPose3 pose = tip_;
  m->points.assign(1, tip_.p_SceneTip);
  m->s.assign(1, 0.0);
  double done_m = 0.0;
  double spins = 0.0;
  while (done_m < c.control.length_m * (1.0 - kRelTol)) {
    const double left = c.control.length_m - done_m;
    const double len = left <= step * (1.0 + kRelTol) ? left : step;
    const needle_model::Control3 piece{done_m == 0.0 ? c.control.rotate_rad : 0.0,
                                       c.control.curvature_per_m, len};
    const needle_model::StepRecord rec = needle_->step(pose, piece);
    double chord = 0.0;
    for (std::size_t i = 1; i < rec.path.size(); ++i) {
      chord += (rec.path[i] - rec.path[i - 1]).norm();
    }
    const double scale = chord > 0.0 ? len / chord : 1.0;  // the arc is a little longer
    double s = 0.0;
    for (std::size_t i = 1; i < rec.path.size(); ++i) {
      s += (rec.path[i] - rec.path[i - 1]).norm() * scale;
      m->points.push_back(rec.path[i]);
      m->s.push_back(done_m + s);
    }
    const double cycle_m = needle_model::cycleLength(len, params_);
    m->pieces.push_back({done_m, len, cycle_m, spins, rec.cycle});
    spins += rec.cycle.spin_fraction > 0.0 ? std::round(len / cycle_m) : 0.0;
    if (done_m == 0.0) {
      last_cycle_ = rec.cycle;
    }
    m->check = world_.checkPolyline(rec.path);
    pose = rec.pose;
    if (!m->check.free()) {
      m->stop_m = done_m + m->check.contact_s_m * scale;
      break;
    }
    done_m += len;
    m->stop_m = done_m;
  }
  m->end = pose;
  std::ostringstream msg;
  msg << std::setprecision(6) << "rotate " << c.control.rotate_rad << " rad at "
      << c.spin_rate_rad_s << " rad/s, insert " << c.control.length_m << " m at " << c.velocity_m_s
      << " m/s, curvature " << c.control.curvature_per_m << " /m (duty cycle "
      << last_cycle_.kappa_per_m << " /m, spin fraction " << last_cycle_.spin_fraction << ")";
  motion_ = std::move(m);
  record("steer", true, msg.str());
  if (last_cycle_.saturated) {
    record("saturated", true,
           "curvature " + std::to_string(c.control.curvature_per_m) +
               " /m needs a spin faster than the limit: " +
               std::to_string(last_cycle_.kappa_per_m) + " /m taken");
  }
  motion_->rotating = c.control.rotate_rad != 0.0;
  if (!motion_->rotating) {
    const CommandStatus started =
        stage_.command(StageJoint::kDepth, depthTarget(*motion_), c.velocity_m_s);
    if (!started) {  // refusal() checks what the stage checks: not expected
      endMotion("stopped", started.toString());
      return started;
    }
  }
  return CommandStatus::accepted();
}

SteerableStage3d::StepResult SteerableStage3d::step(double dt_s) {
  if (!motion_) {
    const double before_m = insertedLength_m();
    stage_.step(dt_s);
    if (insertedLength_m() < before_m) {
      placeTipAt(insertedLength_m());  // a retraction pulls the tip back along the needle
    }
    return {};
  }
  Motion& m = *motion_;
  if (stage_.operatingState() == OperatingState::kEstopped) {
    stage_.step(dt_s);
    endMotion("stopped", "emergency stop: motion stopped");
    return {true, false, "emergency stop: motion stopped"};
  }
  if (m.rotating) {
    const double total = std::abs(m.command.control.rotate_rad);
    const double dt_left = dt_s - (total - m.rotated_rad) / m.command.spin_rate_rad_s;
    m.rotated_rad = std::min(total, m.rotated_rad + m.command.spin_rate_rad_s * dt_s);
    spin_rad_ = m.spin_start_rad + std::copysign(m.rotated_rad, m.command.control.rotate_rad);
    if (dt_left < 0.0) {
      stage_.step(dt_s);
      return {};
    }
    stage_.step(dt_s - dt_left);
    m.rotating = false;
    tip_ = m.rotated;
    record("rotated", true,
           "bevel rotated " + std::to_string(m.command.control.rotate_rad) + " rad");
    const CommandStatus started =
        stage_.command(StageJoint::kDepth, depthTarget(m), m.command.velocity_m_s);
    if (!started) {
      endMotion("stopped", started.toString());
      return {true, false, started.toString()};
    }
    return stepInsertion(dt_left);
  }
  return stepInsertion(dt_s);
}

SteerableStage3d::StepResult SteerableStage3d::stepInsertion(double dt_s) {
  Motion& m = *motion_;
  stage_.step(dt_s);
  const double at = std::clamp(insertedLength_m() - m.start_m, 0.0, m.stop_m);
  spin_rad_ = m.spin_start_rad + m.command.control.rotate_rad + m.dutySpin(at);
  tip_.p_SceneTip = pointAt(m.points, m.s, at);
  tip_.R_SceneTip = m.rotated.R_SceneTip;  // the drawn orientation is known at the end only
  if (stage_.busy()) {
    return {};
  }
  const bool contact = !m.check.free();
  std::ostringstream msg;
  msg << std::setprecision(6);
  if (contact) {
    msg << "insertion stopped at contact (" << sd::toString(m.check.contact)
        << (m.check.obstacle.empty() ? "" : " " + m.check.obstacle) << ") after " << at << " m of "
        << m.command.control.length_m << " m; retract before steering again";
    contact_ = m.check.contact;
    obstacle_ = m.check.obstacle;
  } else {
    msg << "inserted " << at << " m; " << insertedLength_m() << " m in tissue";
  }
  endMotion(contact ? "contact" : "inserted", msg.str());
  return {true, !contact, msg.str()};
}

void SteerableStage3d::cancel(const std::string& why) {
  if (motion_) {
    stage_.cancel();
    endMotion("stopped", why);
  } else {
    stage_.cancel();
  }
}

void SteerableStage3d::endMotion(const std::string& event, const std::string& message) {
  Motion& m = *motion_;
  const double at = std::clamp(insertedLength_m() - m.start_m, 0.0, m.stop_m);
  const bool whole = at >= m.stop_m && m.check.free();
  last_path_.clear();
  for (std::size_t i = 0; i < m.points.size() && m.s[i] <= at; ++i) {
    last_path_.push_back(m.points[i]);
    if (i > 0) {
      path_.push_back(m.points[i]);
      path_s_.push_back(m.start_m + m.s[i]);
    }
  }
  const Vector3 end = pointAt(m.points, m.s, at);
  if ((end - path_.back()).norm() > 1e-12) {
    last_path_.push_back(end);
    path_.push_back(end);
    path_s_.push_back(m.start_m + at);
  }
  // Stopped before the insertion began: the bevel turned part of the way.
  tip_ = m.rotating ? needle_model::rotateBevel(tip_, spin_rad_ - m.spin_start_rad)
         : whole    ? m.end
                    : poseAt(m.points, m.s, at, m.rotated);
  spin_rad_ = std::remainder(spin_rad_, kTwoPi);
  motion_.reset();
  record(event, event != "stopped", message);
}

void SteerableStage3d::placeTipAt(double inserted_m) {
  if (inserted_m <= 0.0) {
    tip_ = entry_;
    path_.assign(1, entry_.p_SceneTip);
    path_s_.assign(1, 0.0);
  } else {
    tip_ = poseAt(path_, path_s_, inserted_m, tip_);
    const std::size_t keep = segmentAt(path_s_, inserted_m) + 1;
    path_.resize(keep);
    path_s_.resize(keep);
    path_.push_back(tip_.p_SceneTip);
    path_s_.push_back(inserted_m);
  }
  if (contact_ != needle_model::Contact3::kFree) {
    contact_ = needle_model::Contact3::kFree;
    record("retracted", true,
           "retracted from the contact with " + (obstacle_.empty() ? "the boundary" : obstacle_));
    obstacle_.clear();
  }
}

struct Journal3File::Impl {
  std::ofstream out;
};

Journal3File::Journal3File(const std::string& path) : impl_(std::make_unique<Impl>()) {
  const bool exists = std::ifstream(path).good();
  impl_->out.open(path, std::ios::app);
  if (!impl_->out) {
    throw std::runtime_error("cannot open 3-D needle journal '" + path + "' for appending");
  }
  if (!exists) {
    impl_->out << header() << '\n' << std::flush;
  }
}

Journal3File::~Journal3File() = default;

const char* Journal3File::header() {
  return "time_s,event,accepted,inserted_m,spin_rad,tip_x_m,tip_y_m,tip_z_m,message";
}

void Journal3File::write(const Journal3Entry& e) {
  impl_->out << std::setprecision(9) << e.time_s << ',' << e.event << ',' << (e.accepted ? 1 : 0)
             << ',' << e.inserted_m << ',' << e.spin_rad << ',' << e.tip.x() << ',' << e.tip.y()
             << ',' << e.tip.z() << ',' << csvQuoted(e.message) << '\n'
             << std::flush;
}

}  // namespace needle_guidance::robot
