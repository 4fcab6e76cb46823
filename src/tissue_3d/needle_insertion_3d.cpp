// 3-D needle insertion on embedded tissue points with condensed compliance
// (needle_insertion_3d.h).
#include "needle_guidance/tissue_3d/needle_insertion_3d.h"

#include <Eigen/Cholesky>
#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace needle_guidance::tissue_3d {
namespace {

constexpr double kEntryInset_m = 1e-5;     // the entry point lies this far inside the face
constexpr double kCutTol_m = 1e-10;        // root finding of the cut length
constexpr double kEventTol_m = 1e-12;      // events closer than this to a segment end coincide
constexpr int kMaxEventsPerMove = 100000;  // bound against a stalled event loop
constexpr int kMaxCutIterations = 60;
// Corotational fixed point: converged when no node's warp changes by more than this, 50
// times below the step-halving target (5 um) of the seeds.
constexpr double kWarpTol_m = 1e-7;
constexpr int kMaxWarpUpdates = 60;

/// s where an affine function with values fa at sa and fb at sb equals level.
double crossing(double sa, double fa, double sb, double fb, double level) {
  const double t = (fb == fa) ? 1.0 : std::clamp((level - fa) / (fb - fa), 0.0, 1.0);
  return sa + t * (sb - sa);
}

}  // namespace

NeedleInsertion3::NeedleInsertion3(TissueModel3& model, const Needle3& needle, double entry_x_m,
                                   double max_tip_x_m)
    : model_(model), needle_(needle), entry_x_m_(entry_x_m), max_tip_x_m_(max_tip_x_m) {
  if (!(needle.cutting_force_N > 0.0) || !(needle.track_spacing_m > 0.0) ||
      !(needle.kinetic_friction_N_per_m >= 0.0) ||
      !(needle.static_friction_N_per_m >= needle.kinetic_friction_N_per_m) ||
      !std::isfinite(entry_x_m)) {
    throw std::invalid_argument(
        "NeedleInsertion3: needs cutting_force > 0, track_spacing > 0, 0 <= kinetic friction <= "
        "static friction and a finite entry face");
  }
  s_ = entry_x_m - 1e-3;
}

void NeedleInsertion3::prefetchLine(const Eigen::Vector2d& lateral) const {
  // The cut track is the reference line at this lateral position: the columns of every node
  // of the elements it crosses are solved in one batch instead of a few per step.
  constexpr double kSample_m = 2e-4;
  std::vector<int> dofs;
  std::vector<char> seen(model_.mesh().elements.size(), 0);
  const double end = max_tip_x_m_ + 2.0 * needle_.track_spacing_m;
  for (double x = entry_x_m_ + kEntryInset_m; x <= end; x += kSample_m) {
    const std::optional<EmbeddedPoint> p = model_.locate(Vector3(x, lateral.x(), lateral.y()));
    if (!p) {
      break;
    }
    if (!seen[static_cast<std::size_t>(p->element)]) {
      seen[static_cast<std::size_t>(p->element)] = 1;
      for (int n : model_.mesh().elements[static_cast<std::size_t>(p->element)]) {
        for (int d = 0; d < 3; ++d) {
          dofs.push_back(3 * n + d);
        }
      }
    }
  }
  model_.compliance().require(dofs);
}

void NeedleInsertion3::requireColumns(const EmbeddedPoint& p) const {
  std::vector<int> dofs;
  for (int n : model_.mesh().elements[static_cast<std::size_t>(p.element)]) {
    for (int d = 0; d < 3; ++d) {
      dofs.push_back(3 * n + d);
    }
  }
  model_.compliance().require(dofs);
}

