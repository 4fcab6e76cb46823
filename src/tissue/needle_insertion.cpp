#include "needle_guidance/tissue/needle_insertion.h"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <unordered_map>

#include "needle_guidance/format.h"
#include "needle_guidance/tissue/interaction_events.h"

namespace needle_guidance::tissue {
namespace {

constexpr double kGeomTol_m = 1e-12;
constexpr int kMoveBisections = 30;

double cross2(const Point2& a, const Point2& b) {
  return a.x() * b.y() - a.y() * b.x();
}

StepStatus refused(const std::string& message) {
  return StepStatus{false, message};
}

std::string str(double v) {
  return formatNumber(v);
}

}  // namespace

NeedleInsertion::NeedleInsertion(FemModel& model, Integrator& integrator,
                                 std::vector<int> entry_nodes, const std::vector<int>& fixed_dofs,
                                 const Point2& bounds_min, const Point2& bounds_max,
                                 const NeedleParams& params)
    : model_(model),
      integrator_(integrator),
      entry_nodes_(std::move(entry_nodes)),
      bounds_min_(bounds_min),
      bounds_max_(bounds_max),
      params_(params) {
  auto positive = [](double v) { return std::isfinite(v) && v > 0.0; };
  auto non_negative = [](double v) { return std::isfinite(v) && v >= 0.0; };
  if (!positive(params.cut_length_m) || !non_negative(params.cutting_force_N) ||
      !non_negative(params.static_friction_N_per_m) ||
      !non_negative(params.kinetic_friction_N_per_m) || !non_negative(params.stick_velocity_m_s) ||
      params.max_cuts_per_step < 1 || params.max_friction_iterations < 1 ||
      !(params.min_area_fraction > 0.0) || !(params.min_area_fraction < 1.0)) {
    throw std::invalid_argument(
        "NeedleInsertion: invalid needle parameters (cut length must be > 0, forces and stick "
        "velocity >= 0, iteration bounds >= 1, min area fraction in (0, 1))");
  }
  if (params.kinetic_friction_N_per_m > params.static_friction_N_per_m) {
    throw std::invalid_argument(
        "NeedleInsertion: kinetic friction " + str(params.kinetic_friction_N_per_m) +
        " N/m exceeds static friction " + str(params.static_friction_N_per_m) + " N/m");
  }
  const int n = model_.nodeCount();
  node_fixed_.assign(static_cast<std::size_t>(n), 0);
  for (int dof : fixed_dofs) {
    if (dof < 0 || dof >= 2 * n) {
      throw std::invalid_argument("NeedleInsertion: fixed DOF " + std::to_string(dof) +
                                  " out of range");
    }
    node_fixed_[static_cast<std::size_t>(dof / 2)] = 1;
  }
  entry_nodes_.erase(std::remove_if(entry_nodes_.begin(), entry_nodes_.end(),
                                    [&](int node) {
                                      return node < 0 || node >= n ||
                                             node_fixed_[static_cast<std::size_t>(node)];
                                    }),
                     entry_nodes_.end());
  if (entry_nodes_.empty()) {
    throw std::invalid_argument("NeedleInsertion: the entry face has no free node");
  }
  const auto& mesh = model_.mesh();
  original_nodes_ = mesh.nodes;
  original_area_.resize(mesh.triangleCount());
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    original_area_[t] = mesh.triangleArea(t);
  }
  f_ext_ = Eigen::VectorXd::Zero(model_.dofCount());
  u_prev_ = integrator_.displacement();
  tip_x_m_ = prev_tip_x_m_ = bounds_min_.x() - 0.01;
  height_m_ = 0.5 * (bounds_min_.y() + bounds_max_.y());
}

NeedleInsertion::NeedleInsertion(const NeedleInsertion& other, FemModel& model,
                                 Integrator& integrator)
    : model_(model),
      integrator_(integrator),
      entry_nodes_(other.entry_nodes_),
      node_fixed_(other.node_fixed_),
      bounds_min_(other.bounds_min_),
      bounds_max_(other.bounds_max_),
      params_(other.params_),
      original_area_(other.original_area_),
      original_nodes_(other.original_nodes_),
      in_tissue_(other.in_tissue_),
      height_m_(other.height_m_),
      tip_x_m_(other.tip_x_m_),
      prev_tip_x_m_(other.prev_tip_x_m_),
      tip_node_(other.tip_node_),
      tip_start_ref_(other.tip_start_ref_),
      shaft_(other.shaft_),
      tip_patch_(other.tip_patch_),
      shaft_state_(other.shaft_state_),
      seeds_(other.seeds_),
      f_ext_(other.f_ext_),
      u_prev_(other.u_prev_),
      info_(other.info_),
      last_dofs_(other.last_dofs_),
      last_f_ext_(other.last_f_ext_),
      last_reactions_(other.last_reactions_),
      motion_direction_(other.motion_direction_) {}

std::optional<Point2> NeedleInsertion::tipReference() const {
  if (tip_node_ < 0) {
    return std::nullopt;
  }
  return model_.mesh().nodes[static_cast<std::size_t>(tip_node_)];
}

