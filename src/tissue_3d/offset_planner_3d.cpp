// Offset planning for rigid needles in 3-D (offset_planner_3d.h).
#include "needle_guidance/tissue_3d/offset_planner_3d.h"

#include <cmath>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/cpu_time.h"

namespace needle_guidance::tissue_3d {
namespace {

constexpr double kPathSample_m = 5e-4;  // needle line sampled for fixed regions at this spacing
constexpr int kMaxVerifications = 4;

std::string mm(double m) {
  std::ostringstream out;
  out.precision(3);
  out << std::fixed << m * 1e3 << " mm";
  return out.str();
}

}  // namespace

OffsetPlanner3::OffsetPlanner3(const TissueScene3d& scene, TissueModel3& model,
                               PlannerOptions3 options)
    : scene_(scene), model_(model), options_(options), regions_(scene) {}

std::string OffsetPlanner3::physicalRefusal(const Target3& t) const {
  const int r = regions_.regionAt(t.position_m);
  if (r == -2) {
    return "target outside the tissue block";
  }
  if (r >= 0 && scene_.regions[static_cast<std::size_t>(r)].fixed) {
    return "target inside fixed region '" + scene_.regions[static_cast<std::size_t>(r)].name +
           "' (" + mm(regions_.distanceToRegion(r, t.position_m)) + " from its surface)";
  }
  const double entry = scene_.block_min_m.x();
  for (double x = entry; x <= t.position_m.x(); x += kPathSample_m) {
    const int q = regions_.regionAt(Vector3(x, t.position_m.y(), t.position_m.z()));
    if (q >= 0 && scene_.regions[static_cast<std::size_t>(q)].fixed) {
      return "the needle line to the target crosses fixed region '" +
             scene_.regions[static_cast<std::size_t>(q)].name + "' at x = " + mm(x);
    }
  }
  return "";
}

OffsetPlanner3::Trajectory OffsetPlanner3::insertAlong(const Eigen::Vector2d& lateral,
                                                       double max_x) {
  NeedleInsertion3 needle(model_, scene_.needle, scene_.block_min_m.x(), max_x);
  Trajectory t;
  const double step = scene_.needle.insertion_velocity_m_s * scene_.needle.step_s;
  std::string why;
  for (double s = scene_.block_min_m.x(); s < max_x + 1e-12;) {
    s = std::min(s + step, max_x);
    if (!needle.moveTo(lateral, s, &why)) {
      throw std::runtime_error(why);
    }
    if (needle.punctured()) {
      t.s.push_back(s);
      t.tip.push_back(needle.tipReference());
    }
    if (s >= max_x) {
      break;
    }
  }
  return t;
}

Vector3 OffsetPlanner3::simulateImplant(const Eigen::Vector2d& lateral, double tip_x,
                                        double step_scale) {
  NeedleInsertion3 needle(model_, scene_.needle, scene_.block_min_m.x(), tip_x);
  const double step = scene_.needle.insertion_velocity_m_s * scene_.needle.step_s * step_scale;
  std::string why;
  const double start = scene_.block_min_m.x() - step;
  for (double s = start; s < tip_x;) {
    s = std::min(s + step, tip_x);
    if (!needle.moveTo(lateral, s, &why)) {
      throw std::runtime_error(why);
    }
  }
  const std::optional<int> seed = needle.implantSeed(&why);
  if (!seed) {
    throw std::runtime_error(why);
  }
  for (double s = tip_x; s > start;) {
    s = std::max(s - step, start);
    if (!needle.moveTo(lateral, s, &why)) {
      throw std::runtime_error(why);
    }
  }
  return needle.seedWorld(*seed);
}

PlanResult3 OffsetPlanner3::plan(const Target3& target) {
  const CpuStopwatch plan_clock(CpuStopwatch::Scope::kProcess);
  PlanResult3 r;
  r.target = target.name;
  const Vector3& goal = target.position_m;
  r.refusal = physicalRefusal(target);
  const Workspace3& w = scene_.workspace;
  double excluded_cpu = 0.0;
  auto finish = [&]() {
    r.plan_cpu_s = plan_clock.seconds() - excluded_cpu;
    return r;
  };
  if (!r.refusal.empty()) {
    r.unreachable = true;
    return finish();
  }
  try {
    if (options_.unplanned) {
      // For the report only: not part of planning, so not in plan_cpu_s.
      const CpuStopwatch unplanned_clock(CpuStopwatch::Scope::kProcess);
      const Vector3 seed = simulateImplant(goal.tail<2>(), goal.x());
      r.unplanned_error_m = (seed - goal).norm();
      excluded_cpu += unplanned_clock.seconds();
    }
    // Lateral and depth by fixed-point iteration on the simulated tip trajectory: the seed's
    // tissue point is the tip's at release.
    Eigen::Vector2d lateral = goal.tail<2>();
    double tip_x = goal.x();
    for (int it = 0; it < options_.max_iterations; ++it) {
      const Eigen::Vector2d reachable = w.nearest(lateral);
      if ((reachable - lateral).norm() > 1e-6) {
        if (!w.use_template) {
          r.refusal = "out of reach: the stage would need (y " + mm(lateral.x()) + ", z " +
                      mm(lateral.y()) + ")";
          r.unreachable = true;
          return finish();
        }
      }
      lateral = reachable;
      const Trajectory t = insertAlong(lateral, w.max_tip_x_m);
      ++r.simulations;
      std::size_t k = 0;
      while (k < t.tip.size() && t.tip[k].x() < goal.x()) {
        ++k;
      }
      if (k == t.tip.size()) {
        r.refusal = "out of reach: at the deepest tip x " + mm(w.max_tip_x_m) +
                    " the tip's tissue point is at x " +
                    mm(t.tip.empty() ? scene_.block_min_m.x() : t.tip.back().x()) +
                    ", short of the target's " + mm(goal.x());
        r.unreachable = true;
        return finish();
      }
      Vector3 predicted = t.tip[k];
      tip_x = t.s[k];
      if (k > 0) {
        const double a = (goal.x() - t.tip[k - 1].x()) / (t.tip[k].x() - t.tip[k - 1].x());
        predicted = t.tip[k - 1] + a * (t.tip[k] - t.tip[k - 1]);
        tip_x = t.s[k - 1] + a * (t.s[k] - t.s[k - 1]);
      }
      r.predicted_error_m = (predicted - goal).norm();
      if (w.use_template || r.predicted_error_m < options_.converge_m) {
        break;
      }
      lateral += goal.tail<2>() - predicted.tail<2>();
    }
    // Verification by independent full simulations, correcting depth and lateral by the
    // measured miss when it is above the tolerance's tenth.
    for (int v = 0; v < kMaxVerifications; ++v) {
      r.verified_seed_m = simulateImplant(lateral, tip_x);
      ++r.simulations;
      r.verified_error_m = (r.verified_seed_m - goal).norm();
      r.lateral_m = lateral;
      r.tip_x_m = tip_x;
      if (r.verified_error_m <= 0.1 * options_.tolerance_m) {
        break;
      }
      tip_x += goal.x() - r.verified_seed_m.x();
      if (!w.use_template) {
        lateral += goal.tail<2>() - r.verified_seed_m.tail<2>();
      }
      if (tip_x > w.max_tip_x_m || !w.reaches(lateral)) {
        break;
      }
    }
    r.placed = r.verified_error_m <= options_.tolerance_m;
    r.unreachable = !r.placed && w.use_template;  // the holes are where they are
    if (!r.placed) {
      r.refusal =
          w.use_template
              ? "no template hole places the seed within " + mm(options_.tolerance_m) +
                    ": nearest hole misses by " + mm(r.verified_error_m)
              : "verified miss " + mm(r.verified_error_m) + " above " + mm(options_.tolerance_m);
    }
  } catch (const std::runtime_error& e) {
    r.refusal = std::string("simulation refused: ") + e.what();
  }
  return finish();
}

}  // namespace needle_guidance::tissue_3d