Eigen::Matrix3d NeedleInsertion3::block(const EmbeddedPoint& p, const EmbeddedPoint& q) const {
  const auto& g = model_.compliance();
  const auto& np = model_.mesh().elements[static_cast<std::size_t>(p.element)];
  const auto& nq = model_.mesh().elements[static_cast<std::size_t>(q.element)];
  Eigen::Matrix3d b = Eigen::Matrix3d::Zero();
  for (int j = 0; j < 4; ++j) {
    for (int d = 0; d < 3; ++d) {
      const Eigen::VectorXd& col = g.column(3 * nq[j] + d);
      for (int i = 0; i < 4; ++i) {
        const double w = p.weights(i) * q.weights(j);
        b.col(d) += w * col.segment<3>(3 * np[i]);
      }
    }
  }
  return b;
}

NeedleInsertion3::Solution NeedleInsertion3::solveAt(double s, const EmbeddedPoint* tip) const {
  ++solves_;
  const int ns = static_cast<int>(shaft_.size());
  const int m = ns + (tip ? 1 : 0);
  Solution sol;
  sol.forces = Eigen::VectorXd::Zero(3 * m);
  sol.displacement = Eigen::VectorXd::Zero(3 * m);
  if (m == 0) {
    return sol;
  }
  Eigen::MatrixXd c(3 * m, 3 * m);
  c.topLeftCorner(3 * ns, 3 * ns) = shaft_compliance_;
  if (tip) {
    requireColumns(*tip);
    for (int k = 0; k < ns; ++k) {
      const Eigen::Matrix3d b = block(shaft_[static_cast<std::size_t>(k)].point, *tip);
      c.block<3, 3>(3 * k, 3 * ns) = b;
      c.block<3, 3>(3 * ns, 3 * k) = b.transpose();
    }
    c.block<3, 3>(3 * ns, 3 * ns) = block(*tip, *tip);
  }
  // Prescribed components (value: displacement) and force components (value: force).
  std::vector<int> fixed, loaded;
  Eigen::VectorXd value(3 * m);
  for (int k = 0; k < ns; ++k) {
    const ShaftPoint& p = shaft_[static_cast<std::size_t>(k)];
    value(3 * k + 1) = lateral_.x() - p.point.reference_m.y();
    value(3 * k + 2) = lateral_.y() - p.point.reference_m.z();
    fixed.push_back(3 * k + 1);
    fixed.push_back(3 * k + 2);
    if (p.stuck) {
      value(3 * k) = s + p.offset_m - p.point.reference_m.x();
      fixed.push_back(3 * k);
    } else {
      value(3 * k) = direction_ * needle_.kinetic_friction_N_per_m * p.share_m;
      loaded.push_back(3 * k);
    }
  }
  if (tip) {
    value.segment<3>(3 * ns) = Vector3(s, lateral_.x(), lateral_.y()) - tip->reference_m;
    for (int d = 0; d < 3; ++d) {
      fixed.push_back(3 * ns + d);
    }
  }
  // The corotational part of the displacement adds to the compliance's answer.
  Eigen::VectorXd warp = Eigen::VectorXd::Zero(3 * m);
  for (int k = 0; k < m && warp_.size() > 0; ++k) {
    warp.segment<3>(3 * k) = warpAt(k < ns ? shaft_[static_cast<std::size_t>(k)].point : *tip);
  }
  const int nf = static_cast<int>(fixed.size()), nl = static_cast<int>(loaded.size());
  Eigen::MatrixXd cff(nf, nf), cfl(nf, nl);
  Eigen::VectorXd rhs(nf), fl(nl);
  for (int j = 0; j < nl; ++j) {
    fl(j) = value(loaded[static_cast<std::size_t>(j)]);
  }
  for (int i = 0; i < nf; ++i) {
    rhs(i) = value(fixed[static_cast<std::size_t>(i)]) - warp(fixed[static_cast<std::size_t>(i)]);
    for (int j = 0; j < nf; ++j) {
      cff(i, j) = c(fixed[static_cast<std::size_t>(i)], fixed[static_cast<std::size_t>(j)]);
    }
    for (int j = 0; j < nl; ++j) {
      cfl(i, j) = c(fixed[static_cast<std::size_t>(i)], loaded[static_cast<std::size_t>(j)]);
    }
  }
  const Eigen::VectorXd ff = cff.ldlt().solve(rhs - cfl * fl);
  for (int i = 0; i < nf; ++i) {
    sol.forces(fixed[static_cast<std::size_t>(i)]) = ff(i);
  }
  for (int j = 0; j < nl; ++j) {
    sol.forces(loaded[static_cast<std::size_t>(j)]) = fl(j);
  }
  sol.displacement = c * sol.forces + warp;
  sol.tip_force_N = tip ? sol.forces(3 * ns) : 0.0;
  return sol;
}