std::vector<Point2> NeedleInsertion::deformedNodes() const {
  const auto& nodes = model_.mesh().nodes;
  const Eigen::VectorXd& u = integrator_.displacement();
  std::vector<Point2> out(nodes.size());
  for (std::size_t i = 0; i < nodes.size(); ++i) {
    out[i] = nodes[i] + Point2(u[2 * i], u[2 * i + 1]);
  }
  return out;
}

Prescribed NeedleInsertion::buildPrescribed() const {
  Prescribed p;
  const auto& nodes = model_.mesh().nodes;
  if (tip_node_ >= 0) {
    const Point2& x = nodes[static_cast<std::size_t>(tip_node_)];
    p.dofs.push_back(dofX(tip_node_));
    p.values.push_back(tip_x_m_ - x.x());
    p.dofs.push_back(dofY(tip_node_));
    p.values.push_back(height_m_ - x.y());
    for (int node : tip_patch_) {  // a finite tip: its face moves rigidly with the tip node
      p.dofs.push_back(dofX(node));
      p.values.push_back(tip_x_m_ - x.x());
      p.dofs.push_back(dofY(node));
      p.values.push_back(height_m_ - x.y());
    }
  }
  for (std::size_t s = 0; s < shaft_.size(); ++s) {
    const int node = shaft_[s];
    const Point2& x = nodes[static_cast<std::size_t>(node)];
    p.dofs.push_back(dofY(node));  // on the needle axis (2.3.3)
    p.values.push_back(height_m_ - x.y());
    if (shaft_state_[s].stuck) {  // static friction: moves with the needle (2.3.5)
      p.dofs.push_back(dofX(node));
      p.values.push_back(tip_x_m_ + shaft_state_[s].offset_m - x.x());
    }
  }
  return p;
}

int NeedleInsertion::prescribedIndex(const Prescribed& p, int dof) const {
  const auto it = std::find(p.dofs.begin(), p.dofs.end(), dof);
  return it == p.dofs.end() ? -1 : static_cast<int>(it - p.dofs.begin());
}

StepStatus NeedleInsertion::step(double dt_s, double needle_height_m, double tip_x_m) {
  if (!std::isfinite(dt_s) || !std::isfinite(needle_height_m) || !std::isfinite(tip_x_m)) {
    return refused("NeedleInsertion::step: non-finite command (dt " + str(dt_s) + " s, height " +
                   str(needle_height_m) + " m, tip x " + str(tip_x_m) + " m)");
  }
  if (dt_s <= 0.0) {
    return refused("NeedleInsertion::step: dt " + str(dt_s) + " s must be > 0");
  }
  if (needle_height_m <= bounds_min_.y() || needle_height_m >= bounds_max_.y()) {
    return refused("NeedleInsertion::step: needle height " + str(needle_height_m) +
                   " m is outside the tissue (" + str(bounds_min_.y()) + ", " +
                   str(bounds_max_.y()) + ") m");
  }
  if (tip_x_m >= bounds_max_.x()) {
    return refused("NeedleInsertion::step: tip x " + str(tip_x_m) +
                   " m is beyond the tissue (max x " + str(bounds_max_.x()) + " m)");
  }
  if (in_tissue_ && std::abs(needle_height_m - height_m_) > kGeomTol_m) {
    return refused(
        "NeedleInsertion::step: the needle height may not change while the tip is in "
        "tissue (" +
        str(height_m_) + " m -> " + str(needle_height_m) + " m)");
  }

  const double advance = tip_x_m - std::max(tip_x_m_, bounds_min_.x());
  if (advance > params_.cut_length_m * params_.max_cuts_per_step) {
    return refused("NeedleInsertion::step: an advance of " + str(advance) +
                   " m in one step may need more than " +
                   std::to_string(params_.max_cuts_per_step) + " cuts of " +
                   str(params_.cut_length_m) +
                   " m (max_cuts_per_step); state unchanged (use smaller steps)");
  }

  // Keep the step's start so a failed step leaves the state unchanged where it can.
  const Eigen::VectorXd u0 = integrator_.displacement();
  const Eigen::VectorXd v0 = integrator_.velocity();
  const Eigen::VectorXd a0 = integrator_.acceleration();
  const double saved_height = height_m_;
  const double saved_tip = tip_x_m_;

  info_ = InsertionStepInfo{};
  prev_tip_x_m_ = tip_x_m_;
  height_m_ = needle_height_m;
  tip_x_m_ = tip_x_m;
  const double entry_x = bounds_min_.x();
  const bool inserting = tip_x_m_ >= prev_tip_x_m_;
  const bool entered = !in_tissue_ && tip_x_m_ > entry_x;

  if (in_tissue_ && tip_x_m_ <= entry_x) {  // the needle has left the tissue
    in_tissue_ = false;
    tip_node_ = -1;
    info_.released = static_cast<int>(shaft_.size());
    shaft_.clear();
    shaft_state_.clear();
  } else if (!in_tissue_ && tip_x_m_ > entry_x) {
    if (!enterTissue()) {
      height_m_ = saved_height;
      tip_x_m_ = saved_tip;
      return refused("NeedleInsertion::step: no free entry node can be placed at height " +
                     str(needle_height_m) + " m");
    }
  } else if (in_tissue_ && !inserting) {
    if (tip_node_ >= 0) {  // retraction keeps no tip node (2.3.6)
      shaft_.push_back(tip_node_);
      shaft_state_.push_back(ShaftState{});
      shaft_state_.back().direction = -1.0;
      tip_node_ = -1;
    }
    releaseBehind();
  } else if (in_tissue_ && inserting && tip_node_ < 0) {
    // Re-insertion along the cut path: the deepest shaft node becomes the tip again once the
    // needle reaches it; until then the needle slides in the existing cut.
    const auto deformed = deformedNodes();
    if (shaft_.empty()) {
      enterTissue();
    } else if (tip_x_m_ >= deformed[static_cast<std::size_t>(shaft_.back())].x()) {
      tip_node_ = shaft_.back();
      tip_start_ref_ = model_.mesh().nodes[static_cast<std::size_t>(tip_node_)];
      shaft_.pop_back();
      shaft_state_.pop_back();
    }
  }

  refreshTipPatch();
  const double direction = inserting ? 1.0 : -1.0;
  if (direction != motion_direction_) {  // kinetic friction turns with the needle (2.3.6)
    for (ShaftState& state : shaft_state_) {
      state.direction = state.stuck ? state.direction : direction;
    }
    motion_direction_ = direction;
  }
  applyKineticForces();
  Solved end;
  const bool located =
      params_.locate_events && integrator_.kind() == IntegratorKind::kQuasiStatic && in_tissue_;
  // Entering, the tip starts at the entry face: the first cut is located from there.
  const double from_x = entered ? std::max(prev_tip_x_m_, entry_x) : prev_tip_x_m_;
  StepStatus status =
      located ? solveLocated(dt_s, from_x, inserting, end) : solveFixed(dt_s, inserting, end);
  if (!status) {
    integrator_.setState(u0, v0, a0);
    height_m_ = saved_height;
    tip_x_m_ = saved_tip;
    return status;
  }
  tip_x_m_ = tip_x_m;
  if (tip_node_ >= 0) {
    info_.tip_force_N = tipForce(end.prescribed, end.reactions);
  }
  for (std::size_t s = 0; s < shaft_.size(); ++s) {
    const int index = prescribedIndex(end.prescribed, dofX(shaft_[s]));
    info_.friction_force_N += index >= 0 ? end.reactions[index] : f_ext_[dofX(shaft_[s])];
    info_.slipping += shaft_state_[s].stuck ? 0 : 1;
  }
  last_dofs_ = end.prescribed.dofs;
  last_f_ext_ = f_ext_;
  last_reactions_ = end.reactions;
  u_prev_ = integrator_.displacement();
  return StepStatus{};
}

