// One exact Bellman step from a continuous pose over the solved table (dissertation 5.4.2-5.4.3).
#include "needle_guidance/steering/exact_pose_prediction.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::steering {
namespace {

int wrapIndex(std::int64_t k, int n) {
  const std::int64_t r = k % n;
  return static_cast<int>(r < 0 ? r + n : r);
}

double normalCdf(double z) {
  return 0.5 * std::erfc(-z / std::sqrt(2.0));
}

/// Mass of N(0, sigma) on [lo, hi] in units of the orientation quantum; an end at +-infinity
/// is the folded tail.
double binMass(double lo, double hi, double alpha, double sigma, bool first, bool last) {
  const double a = first ? 0.0 : normalCdf(lo * alpha / sigma);
  const double b = last ? 1.0 : normalCdf(hi * alpha / sigma);
  return b - a;
}

}  // namespace

std::string PosePrediction::toString() const {
  std::ostringstream s;
  switch (status) {
    case ControlLookup::Status::kOk:
      s << "ok: " << steering::toString(control) << ", P_s = " << probability_of_success
        << " (insert " << control_ps[0] << ", flip " << control_ps[1] << ")";
      break;
    case ControlLookup::Status::kOutsideGrid:
      s << "outside grid";
      break;
    case ControlLookup::Status::kInTarget:
      s << "in target";
      break;
    case ControlLookup::Status::kInObstacle:
      s << "in obstacle";
      break;
  }
  return s.str();
}

ExactPosePrediction::ExactPosePrediction(const SteeringModel& model, const PolicyTable& table,
                                         PoseControl control)
    : model_(model),
      table_(table),
      mode_(control),
      world_(model.problem(), model.params().arc_chord_tolerance_m) {
  const GridSpec& a = model.grid();
  const GridSpec& b = table.grid();
  if (table.problemHash() != model.hash() || a.nx != b.nx || a.ny != b.ny || a.nc != b.nc) {
    throw std::invalid_argument(
        "ExactPosePrediction: the table was solved for another model (table grid " +
        std::to_string(b.nx) + " x " + std::to_string(b.ny) + " x " + std::to_string(b.nc) +
        ", model grid " + std::to_string(a.nx) + " x " + std::to_string(a.ny) + " x " +
        std::to_string(a.nc) + ")");
  }
}

ControlLookup::Status ExactPosePrediction::status(const TipPose& pose) const noexcept {
  const Point2& p = pose.p_SceneTip;
  if (!p.allFinite() || !std::isfinite(pose.theta_rad) || !world_.inWorkspace(p) ||
      table_.grid().nearestState(pose) < 0) {
    return ControlLookup::Status::kOutsideGrid;
  }
  if (world_.obstacleAt(p) >= 0) {
    return ControlLookup::Status::kInObstacle;
  }
  return world_.inTarget(p) ? ControlLookup::Status::kInTarget : ControlLookup::Status::kOk;
}

double ExactPosePrediction::controlPs(const TipPose& pose, Control u) const noexcept {
  switch (status(pose)) {
    case ControlLookup::Status::kOk:
      return stepPs(pose, u);
    case ControlLookup::Status::kInTarget:
      return 1.0;
    default:
      return 0.0;
  }
}