EmbeddedPoint NeedleInsertion3::along(double cut_m) const {
  const Vector3 p = tip_.reference_m + cut_m * cut_dir_;
  std::optional<EmbeddedPoint> e = model_.locate(p);
  if (!e) {
    throw std::runtime_error("NeedleInsertion3: the cut track leaves the tissue mesh at [" +
                             std::to_string(p.x() * 1e3) + ", " + std::to_string(p.y() * 1e3) +
                             ", " + std::to_string(p.z() * 1e3) + "] mm");
  }
  return *e;
}

double NeedleInsertion3::cutLength(double s) const {
  const double fb = needle_.cutting_force_N;
  if (solveAt(s, &tip_).tip_force_N <= fb) {
    return 0.0;
  }
  // The tip's tissue point cannot pass the needle tip: the cut is at most `room`.
  double hi = std::max(0.0, (s - tip_.reference_m.x()) / cut_dir_.x());
  double lo = 0.0, f_lo = solveAt(s, &tip_).tip_force_N - fb;
  EmbeddedPoint p_hi = along(hi);
  double f_hi = solveAt(s, &p_hi).tip_force_N - fb;
  if (f_hi >= 0.0) {
    return hi;
  }
  // Illinois regula falsi on the tip force, which falls as the cut lengthens.
  int side = 0;
  for (int it = 0; it < kMaxCutIterations && hi - lo > kCutTol_m; ++it) {
    const double mid = (lo * f_hi - hi * f_lo) / (f_hi - f_lo);
    const EmbeddedPoint p = along(mid);
    const double f = solveAt(s, &p).tip_force_N - fb;
    if (f > 0.0) {
      lo = mid;
      f_lo = f;
      if (side == 1) {
        f_hi *= 0.5;
      }
      side = 1;
    } else {
      hi = mid;
      f_hi = f;
      if (side == -1) {
        f_lo *= 0.5;
      }
      side = -1;
    }
    if (std::abs(f) < 1e-12 * fb) {
      return mid;
    }
  }
  return 0.5 * (lo + hi);
}

void NeedleInsertion3::commit(double s, const EmbeddedPoint* tip) {
  s_ = s;
  if (tip) {
    tip_ = *tip;
  }
  committed_ = solveAt(s, tip_active_ ? &tip_ : nullptr);
  for (std::size_t k = 0; k < shaft_.size(); ++k) {
    shaft_[k].world_x_m =
        shaft_[k].point.reference_m.x() + committed_.displacement(3 * static_cast<int>(k));
  }
}

void NeedleInsertion3::addTrackPoint(const EmbeddedPoint& p) {
  requireColumns(p);
  const int ns = static_cast<int>(shaft_.size());
  Eigen::MatrixXd c(3 * ns + 3, 3 * ns + 3);
  c.topLeftCorner(3 * ns, 3 * ns) = shaft_compliance_;
  for (int k = 0; k < ns; ++k) {
    const Eigen::Matrix3d b = block(shaft_[static_cast<std::size_t>(k)].point, p);
    c.block<3, 3>(3 * k, 3 * ns) = b;
    c.block<3, 3>(3 * ns, 3 * k) = b.transpose();
  }
  c.block<3, 3>(3 * ns, 3 * ns) = block(p, p);
  shaft_compliance_ = std::move(c);
  ShaftPoint sp;
  sp.point = p;
  sp.share_m = needle_.track_spacing_m;
  // The needle slides past the tissue it has just cut at the insertion speed: the point
  // slips unless that speed is below the stick velocity.
  sp.world_x_m = worldOf(p.reference_m).x();
  sp.stuck = needle_.insertion_velocity_m_s < needle_.stick_velocity_m_s;
  sp.offset_m = sp.world_x_m - s_;
  shaft_.push_back(sp);
}