void NeedleInsertion::applyKineticForces() {
  f_ext_.setZero();
  for (std::size_t s = 0; s < shaft_.size(); ++s) {
    if (!shaft_state_[s].stuck) {
      f_ext_[dofX(shaft_[s])] =
          shaft_state_[s].direction * params_.kinetic_friction_N_per_m * shaftShare(s);
    }
  }
}

StepStatus NeedleInsertion::solveAt(double x_m, double dt_s, Solved& out) {
  tip_x_m_ = x_m;
  out.x_m = x_m;
  out.prescribed = buildPrescribed();
  const StepStatus status = integrator_.step(dt_s, f_ext_, out.prescribed, out.reactions);
  out.u = integrator_.displacement();
  return status;
}

StepStatus NeedleInsertion::solveLocated(double dt_s, double from_x_m, bool inserting,
                                         Solved& end) {
  const double to_x = tip_x_m_;
  const double length = std::abs(to_x - from_x_m);
  // The step's start: the last step's end when nothing changed since, else solved again.
  Solved a;
  a.x_m = from_x_m;
  tip_x_m_ = from_x_m;
  a.prescribed = buildPrescribed();
  a.u = integrator_.displacement();
  const bool unchanged = a.prescribed.dofs == last_dofs_ && last_f_ext_.size() == f_ext_.size() &&
                         last_f_ext_ == f_ext_ && from_x_m == prev_tip_x_m_;
  bool after_event = !unchanged;
  StepStatus status;
  if (unchanged) {
    a.reactions = last_reactions_;
  } else if (!(status = solveAt(from_x_m, dt_s, a))) {
    return status;
  }
  bool cut_blocked = false;
  int cuts = 0;
  for (int events = 0;; ++events) {
    if (events > params_.max_events_per_step + params_.max_cuts_per_step) {
      return refused("NeedleInsertion::step: more than " +
                     std::to_string(params_.max_events_per_step) +
                     " stick-slip and release events in one step of " + str(length) +
                     " m; the needle stays where it was, cuts made in the step are kept (use "
                     "smaller steps)");
    }
    const double fraction_left = length > 0.0 ? std::abs(to_x - a.x_m) / length : 1.0;
    const double dt_left = std::max(dt_s * fraction_left, 1e-12);
    if (firstEvent(a, a, inserting && !cut_blocked) == 0.0) {
      // An event at a itself (a stuck node over its limit, a cut due): applied there without
      // solving the step's end first.
      tip_x_m_ = a.x_m;
      applyEvents(a, a, 0.0, inserting && !cut_blocked, cut_blocked, cuts);
      ++info_.events;
      applyKineticForces();
      if (!(status = solveAt(a.x_m, dt_left, a))) {
        return status;
      }
      after_event = true;
      continue;
    }
    Solved b;
    integrator_.setState(a.u, Eigen::VectorXd::Zero(a.u.size()), Eigen::VectorXd::Zero(a.u.size()));
    if (!(status = solveAt(to_x, dt_left, b))) {
      return status;
    }
    const Eigen::VectorXd f_before = f_ext_;
    if (after_event && stickSlipping(a, b, dt_left)) {
      // The state at a stands: a node that sticks there is held where it is, by the kinetic
      // friction it felt (no solve needed); the step's end is solved again.
      std::unordered_map<int, double> held;
      for (std::size_t i = 0; i < a.prescribed.dofs.size(); ++i) {
        held[a.prescribed.dofs[i]] = a.reactions[static_cast<Eigen::Index>(i)];
      }
      tip_x_m_ = a.x_m;
      a.prescribed = buildPrescribed();
      a.reactions.resize(static_cast<Eigen::Index>(a.prescribed.dofs.size()));
      for (std::size_t i = 0; i < a.prescribed.dofs.size(); ++i) {
        const int dof = a.prescribed.dofs[i];
        const auto it = held.find(dof);
        a.reactions[static_cast<Eigen::Index>(i)] = it != held.end() ? it->second : f_before[dof];
      }
      continue;
    }
    after_event = false;
    const double s = b.x_m == a.x_m ? events::kNever : firstEvent(a, b, inserting && !cut_blocked);
    if (!(s <= 1.0)) {
      end = std::move(b);
      return status;
    }
    if (cuts > params_.max_cuts_per_step) {
      return refused("NeedleInsertion::step: more than " +
                     std::to_string(params_.max_cuts_per_step) + " cuts in one step of " +
                     str(length) + " m (cut length " + str(params_.cut_length_m) +
                     " m); the needle stays where it was, cuts made in the step are kept (use "
                     "smaller steps)");
    }
    // The state at the event: exact for the linear model between events.
    const double x_event = a.x_m + s * (b.x_m - a.x_m);
    integrator_.setState(a.u + s * (b.u - a.u), Eigen::VectorXd::Zero(a.u.size()),
                         Eigen::VectorXd::Zero(a.u.size()));
    tip_x_m_ = x_event;
    applyEvents(a, b, s, inserting && !cut_blocked, cut_blocked, cuts);
    ++info_.events;
    applyKineticForces();
    if (!(status = solveAt(x_event, dt_left * s + 1e-12, a))) {
      return status;
    }
    after_event = true;
  }
}