double ExactPosePrediction::stepPs(const TipPose& pose, Control u) const noexcept {
  const GridSpec& g = table_.grid();
  const StateId rounded = g.nearestState(pose);
  int qx = 0, qy = 0, qk = 0;
  Bevel qb = Bevel::kLeft;
  g.decode(rounded, qx, qy, qk, qb);
  const int nc = g.nc;
  const int s = model_.params().orientation_subdivision;
  const double alpha = g.alphaRad();
  const double delta = model_.arcLength_m();
  const bool interpolated = model_.transitionModel() == TransitionModel::kInterpolated;
  // Orientation offset of theta from its nearest model orientation, in orientation quanta.
  const double shift = pose.theta_rad / alpha - std::floor(pose.theta_rad / alpha + 0.5);

  const std::vector<double>& probs = model_.deflectionProbabilities(u);
  const int first = model_.firstDeflection(u);
  const int n = static_cast<int>(probs.size());
  const double sigma = model_.binSigma(u);
  const bool shifted = sigma > 0.0 && n < nc && shift != 0.0;  // a wrapped normal is not shifted
  const Bevel traced = u == Control::kInsert ? pose.bevel : flipped(pose.bevel);
  double total = 0.0, ps = 0.0;
  for (int i = 0; i < n; ++i) {
    const int d = first + i;
    double w = probs[static_cast<std::size_t>(i)];
    if (shifted) {
      // The model's bin (which keeps its variance correction) moved by the offset.
      const bool lo_end = i == 0, hi_end = i == n - 1;
      w += binMass(d - shift - 0.5, d - shift + 0.5, alpha, sigma, lo_end, hi_end) -
           binMass(d - 0.5, d + 0.5, alpha, sigma, lo_end, hi_end);
      w = std::max(0.0, w);
    }
    total += w;
    if (w == 0.0) {
      continue;
    }
    const int o = wrapIndex(static_cast<std::int64_t>(qk) + d, nc);
    const int o_next = wrapIndex(traced == Bevel::kLeft ? o + s : o - s, nc);
    TipPose from = pose;
    from.theta_rad = o * alpha;
    const ArcTrace arc = world_.traceArc(from, u, 0.0, delta);
    if (arc.outcome != ArcOutcome::kFree) {
      continue;
    }
    if (!interpolated) {
      const auto [dx, dy] = model_.arcDisplacement(static_cast<int>(traced) * nc + o);
      const int ex = qx + dx, ey = qy + dy;
      if (ex >= 0 && ex < g.nx && ey >= 0 && ey < g.ny) {
        ps += w * double(table_.value(g.state(ex, ey, o_next, traced)));
      }
      continue;
    }
    const Point2& end = arc.end.p_SceneTip;
    if (world_.inTarget(end)) {
      ps += w;
      continue;
    }
    const double fx = (end.x() - g.origin.x()) / g.spacing_m;
    const double fy = (end.y() - g.origin.y()) / g.spacing_m;
    const int ix = static_cast<int>(std::floor(fx)), iy = static_cast<int>(std::floor(fy));
    const double wx = fx - ix, wy = fy - iy;
    double kept = 0.0, value = 0.0;
    for (int corner = 0; corner < 4; ++corner) {
      const int cx = ix + (corner & 1), cy = iy + (corner >> 1);
      if (cx < 0 || cx >= g.nx || cy < 0 || cy >= g.ny ||
          table_.cell(g.position(cx, cy)) != Cell::kFree) {
        continue;
      }
      const double share = ((corner & 1) ? wx : 1.0 - wx) * ((corner >> 1) ? wy : 1.0 - wy);
      kept += share;
      value += share * double(table_.value(g.state(cx, cy, o_next, traced)));
    }
    if (kept > 0.0) {
      ps += w * value / kept;
    }
  }
  return total > 0.0 ? std::clamp(ps / total, 0.0, 1.0) : 0.0;
}

PosePrediction ExactPosePrediction::predict(const TipPose& pose) const noexcept {
  PosePrediction out;
  out.status = status(pose);
  if (out.status == ControlLookup::Status::kInTarget) {
    out.probability_of_success = 1.0;
  }
  if (out.status != ControlLookup::Status::kOk) {
    return out;
  }
  out.control_ps[0] = stepPs(pose, Control::kInsert);
  out.control_ps[1] = stepPs(pose, Control::kFlip);
  if (mode_ == PoseControl::kTable) {
    out.control = table_.lookup(pose).control;
  } else {
    out.control = out.control_ps[1] > out.control_ps[0] ? Control::kFlip : Control::kInsert;
  }
  out.probability_of_success = out.control_ps[static_cast<int>(out.control)];
  return out;
}

SteeringPolicy ExactPosePrediction::policy() const {
  if (mode_ == PoseControl::kTable) {
    return tablePolicy(table_);
  }
  return [this](const TipPose& pose, int) { return predict(pose).control; };
}

}  // namespace needle_guidance::steering