void NeedleInsertion3::releaseShaftPoint(std::size_t k) {
  const int n = static_cast<int>(shaft_.size()), i = static_cast<int>(k);
  Eigen::MatrixXd c(3 * n - 3, 3 * n - 3);
  std::vector<int> keep;
  for (int r = 0; r < 3 * n; ++r) {
    if (r / 3 != i) {
      keep.push_back(r);
    }
  }
  for (std::size_t a = 0; a < keep.size(); ++a) {
    for (std::size_t b = 0; b < keep.size(); ++b) {
      c(static_cast<int>(a), static_cast<int>(b)) = shaft_compliance_(keep[a], keep[b]);
    }
  }
  shaft_compliance_ = std::move(c);
  shaft_.erase(shaft_.begin() + static_cast<std::ptrdiff_t>(k));
}

Vector3 NeedleInsertion3::warpAt(const EmbeddedPoint& p) const {
  Vector3 v = Vector3::Zero();
  const auto& nodes = model_.mesh().elements[static_cast<std::size_t>(p.element)];
  for (int a = 0; a < 4 && warp_.size() > 0; ++a) {
    v += p.weights(a) * warp_.segment<3>(3 * nodes[a]);
  }
  return v;
}

bool NeedleInsertion3::settleWarp(bool fresh) {
  if (!model_.corotational()) {
    return true;
  }
  if (warp_.size() == 0) {
    warp_ = Eigen::VectorXd::Zero(3 * model_.mesh().nodeCount());
  }
  if (fresh || warp_updates_ == 0) {
    warp_mixer_.reset();  // the constraints or the tip moved since the last update
  }
  const Eigen::VectorXd v = model_.corotationDisplacement(displacementField());
  const double change = (v - warp_).lpNorm<Eigen::Infinity>();
  warp_ = change <= kWarpTol_m ? v : warp_mixer_.next(warp_, v);
  commit(s_, nullptr);
  ++info_.corotation_updates;
  if (change <= kWarpTol_m) {
    warp_updates_ = 0;
    return true;
  }
  if (++warp_updates_ > kMaxWarpUpdates) {
    throw std::runtime_error(
        "the corotational iteration did not converge: the warp still changed by " +
        std::to_string(change * 1e3) + " mm after " + std::to_string(kMaxWarpUpdates) +
        " updates (rotations too large for the fixed point on the linear "
        "stiffness)");
  }
  return false;
}

Vector3 NeedleInsertion3::nodeDisplacement(int node) const {
  Vector3 u = warp_.size() > 0 ? Vector3(warp_.segment<3>(3 * node)) : Vector3::Zero();
  const auto& g = model_.compliance();
  const int ns = static_cast<int>(shaft_.size());
  for (int k = 0; k < committed_.forces.size() / 3; ++k) {
    const EmbeddedPoint& p = k < ns ? shaft_[static_cast<std::size_t>(k)].point : tip_;
    const auto& nodes = model_.mesh().elements[static_cast<std::size_t>(p.element)];
    for (int a = 0; a < 4; ++a) {
      for (int d = 0; d < 3; ++d) {
        const double f = p.weights(a) * committed_.forces(3 * k + d);
        if (f != 0.0) {
          u += f * g.column(3 * nodes[a] + d).segment<3>(3 * node);
        }
      }
    }
  }
  return u;
}