double NeedleInsertion::cutFraction(const Solved& a, const Solved& b) const {
  // Cutting (2.3.4): the tip force has reached the cutting force and the needle tip is a cut
  // length ahead of the tip node's reference position (a cut never runs past the needle: with a
  // force already past the cutting force, as with none, the tip node follows in cuts of b).
  const double p_x = model_.mesh().nodes[static_cast<std::size_t>(tip_node_)].x();
  const double force =
      events::upCrossing(tipForce(a.prescribed, a.reactions), tipForce(b.prescribed, b.reactions),
                         params_.cutting_force_N);
  const double room = events::upCrossing(a.x_m - p_x, b.x_m - p_x, params_.cut_length_m);
  return std::max(force, room);
}

double NeedleInsertion::firstEvent(const Solved& a, const Solved& b, bool may_cut) const {
  double s = events::kNever;
  if (may_cut && tip_node_ >= 0) {
    s = cutFraction(a, b);
  }
  const auto& nodes = model_.mesh().nodes;
  for (std::size_t k = 0; k < shaft_.size(); ++k) {
    const int dof = dofX(shaft_[k]);
    if (shaft_state_[k].stuck) {  // static friction exceeded: slips (2.3.5)
      const int index = prescribedIndex(b.prescribed, dof);
      s = std::min(s, events::magnitudeCrossing(a.reactions[index], b.reactions[index],
                                                params_.static_friction_N_per_m * shaftShare(k)));
    } else if (tip_node_ < 0) {  // retraction passes the node: released (2.3.6)
      const double x = nodes[static_cast<std::size_t>(shaft_[k])].x();
      s = std::min(s, events::upCrossing(x + a.u[dof] - a.x_m, x + b.u[dof] - b.x_m, kGeomTol_m));
    }
  }
  return s;
}

void NeedleInsertion::applyEvents(const Solved& a, const Solved& b, double s, bool may_cut,
                                  bool& cut_blocked, int& cuts) {
  constexpr double kSameEvent = 1e-9;  // fractions this close are one event
  const auto& nodes = model_.mesh().nodes;
  auto at = [&](double f0, double f1) { return f0 + s * (f1 - f0); };
  for (std::size_t k = shaft_.size(); k-- > 0;) {
    const int dof = dofX(shaft_[k]);
    ShaftState& state = shaft_state_[k];
    if (state.stuck) {
      const int index = prescribedIndex(b.prescribed, dof);
      const double limit = params_.static_friction_N_per_m * shaftShare(k);
      if (events::magnitudeCrossing(a.reactions[index], b.reactions[index], limit) <=
          s + kSameEvent) {
        state.stuck = false;
        state.direction = at(a.reactions[index], b.reactions[index]) > 0.0 ? 1.0 : -1.0;
        state.slip_x_m = tip_x_m_;
      }
    } else if (tip_node_ < 0) {
      const double x = nodes[static_cast<std::size_t>(shaft_[k])].x();
      if (events::upCrossing(x + a.u[dof] - a.x_m, x + b.u[dof] - b.x_m, kGeomTol_m) <=
          s + kSameEvent) {
        shaft_.erase(shaft_.begin() + static_cast<std::ptrdiff_t>(k));
        shaft_state_.erase(shaft_state_.begin() + static_cast<std::ptrdiff_t>(k));
        ++info_.released;
      }
    }
  }
  if (may_cut && tip_node_ >= 0 && cutFraction(a, b) <= s + kSameEvent) {
    const int shaft_before = static_cast<int>(shaft_.size());
    if (cut()) {
      ++cuts;
      ++info_.cuts;
      for (std::size_t k = static_cast<std::size_t>(shaft_before); k < shaft_state_.size(); ++k) {
        shaft_state_[k].slip_x_m = -1e300;  // promoted: slipping, may stick at once
      }
      refreshTipPatch();
    } else {
      cut_blocked = true;  // nothing ahead to cut: the tip pushes on
    }
  }
}

bool NeedleInsertion::stickSlipping(const Solved& a, const Solved& b, double dt_s) {
  bool stuck_any = false;
  const auto& nodes = model_.mesh().nodes;
  for (std::size_t k = 0; k < shaft_.size(); ++k) {
    ShaftState& state = shaft_state_[k];
    if (state.stuck || !(state.slip_x_m < a.x_m)) {
      continue;
    }
    const int dof = dofX(shaft_[k]);
    if (events::sticks(b.x_m - a.x_m, b.u[dof] - a.u[dof], dt_s, params_.stick_velocity_m_s)) {
      state.stuck = true;
      state.offset_m = nodes[static_cast<std::size_t>(shaft_[k])].x() + a.u[dof] - a.x_m;
      stuck_any = true;
    }
  }
  if (stuck_any) {
    applyKineticForces();
  }
  return stuck_any;
}

StepStatus NeedleInsertion::solveFixed(double dt_s, bool inserting, Solved& end) {
  const Eigen::VectorXd u0 = integrator_.displacement();
  const Eigen::VectorXd v0 = integrator_.velocity();
  const Eigen::VectorXd a0 = integrator_.acceleration();
  const double x = tip_x_m_;
  for (std::size_t s = 0; s < shaft_.size(); ++s) {  // slipping nodes drag along the motion
    shaft_state_[s].direction =
        shaft_state_[s].stuck ? shaft_state_[s].direction : (inserting ? 1.0 : -1.0);
  }
  applyKineticForces();
  StepStatus status;
  for (int iteration = 0; iteration < params_.max_friction_iterations; ++iteration) {
    if (iteration > 0) {
      integrator_.setState(u0, v0, a0);
    }
    if (!(status = solveAt(x, dt_s, end))) {
      return status;
    }
    // Stick decisions only in the first solve: a node that slipped keeps slipping until the
    // next step, so the stuck set only shrinks and the iteration ends in a few solves.
    if (!updateFriction(end.prescribed, end.reactions, dt_s, /*allow_stick=*/iteration == 0)) {
      break;
    }
  }
  // Cutting (2.3.4): while the needle pushes the tip node harder than the cutting force, the
  // tip advances b in the reference mesh and the step is solved again.
  int cuts = 0;
  while (inserting && tip_node_ >= 0 && cuts < params_.max_cuts_per_step) {
    if (tipForce(end.prescribed, end.reactions) < params_.cutting_force_N || !cut()) {
      break;
    }
    ++cuts;
    ++info_.cuts;
    refreshTipPatch();
    applyKineticForces();
    integrator_.setState(u0, v0, a0);
    if (!(status = solveAt(x, dt_s, end))) {
      return status;
    }
  }
  return status;
}

bool NeedleInsertion::updateFriction(const Prescribed& prescribed, const Eigen::VectorXd& reactions,
                                     double dt_s, bool allow_stick) {
  // Stick–slip (2.3.5, after Baraff and Witkin): a stuck node slips when holding it needs more
  // than the slip force; a slipping node sticks again when it moves with the needle.
  bool changed = false;
  const Eigen::VectorXd& u = integrator_.displacement();
  const double needle_velocity = (tip_x_m_ - prev_tip_x_m_) / dt_s;
  const auto& nodes = model_.mesh().nodes;
  for (std::size_t s = 0; s < shaft_.size(); ++s) {
    const int node = shaft_[s];
    ShaftState& state = shaft_state_[s];
    if (state.stuck) {
      const int index = prescribedIndex(prescribed, dofX(node));
      if (index >= 0 &&
          std::abs(reactions[index]) > params_.static_friction_N_per_m * shaftShare(s)) {
        state.stuck = false;
        state.direction = reactions[index] > 0.0 ? 1.0 : -1.0;
        f_ext_[dofX(node)] = state.direction * params_.kinetic_friction_N_per_m * shaftShare(s);
        changed = true;
      }
    } else if (allow_stick) {
      const double node_velocity = (u[dofX(node)] - u_prev_[dofX(node)]) / dt_s;
      if (std::abs(needle_velocity - node_velocity) < params_.stick_velocity_m_s) {
        state.stuck = true;
        state.offset_m = nodes[static_cast<std::size_t>(node)].x() + u[dofX(node)] - tip_x_m_;
        f_ext_[dofX(node)] = 0.0;
        changed = true;
      }
    }
  }
  return changed;
}