double NeedleInsertion3::stuckExcess(double s) const {
  double worst = -1e300;
  bool any = false;
  for (const ShaftPoint& p : shaft_) {
    any = any || p.stuck;
  }
  if (!any) {
    return worst;
  }
  const double to_event = next_event_cut_m_ - cut_total_m_;
  const EmbeddedPoint tip = along(std::min(cutLength(s), to_event));
  const Solution sol = solveAt(s, &tip);
  for (std::size_t k = 0; k < shaft_.size(); ++k) {
    if (shaft_[k].stuck) {
      worst = std::max(worst, std::abs(sol.forces(3 * static_cast<int>(k))) -
                                  needle_.static_friction_N_per_m * shaft_[k].share_m);
    }
  }
  return worst;
}

double NeedleInsertion3::firstSlip(double target) const {
  constexpr int kBisections = 48;
  if (!(stuckExcess(target) > 0.0)) {
    return target;
  }
  double lo = s_, hi = target;
  for (int i = 0; i < kBisections && hi - lo > kEventTol_m; ++i) {
    const double mid = 0.5 * (lo + hi);
    (stuckExcess(mid) > 0.0 ? hi : lo) = mid;
  }
  return hi;
}

bool NeedleInsertion3::insertSegment(double target) {
  const double fb = needle_.cutting_force_N;
  if (!punctured_) {
    // The tip presses the surface point: its force is affine in s until it reaches f_b.
    const double fa = solveAt(s_, &tip_).tip_force_N;
    const double f_end = solveAt(target, &tip_).tip_force_N;
    if (f_end < fb) {
      commit(target, nullptr);
      return true;
    }
    commit(crossing(s_, fa, target, f_end, fb), nullptr);
    punctured_ = true;
    pending_track_ = tip_;
    cut_total_m_ = 0.0;
    next_event_cut_m_ = needle_.track_spacing_m;
    ++info_.events;
    return false;
  }
  // A stuck shaft point slips where holding it first needs more than the static friction:
  // located by bisection on the tip position, the cut solved at each.
  const double end = firstSlip(target);
  if (end < target) {
    if (!cutTo(std::max(end, s_))) {
      return false;  // a track point came first
    }
    // The point(s) at their static limit slip (at least the one nearest to it: progress).
    std::size_t nearest = shaft_.size();
    double nearest_ratio = -1.0;
    bool flipped = false;
    for (std::size_t k = 0; k < shaft_.size(); ++k) {
      ShaftPoint& p = shaft_[k];
      const double ratio = std::abs(committed_.forces(3 * static_cast<int>(k))) /
                           (needle_.static_friction_N_per_m * p.share_m);
      if (p.stuck && ratio >= 1.0 - 1e-9) {
        p.stuck = false;
        flipped = true;
      } else if (p.stuck && ratio > nearest_ratio) {
        nearest = k;
        nearest_ratio = ratio;
      }
    }
    if (!flipped && nearest < shaft_.size()) {
      shaft_[nearest].stuck = false;
    }
    commit(s_, nullptr);
    ++info_.events;
    return false;
  }
  return cutTo(target);
}

bool NeedleInsertion3::cutTo(double target) {
  const double fb = needle_.cutting_force_N;
  const double cut = cutLength(target);
  const double to_event = next_event_cut_m_ - cut_total_m_;
  if (cut < to_event - kCutTol_m) {
    const EmbeddedPoint p = along(cut);
    cut_total_m_ += cut;
    commit(target, &p);
    return true;
  }
  // The cut reaches the next track point: with the tip's tissue point there, the tip force is
  // affine in s, so the event is located exactly.
  const EmbeddedPoint p = along(to_event);
  const double fa = solveAt(s_, &p).tip_force_N;
  const double f_end = solveAt(target, &p).tip_force_N;
  const double s_event = f_end > fb ? crossing(s_, fa, target, f_end, fb) : target;
  cut_total_m_ = next_event_cut_m_;
  next_event_cut_m_ += needle_.track_spacing_m;
  addTrackPoint(pending_track_);
  pending_track_ = p;
  commit(s_event, &p);
  ++info_.events;
  return s_event >= target - kEventTol_m;
}