bool NeedleInsertion::enterTissue() {
  const auto& nodes = model_.mesh().nodes;
  int best = -1;
  double best_distance = 1e300;
  for (int node : entry_nodes_) {
    const double d = std::abs(nodes[static_cast<std::size_t>(node)].y() - height_m_);
    if (d < best_distance) {
      best_distance = d;
      best = node;
    }
  }
  if (best < 0) {
    return false;
  }
  const Point2 start = nodes[static_cast<std::size_t>(best)];
  moveNodeSafely(best, Point2(start.x(), height_m_));
  tip_node_ = best;
  tip_start_ref_ = model_.mesh().nodes[static_cast<std::size_t>(best)];
  in_tissue_ = true;
  return true;
}

Eigen::Matrix2d NeedleInsertion::deformationGradient(int triangle) const {
  const auto& mesh = model_.mesh();
  const auto& t = mesh.triangles[static_cast<std::size_t>(triangle)];
  const Eigen::VectorXd& u = integrator_.displacement();
  Eigen::Matrix2d dX, dx;
  for (int k = 0; k < 2; ++k) {
    const Point2 X0 = mesh.nodes[static_cast<std::size_t>(t[0])];
    const Point2 Xk = mesh.nodes[static_cast<std::size_t>(t[k + 1])];
    const Point2 u0(u[dofX(t[0])], u[dofY(t[0])]);
    const Point2 uk(u[dofX(t[k + 1])], u[dofY(t[k + 1])]);
    dX.col(k) = Xk - X0;
    dx.col(k) = (Xk + uk) - (X0 + u0);
  }
  return dx * dX.inverse();
}

bool NeedleInsertion::cut() {
  const auto& mesh = model_.mesh();
  const int i = tip_node_;
  const Point2 p = mesh.nodes[static_cast<std::size_t>(i)];
  // The triangle of the tip's star that a ray from p along direction r enters, and where the
  // ray leaves it through the opposite edge (j, k) at q.
  auto ahead = [&](const Point2& r, int& tri, int& j, int& k, Point2& q) {
    for (int t : model_.trianglesOfNode(i)) {
      const auto& nodes = mesh.triangles[static_cast<std::size_t>(t)];
      int pos = 0;
      while (nodes[static_cast<std::size_t>(pos)] != i) {
        ++pos;
      }
      const int a = nodes[static_cast<std::size_t>((pos + 1) % 3)];
      const int b = nodes[static_cast<std::size_t>((pos + 2) % 3)];
      const Point2 pa = mesh.nodes[static_cast<std::size_t>(a)] - p;
      const Point2 pb = mesh.nodes[static_cast<std::size_t>(b)] - p;
      // Counter-clockwise triangle (i, a, b): r lies in the wedge between pa and pb.
      if (cross2(pa, r) >= 0.0 && cross2(r, pb) >= 0.0) {
        const Point2 e = pb - pa;
        const double denom = cross2(r, e);
        if (std::abs(denom) < kGeomTol_m * kGeomTol_m) {
          continue;
        }
        const double s = cross2(pa, e) / denom;  // p + s r on line (a, b)
        tri = t;
        j = a;
        k = b;
        q = p + s * r;
        return true;
      }
    }
    return false;
  };
  Point2 r(1.0, 0.0);
  int tri = -1, j = -1, k = -1;
  Point2 q;
  if (!ahead(r, tri, j, k, q)) {
    return false;  // the tip is on the boundary facing out: nothing ahead to cut
  }
  // The needle's direction in the world mapped back to the reference mesh (2.3.4).
  const Point2 mapped = deformationGradient(tri).inverse() * Point2(1.0, 0.0);
  if (mapped.allFinite() && mapped.x() > 0.0) {
    const Point2 candidate = mapped.normalized();
    int tri2, j2, k2;
    Point2 q2;
    if (ahead(candidate, tri2, j2, k2, q2)) {
      r = candidate;
      tri = tri2;
      j = j2;
      k = k2;
      q = q2;
    }
  }
  // Cut b along r, but never past the needle tip: the material point at the tip cannot run
  // ahead of the needle (a full b would overshoot when the remaining compression is < b).
  const double b = std::min(params_.cut_length_m, (tip_x_m_ - p.x()) / r.x());
  if (!(b > kGeomTol_m)) {
    return false;
  }
  const Point2 last =
      shaft_.empty() ? tip_start_ref_ : mesh.nodes[static_cast<std::size_t>(shaft_.back())];
  const bool promote = (last - p).norm() > 2.0 * (q - p).norm() || (q - p).norm() <= b;
  if (!promote) {
    const double moved = moveNodeSafely(i, p + b * r);
    if (moved > 1e-3) {
      return true;
    }
    // The move would invert an element (figure 2.9): hand the tip to the next node instead.
  }
  // Distance rule (2.3.4): node i joins the shaft, its x returns to where it started, and the
  // closer of j, k (not fixed) moves to p + b r as the new tip node.
  const Point2 target = p + b * r;
  std::array<int, 2> candidates{j, k};
  if ((mesh.nodes[static_cast<std::size_t>(k)] - target).norm() <
      (mesh.nodes[static_cast<std::size_t>(j)] - target).norm()) {
    std::swap(candidates[0], candidates[1]);
  }
  int next = -1;
  for (int c : candidates) {
    if (!node_fixed_[static_cast<std::size_t>(c)] &&
        std::find(shaft_.begin(), shaft_.end(), c) == shaft_.end()) {
      next = c;
      break;
    }
  }
  if (next < 0) {
    return false;  // only fixed nodes ahead: the tip is at a fixed boundary
  }
  const Point2 start_of_i = tip_start_ref_;
  shaft_.push_back(i);
  shaft_state_.push_back(ShaftState{});  // starts slipping; sticks when it moves with the needle
  ++info_.promoted;
  moveNodeSafely(i, Point2(start_of_i.x(), mesh.nodes[static_cast<std::size_t>(i)].y()));
  tip_start_ref_ = mesh.nodes[static_cast<std::size_t>(next)];
  tip_node_ = next;
  moveNodeSafely(next, target);
  return true;
}

double NeedleInsertion::moveNodeSafely(int node, const Point2& target) {
  const auto& mesh = model_.mesh();
  const Point2 start = mesh.nodes[static_cast<std::size_t>(node)];
  if ((target - start).norm() < kGeomTol_m) {
    return 1.0;
  }
  // Every adjacent triangle keeps at least min_area_fraction of its original area.
  auto allowed = [&](const Point2& p) {
    for (int t : model_.trianglesOfNode(node)) {
      const auto& tri = mesh.triangles[static_cast<std::size_t>(t)];
      std::array<Point2, 3> v;
      for (int k = 0; k < 3; ++k) {
        const int n = tri[static_cast<std::size_t>(k)];
        v[static_cast<std::size_t>(k)] = n == node ? p : mesh.nodes[static_cast<std::size_t>(n)];
      }
      const double area = 0.5 * cross2(v[1] - v[0], v[2] - v[0]);
      if (area < params_.min_area_fraction * original_area_[static_cast<std::size_t>(t)]) {
        return false;
      }
    }
    return true;
  };
  double fraction = 1.0;
  if (!allowed(target)) {
    double lo = 0.0, hi = 1.0;
    for (int it = 0; it < kMoveBisections; ++it) {
      const double mid = 0.5 * (lo + hi);
      (allowed(start + mid * (target - start)) ? lo : hi) = mid;
    }
    fraction = lo;
    ++info_.relocations;
    if (fraction <= 0.0) {
      return 0.0;
    }
  }
  const std::vector<int> changed = model_.moveNode(node, start + fraction * (target - start));
  integrator_.modelChanged(changed);
  relocateSeeds(node);
  return fraction;
}

double NeedleInsertion::shaftShare(std::size_t s) const {
  const auto& nodes = model_.mesh().nodes;
  auto x_of = [&](int node) { return nodes[static_cast<std::size_t>(node)].x(); };
  const double before = s == 0 ? bounds_min_.x() : x_of(shaft_[s - 1]);
  const double after = s + 1 < shaft_.size() ? x_of(shaft_[s + 1])
                       : tip_node_ >= 0      ? x_of(tip_node_)
                                             : x_of(shaft_[s]);
  return 0.5 * std::abs(after - before);
}

double NeedleInsertion::tipForce(const Prescribed& prescribed,
                                 const Eigen::VectorXd& reactions) const {
  double force = reactions[prescribedIndex(prescribed, dofX(tip_node_))];
  for (int node : tip_patch_) {
    force += reactions[prescribedIndex(prescribed, dofX(node))];
  }
  return force;
}

void NeedleInsertion::refreshTipPatch() {
  tip_patch_.clear();
  if (tip_node_ < 0 || !(params_.tip_radius_m > 0.0)) {
    return;
  }
  // Free nodes within the tip radius of p on or ahead of the tip face, found by a search over
  // mesh neighbours outwards from the tip node.
  const auto& mesh = model_.mesh();
  const Point2 p = mesh.nodes[static_cast<std::size_t>(tip_node_)];
  const double r = params_.tip_radius_m;
  std::vector<int> frontier{tip_node_};
  std::vector<int> seen{tip_node_};
  while (!frontier.empty()) {
    const int node = frontier.back();
    frontier.pop_back();
    for (int t : model_.trianglesOfNode(node)) {
      for (int k : mesh.triangles[static_cast<std::size_t>(t)]) {
        if (std::find(seen.begin(), seen.end(), k) != seen.end()) {
          continue;
        }
        seen.push_back(k);
        const Point2& x = mesh.nodes[static_cast<std::size_t>(k)];
        if ((x - p).norm() > r) {
          continue;
        }
        frontier.push_back(k);
        const bool on_shaft = std::find(shaft_.begin(), shaft_.end(), k) != shaft_.end();
        if (x.x() >= p.x() - kGeomTol_m && !node_fixed_[static_cast<std::size_t>(k)] && !on_shaft) {
          tip_patch_.push_back(k);
        }
      }
    }
  }
}