bool NeedleInsertion3::retractSegment(double target) {
  const double end = std::max(target, entry_x_m_);
  if (end < s_ - kEventTol_m && !shaft_.empty()) {
    const Solution a = solveAt(s_, nullptr), b = solveAt(end, nullptr);
    double s_event = end;
    for (std::size_t k = 0; k < shaft_.size(); ++k) {
      const int i = 3 * static_cast<int>(k);
      const ShaftPoint& p = shaft_[k];
      if (p.stuck) {
        const double limit = needle_.static_friction_N_per_m * p.share_m;
        if (std::abs(b.forces(i)) > limit) {
          const double level = b.forces(i) > 0.0 ? limit : -limit;
          s_event = std::max(s_event, crossing(s_, a.forces(i), end, b.forces(i), level));
        }
      } else {
        // Released when the tip passes back over it: s = world x.
        const double ga = s_ - (p.point.reference_m.x() + a.displacement(i));
        const double gb = end - (p.point.reference_m.x() + b.displacement(i));
        if (gb <= 0.0) {
          s_event = std::max(s_event, crossing(s_, ga, end, gb, 0.0));
        }
      }
    }
    const Solution e = solveAt(s_event, nullptr);
    bool changed = false;
    for (std::size_t k = shaft_.size(); k-- > 0;) {
      const int i = 3 * static_cast<int>(k);
      ShaftPoint& p = shaft_[k];
      const double world_x = p.point.reference_m.x() + e.displacement(i);
      if (p.stuck &&
          std::abs(e.forces(i)) >= needle_.static_friction_N_per_m * p.share_m * (1.0 - 1e-9)) {
        p.stuck = false;
        changed = true;
      } else if (!p.stuck && s_event <= world_x + kEventTol_m) {
        releaseShaftPoint(k);
        changed = true;
      }
    }
    commit(s_event, nullptr);
    info_.events += changed ? 1 : 0;
    if (s_event > end + kEventTol_m) {
      return false;
    }
  } else if (end < s_) {
    commit(end, nullptr);
  }
  if (target <= entry_x_m_) {
    // Out of the tissue: nothing holds it any more.
    shaft_.clear();
    shaft_compliance_.resize(0, 0);
    in_tissue_ = punctured_ = tip_active_ = false;
    commit(target, nullptr);
  }
  return true;
}

bool NeedleInsertion3::moveTo(const Eigen::Vector2d& lateral, double tip_x, std::string* why_not) {
  auto refuse = [&](const std::string& why) {
    if (why_not) {
      *why_not = why;
    }
    return false;
  };
  if (!lateral.allFinite() || !std::isfinite(tip_x)) {
    return refuse("non-finite lateral position or tip position");
  }
  if (in_tissue_ && (lateral - lateral_).norm() > 1e-12) {
    return refuse("the lateral position can change only outside the tissue");
  }
  info_.events = 0;
  info_.corotation_updates = 0;
  warp_updates_ = 0;
  solves_ = 0;
  if (!in_tissue_) {
    lateral_ = lateral;
    if (tip_x < entry_x_m_) {
      s_ = tip_x;
      direction_ = 1;
      return true;
    }
    std::optional<EmbeddedPoint> entry =
        model_.locate(Vector3(entry_x_m_ + kEntryInset_m, lateral.x(), lateral.y()));
    if (!entry) {
      return refuse("the needle line (y " + std::to_string(lateral.x() * 1e3) + " mm, z " +
                    std::to_string(lateral.y() * 1e3) + " mm) misses the tissue mesh");
    }
    prefetchLine(lateral);
    s_ = entry->reference_m.x();
    tip_ = *entry;
    in_tissue_ = tip_active_ = true;
    punctured_ = false;
    direction_ = 1;
    commit(s_, &tip_);
    ++info_.events;
  }
  if (direction_ > 0 && !punctured_ && tip_x < s_ && tip_x >= entry_x_m_) {
    tip_x = s_;  // touching the entry face: nothing to move yet
  }
  const int dir = tip_x >= s_ ? 1 : -1;
  if (dir != direction_) {
    if (dir > 0) {
      return refuse("the needle must leave the tissue before it is inserted again");
    }
    // The needle stops and reverses: every shaft point sticks where it is; the tip's cut ends.
    direction_ = -1;
    tip_active_ = false;
    for (ShaftPoint& p : shaft_) {
      p.stuck = true;
      p.offset_m = p.world_x_m - s_;
    }
    commit(s_, nullptr);
  }
  try {
    for (int i = 0; i < kMaxEventsPerMove; ++i) {
      const bool done = direction_ > 0 ? insertSegment(tip_x) : retractSegment(tip_x);
      // Corotational: at the move's end the segment is solved again until the warp has
      // converged; events inside the move are located with the warp of its start (the warp
      // is a second-order part of the displacement, so that lag is far below the tolerance).
      if (done && settleWarp(false)) {
        break;
      }
    }
  } catch (const std::runtime_error& e) {
    return refuse(e.what());
  }
  info_.tip_force_N = committed_.tip_force_N;
  info_.friction_force_N = 0.0;
  info_.slipping = 0;
  for (std::size_t k = 0; k < shaft_.size(); ++k) {
    info_.friction_force_N += committed_.forces(3 * static_cast<int>(k));
    info_.slipping += shaft_[k].stuck ? 0 : 1;
  }
  info_.shaft_points = static_cast<int>(shaft_.size());
  info_.solves = solves_;
  return true;
}