void NeedleInsertion::releaseBehind() {
  const auto& nodes = model_.mesh().nodes;
  const Eigen::VectorXd& u = integrator_.displacement();
  for (std::size_t s = shaft_.size(); s-- > 0;) {
    const int node = shaft_[s];
    const double world_x = nodes[static_cast<std::size_t>(node)].x() + u[dofX(node)];
    if (world_x > tip_x_m_ + kGeomTol_m) {  // the needle has retracted past it (2.3.6)
      shaft_.erase(shaft_.begin() + static_cast<std::ptrdiff_t>(s));
      shaft_state_.erase(shaft_state_.begin() + static_cast<std::ptrdiff_t>(s));
      ++info_.released;
    }
  }
}

std::optional<int> NeedleInsertion::implantSeed(std::string* why_not) {
  if (!in_tissue_) {
    if (why_not) {
      *why_not = "the needle tip is not in tissue";
    }
    return std::nullopt;
  }
  Seed seed;
  seed.id = static_cast<int>(seeds_.size());
  if (tip_node_ >= 0) {
    seed.p_ref = model_.mesh().nodes[static_cast<std::size_t>(tip_node_)];
  } else {
    // No tip node while retracting: map the world tip point back to the reference mesh.
    const auto deformed = deformedNodes();
    const auto& mesh = model_.mesh();
    const Point2 tip(tip_x_m_, height_m_);
    bool found = false;
    for (std::size_t t = 0; t < mesh.triangleCount() && !found; ++t) {
      const auto& tri = mesh.triangles[t];
      const auto bary = geometry::barycentric(tip, deformed[static_cast<std::size_t>(tri[0])],
                                              deformed[static_cast<std::size_t>(tri[1])],
                                              deformed[static_cast<std::size_t>(tri[2])]);
      if (std::min({bary[0], bary[1], bary[2]}) >= -1e-9) {
        seed.p_ref = bary[0] * mesh.nodes[static_cast<std::size_t>(tri[0])] +
                     bary[1] * mesh.nodes[static_cast<std::size_t>(tri[1])] +
                     bary[2] * mesh.nodes[static_cast<std::size_t>(tri[2])];
        found = true;
      }
    }
    if (!found) {
      if (why_not) {
        *why_not = "the needle tip is not inside the deformed tissue";
      }
      return std::nullopt;
    }
  }
  locateSeed(seed);
  seeds_.push_back(seed);
  return seed.id;
}

void NeedleInsertion::locateSeed(Seed& seed) const {
  const auto& mesh = model_.mesh();
  auto inside = [&](int t, std::array<double, 3>& bary) {
    const auto& tri = mesh.triangles[static_cast<std::size_t>(t)];
    bary = geometry::barycentric(seed.p_ref, mesh.nodes[static_cast<std::size_t>(tri[0])],
                                 mesh.nodes[static_cast<std::size_t>(tri[1])],
                                 mesh.nodes[static_cast<std::size_t>(tri[2])]);
    return std::min({bary[0], bary[1], bary[2]}) >= -1e-10;
  };
  std::array<double, 3> bary{};
  // Constant time in the usual case (2.4): the seed can only have moved into a triangle around
  // the nodes of its previous one.
  if (seed.triangle >= 0) {
    for (int node : mesh.triangles[static_cast<std::size_t>(seed.triangle)]) {
      for (int t : model_.trianglesOfNode(node)) {
        if (inside(t, bary)) {
          seed.triangle = t;
          seed.barycentric = bary;
          return;
        }
      }
    }
  }
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    if (inside(static_cast<int>(t), bary)) {
      seed.triangle = static_cast<int>(t);
      seed.barycentric = bary;
      return;
    }
  }
  throw std::logic_error("NeedleInsertion: seed " + std::to_string(seed.id) +
                         " lies outside the reference mesh");
}

void NeedleInsertion::relocateSeeds(int moved_node) {
  const auto& mesh = model_.mesh();
  for (Seed& seed : seeds_) {
    const auto& tri = mesh.triangles[static_cast<std::size_t>(seed.triangle)];
    if (tri[0] == moved_node || tri[1] == moved_node || tri[2] == moved_node) {
      locateSeed(seed);
    }
  }
}

Point2 NeedleInsertion::seedPosition(const Seed& seed) const {
  const auto& mesh = model_.mesh();
  const Eigen::VectorXd& u = integrator_.displacement();
  const auto& tri = mesh.triangles[static_cast<std::size_t>(seed.triangle)];
  Point2 p = Point2::Zero();
  for (int k = 0; k < 3; ++k) {
    const int node = tri[static_cast<std::size_t>(k)];
    p += seed.barycentric[static_cast<std::size_t>(k)] *
         (mesh.nodes[static_cast<std::size_t>(node)] + Point2(u[dofX(node)], u[dofY(node)]));
  }
  return p;
}

}  // namespace needle_guidance::tissue