std::optional<int> NeedleInsertion3::implantSeed(std::string* why_not) {
  if (!in_tissue_ || !punctured_ || !tip_active_) {
    if (why_not) {
      *why_not = "the needle tip is not in tissue";
    }
    return std::nullopt;
  }
  seeds_.push_back(tip_.reference_m);
  return static_cast<int>(seeds_.size()) - 1;
}

int NeedleInsertion3::addSeed(const Vector3& reference_m) {
  if (!model_.locate(reference_m)) {
    throw std::invalid_argument(
        "NeedleInsertion3::addSeed: the seed's tissue point is outside "
        "the mesh");
  }
  seeds_.push_back(reference_m);
  return static_cast<int>(seeds_.size()) - 1;
}

const Vector3& NeedleInsertion3::seedReference(int seed) const {
  return seeds_.at(static_cast<std::size_t>(seed));
}

Vector3 NeedleInsertion3::worldOf(const Vector3& reference) const {
  const std::optional<EmbeddedPoint> p = model_.locate(reference);
  if (!p) {
    throw std::invalid_argument("NeedleInsertion3::worldOf: the point is outside the mesh");
  }
  Vector3 x = reference;
  const auto& nodes = model_.mesh().elements[static_cast<std::size_t>(p->element)];
  for (int a = 0; a < 4; ++a) {
    x += p->weights(a) * nodeDisplacement(nodes[a]);
  }
  return x;
}

Vector3 NeedleInsertion3::seedWorld(int seed) const {
  return worldOf(seedReference(seed));
}

std::vector<Vector3> NeedleInsertion3::shaftReference() const {
  std::vector<Vector3> out;
  for (const ShaftPoint& p : shaft_) {
    out.push_back(p.point.reference_m);
  }
  return out;
}

Eigen::VectorXd NeedleInsertion3::displacementField() const {
  Eigen::VectorXd f = Eigen::VectorXd::Zero(3 * model_.mesh().nodeCount());
  const int ns = static_cast<int>(shaft_.size());
  for (int k = 0; k < committed_.forces.size() / 3; ++k) {
    const EmbeddedPoint& p = k < ns ? shaft_[static_cast<std::size_t>(k)].point : tip_;
    const auto& nodes = model_.mesh().elements[static_cast<std::size_t>(p.element)];
    for (int a = 0; a < 4; ++a) {
      f.segment<3>(3 * nodes[a]) += p.weights(a) * committed_.forces.segment<3>(3 * k);
    }
  }
  Eigen::VectorXd u = model_.compliance().solve(f);
  if (warp_.size() > 0) {
    u += warp_;
  }
  return u;
}

}  // namespace needle_guidance::tissue_3d
