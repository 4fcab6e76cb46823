// Offset planning for rigid needles in 3-D (offset_planner_3d.h).
#include "needle_guidance/tissue_3d/offset_planner_3d.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/cpu_time.h"

namespace needle_guidance::tissue_3d {
namespace {

constexpr double kPathSample_m = 5e-4;  // needle line sampled for fixed regions at this spacing
constexpr int kMaxVerifications = 4;
constexpr int kMaxHoles = 3;  // template holes verified per target, the nearest included

/// The x of the tip's tissue point; before puncture the tip pins the entry point, entry_x [m].
double tissuePointX(const NeedleInsertion3& n, double entry_x) {
  return n.punctured() ? n.tipReference().x() : entry_x;
}

std::string mm(double m) {
  std::ostringstream out;
  out.precision(3);
  out << std::fixed << m * 1e3 << " mm";
  return out.str();
}

/// The reach refusal on a template: no hole lands within the tolerance; the nearest hole (row,
/// column, y, z) and its verified miss, and the best other hole verified.
/// nearest_predicted_m: the nearest hole's predicted miss, said when it was not verified.
std::string templateRefusal(const Workspace3& w, const PlanResult3& r, double tolerance_m,
                            double nearest_predicted_m = -1.0) {
  auto name = [&](const Eigen::Vector2i& k) {
    const Eigen::Vector2d p = w.hole(k.x(), k.y());
    return "row " + std::to_string(k.x()) + ", column " + std::to_string(k.y()) + " (y " +
           mm(p.x()) + ", z " + mm(p.y()) + ")";
  };
  std::string why =
      "out of reach: no template hole places the seed within " + mm(tolerance_m) +
      "; the nearest hole, " + name(r.nearest_hole) +
      (r.nearest_hole_error_m >= 0.0
           ? ", misses by " + mm(r.nearest_hole_error_m) + " (verified)"
           : ", is predicted to miss by " + mm(nearest_predicted_m) + " (not verified)");
  if (r.hole != r.nearest_hole) {
    why += "; the best of " + std::to_string(r.holes_verified) + " holes verified, " +
           name(r.hole) + ", by " + mm(r.verified_error_m);
  }
  return why;
}

/// Releases a seed at the tip and withdraws the needle to out_x: the seed's final position. The
/// retraction is one move: its events (track points released, stick and slip) are located
/// within it, and once the needle is out the elastic tissue is at rest, so the seed lies at its
/// tissue point however the retraction is cut into moves. Throws std::runtime_error when the
/// simulation refuses.
Vector3 releaseAndRetract(NeedleInsertion3& needle, const Eigen::Vector2d& lateral, double out_x) {
  std::string why;
  const std::optional<int> seed = needle.implantSeed(&why);
  if (!seed) {
    throw std::runtime_error(why);
  }
  if (!needle.moveTo(lateral, out_x, &why)) {
    throw std::runtime_error(why);
  }
  return needle.seedWorld(*seed);
}

/// Inserts needle at lateral by moves of long_move from a step before the entry face until its
/// tip's tissue point reaches the stop (stopAtTissueX) or the tip the deepest position max_x;
/// returns the moves. Nothing reads a move's end but the next move, whose events do not depend
/// on it: every move is a transit (passTo: its end's warp not settled), the one that reaches
/// the stop ends there on the warp settled at the stop, and the one to max_x is settled (the
/// figures of a refusal). Throws std::runtime_error when the simulation refuses.
int insertToStop(NeedleInsertion3& needle, const Eigen::Vector2d& lateral, double start_x,
                 double long_move, double max_x) {
  std::string why;
  int moves = 0;
  for (double s = start_x; s < max_x && !needle.lastMove().stopped; ++moves) {
    s = std::min(s + long_move, max_x);
    if (!(s >= max_x ? needle.moveTo(lateral, s, &why) : needle.passTo(lateral, s, &why))) {
      throw std::runtime_error(why);
    }
  }
  return moves;
}

}  // namespace

OffsetPlanner3::OffsetPlanner3(const TissueScene3d& scene, TissueModel3& model,
                               PlannerOptions3 options)
    : scene_(scene), model_(model), options_(options), regions_(scene) {
  if (!(options_.corotational_accept_fraction > 0.0 &&
        options_.corotational_accept_fraction <= 1.0)) {
    throw std::invalid_argument(
        "OffsetPlanner3: corotational_accept_fraction must be in (0, 1], not " +
        std::to_string(options_.corotational_accept_fraction));
  }
  if (!(options_.corotational_event_tolerance_fraction > 0.0 &&
        options_.corotational_event_tolerance_fraction <= options_.corotational_accept_fraction)) {
    throw std::invalid_argument(
        "OffsetPlanner3: corotational_event_tolerance_fraction must be in (0, "
        "corotational_accept_fraction], not " +
        std::to_string(options_.corotational_event_tolerance_fraction));
  }
  if (options_.max_corotational_insertions < 1) {
    throw std::invalid_argument("OffsetPlanner3: max_corotational_insertions must be >= 1, not " +
                                std::to_string(options_.max_corotational_insertions));
  }
  if (!(options_.corotational_step_scale > 0.0 &&
        std::isfinite(options_.corotational_step_scale))) {
    throw std::invalid_argument("OffsetPlanner3: corotational_step_scale must be > 0, not " +
                                std::to_string(options_.corotational_step_scale));
  }
  linear_start_ =
      model_.corotational() && !scene_.workspace.use_template && scene_.needle.follow_tissue;
}

OffsetPlanner3::~OffsetPlanner3() = default;

std::string OffsetPlanner3::physicalRefusal(const Target3& t) const {
  const int r = regions_.regionAt(t.position_m);
  if (r == -2) {
    return "target outside the tissue block";
  }
  if (r >= 0 && scene_.regions[static_cast<std::size_t>(r)].fixed) {
    return "target inside fixed region '" + scene_.regions[static_cast<std::size_t>(r)].name +
           "' (" + mm(regions_.distanceToRegion(r, t.position_m)) + " from its surface)";
  }
  const std::string fixed = fixedRegionOnLine(t.position_m.tail<2>(), t.position_m.x());
  return fixed.empty() ? "" : "the needle line to the target crosses " + fixed;
}

std::string OffsetPlanner3::fixedRegionOnLine(const Eigen::Vector2d& lateral, double tip_x) const {
  for (double x = scene_.block_min_m.x(); x <= tip_x; x += kPathSample_m) {
    const int q = regions_.regionAt(Vector3(x, lateral.x(), lateral.y()));
    if (q >= 0 && scene_.regions[static_cast<std::size_t>(q)].fixed) {
      return "fixed region '" + scene_.regions[static_cast<std::size_t>(q)].name +
             "' at x = " + mm(x);
    }
  }
  return "";
}

OffsetPlanner3::Trajectory OffsetPlanner3::insertAlong(TissueModel3& model,
                                                       const Eigen::Vector2d& lateral, double max_x,
                                                       double stop_x) {
  NeedleInsertion3 needle(model, scene_.needle, scene_.block_min_m.x(), max_x);
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
    if (s >= max_x || (!t.tip.empty() && t.tip.back().x() >= stop_x)) {
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
  return releaseAndRetract(needle, lateral, start);
}

bool OffsetPlanner3::predict(TissueModel3& model, const Vector3& goal, Eigen::Vector2d& lateral,
                             double& tip_x, PlanResult3& r, int& simulations, int max_iterations) {
  // Fixed-point iteration on the simulated tip trajectory: the seed's tissue point is the tip's
  // at release. On a template the hole is given and only the depth is predicted.
  const Workspace3& w = scene_.workspace;
  for (int it = 0; it < max_iterations; ++it) {
    const Eigen::Vector2d reachable = w.nearest(lateral);
    if (!w.use_template && (reachable - lateral).norm() > 1e-6) {
      r.refusal = "out of reach: the stage would need (y " + mm(lateral.x()) + ", z " +
                  mm(lateral.y()) + ")";
      return false;
    }
    lateral = reachable;
    const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
    const Trajectory t = insertAlong(model, lateral, w.max_tip_x_m, goal.x());
    ++simulations;
    if (&model == &model_) {
      r.simulation_cpu_s += clock.seconds();
    }
    std::size_t k = 0;
    while (k < t.tip.size() && t.tip[k].x() < goal.x()) {
      ++k;
    }
    if (k == t.tip.size()) {
      r.refusal = "out of reach: at the deepest tip x " + mm(w.max_tip_x_m) +
                  " the tip's tissue point is at x " +
                  mm(t.tip.empty() ? scene_.block_min_m.x() : t.tip.back().x()) +
                  ", short of the target's " + mm(goal.x());
      return false;
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
  return true;
}

OffsetPlanner3::Attempt OffsetPlanner3::insertToGoal(const Vector3& goal,
                                                     const Eigen::Vector2d& lateral,
                                                     double step_scale, PlanResult3& r) {
  // The needle goes in by long moves (step_scale x the scene's step: the answer does not depend
  // on the move length, as the events are located within each move) and stops where the tip's
  // tissue point reaches the goal's x (EmbeddedNeedle::stopAtTissueX, located within its move
  // like a track point, on the warp settled there). From there the seed is released and the
  // needle withdrawn: an insertion to that depth, the verification.
  const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
  const Workspace3& w = scene_.workspace;
  const double x0 = scene_.block_min_m.x();
  const double step = scene_.needle.insertion_velocity_m_s * scene_.needle.step_s;
  const double long_move = step * step_scale;
  ++r.simulations;
  NeedleInsertion3 needle(model_, scene_.needle, x0, w.max_tip_x_m,
                          options_.corotational_event_tolerance_fraction * options_.tolerance_m);
  needle.stopAtTissueX(goal.x());
  r.corotational_moves += insertToStop(needle, lateral, x0 - step, long_move, w.max_tip_x_m);
  if (!needle.lastMove().stopped) {
    r.refusal = "out of reach: at the deepest tip x " + mm(w.max_tip_x_m) +
                " the tip's tissue point is at x " + mm(tissuePointX(needle, x0)) +
                ", short of the target's " + mm(goal.x());
    r.simulation_cpu_s += clock.seconds();
    return {};
  }
  Attempt a{lateral, needle.tipX(), releaseAndRetract(needle, lateral, x0 - step), 0.0};
  ++r.corotational_moves;
  a.error = (a.seed - goal).norm();
  r.simulation_cpu_s += clock.seconds();
  return a;
}

Eigen::Vector2d OffsetPlanner3::linearStart(TissueModel3& linear, const Vector3& goal,
                                            const Eigen::Vector2d& lateral, PlanResult3& r) {
  // One insertion in the linear model by the corotational insertion's long moves, stopped where
  // the tip's tissue point reaches the goal's x; the lateral position moves by the tissue
  // point's lateral miss there. Where the linear model does not reach the goal, the lateral
  // position stays.
  const Workspace3& w = scene_.workspace;
  const double x0 = scene_.block_min_m.x();
  const double step = scene_.needle.insertion_velocity_m_s * scene_.needle.step_s;
  const double long_move = step * options_.corotational_step_scale;
  ++r.linear_simulations;
  NeedleInsertion3 needle(linear, scene_.needle, x0, w.max_tip_x_m);
  if (&linear == &model_) {
    needle.useLinearModel();
  }
  needle.stopAtTissueX(goal.x());
  insertToStop(needle, lateral, x0 - step, long_move, w.max_tip_x_m);
  if (!needle.lastMove().stopped) {
    return lateral;
  }
  return w.nearest(lateral + goal.tail<2>() - needle.tipReference().tail<2>());
}

bool OffsetPlanner3::planCorotational(const Vector3& goal, Eigen::Vector2d lateral, Attempt& plan,
                                      PlanResult3& r) {
  // The start: on a stage with a followed track the linear model's lateral position (the track's
  // drift corrected; where the linear model cannot reach, the corotational insertion decides);
  // on the rest line the target's own; on a template the nearest hole, whose verified seed then
  // gives the drift that ranks the other holes (a seed moves with its hole one to one).
  const Workspace3& w = scene_.workspace;
  if (linear_start_) {
    // One linear insertion: the lateral position moves by its drift (the drift changes little
    // over that shift, and the corotational insertion measures what remains). It runs in the
    // scene's tissue seen as linear, on the factor and compliance columns the corotational
    // insertion then uses, while that tissue's reference is still the linear stiffness; once a
    // corotational insertion has re-warped it, in a linear model of the same mesh (assembled
    // and factored once, as set-up: setupCpuSeconds, not plan CPU).
    TissueModel3* linear = &model_;
    if (model_.embedding().referenceVersion() != 0) {
      if (!linear_) {
        const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
        linear_ = std::make_unique<TissueModel3>(model_.mesh(), scene_.materialTable(), false);
        const double setup = clock.seconds();
        setup_cpu_s_ += setup;
        setup_in_plan_cpu_s_ += setup;
      }
      linear = linear_.get();
    }
    lateral = linearStart(*linear, goal, w.nearest(lateral), r);
    r.predicted_error_m = -1.0;  // the corotational insertion predicts and verifies at once
  }
  double step_scale = options_.corotational_step_scale;
  return insertUntilPlaced(goal, lateral, step_scale, plan, r);
}

bool OffsetPlanner3::insertUntilPlaced(const Vector3& goal, Eigen::Vector2d lateral,
                                       double& step_scale, Attempt& plan, PlanResult3& r) {
  // Corotational insertions from lateral: the depth found and verified by each, the needle
  // moved by the miss (another hole on a template) until the seed lands within the acceptance.
  const Workspace3& w = scene_.workspace;
  const double accept = options_.corotational_accept_fraction * options_.tolerance_m;
  std::vector<Eigen::Vector2i> tried;
  Eigen::Vector2d drift = Eigen::Vector2d::Zero();
  for (int k = 0; k < options_.max_corotational_insertions; ++k) {
    if (w.use_template && k > 0) {
      // The untried hole whose seed is predicted closest, if it beats the best verified seed
      // by a tenth of the tolerance.
      const Eigen::Vector2i centre = w.holeIndex(goal.tail<2>() - drift);
      auto miss = [&](const Eigen::Vector2i& h) {
        return (w.hole(h.x(), h.y()) + drift - goal.tail<2>()).norm();
      };
      std::optional<Eigen::Vector2i> next;
      for (int i = std::max(0, centre.x() - 1); i <= std::min(w.template_rows - 1, centre.x() + 1);
           ++i) {
        for (int j = std::max(0, centre.y() - 1);
             j <= std::min(w.template_columns - 1, centre.y() + 1); ++j) {
          const Eigen::Vector2i h(i, j);
          if (std::find(tried.begin(), tried.end(), h) == tried.end() &&
              (!next || miss(h) < miss(*next)) &&
              fixedRegionOnLine(w.hole(i, j), goal.x()).empty()) {
            next = h;
          }
        }
      }
      if (!next || miss(*next) >= plan.error - 0.1 * options_.tolerance_m) {
        break;
      }
      lateral = w.hole(next->x(), next->y());
    }
    Attempt a;
    try {
      a = insertToGoal(goal, lateral, step_scale, r);
    } catch (const std::runtime_error&) {
      if (step_scale == 1.0) {
        throw;
      }
      step_scale = 1.0;  // refused at the planner's longer moves: the scene's step decides
      a = insertToGoal(goal, lateral, step_scale, r);
    }
    if (a.error < 0.0) {
      if (plan.error >= 0.0) {
        r.refusal.clear();  // an earlier insertion reached: its verified miss is the answer
        break;
      }
      return false;
    }
    if (w.use_template) {
      tried.push_back(w.holeIndex(a.lateral));
      ++r.holes_verified;
      if (k == 0) {
        r.nearest_hole_error_m = a.error;
      }
      drift = a.seed.tail<2>() - a.lateral;
    }
    if (plan.error < 0.0 || a.error < plan.error) {
      plan = a;
      r.hole = w.use_template ? tried.back() : r.hole;
    }
    if (plan.error <= accept) {
      break;
    }
    if (!w.use_template) {
      lateral = a.lateral + goal.tail<2>() - a.seed.tail<2>();
      if (!w.reaches(lateral)) {
        break;  // the verified miss of the best insertion stands
      }
    }
  }
  return true;
}

OffsetPlanner3::Attempt OffsetPlanner3::verify(const Vector3& goal, Eigen::Vector2d lateral,
                                               double tip_x, bool move_lateral, PlanResult3& r) {
  // Independent full simulations, correcting the depth (and the lateral position) by the
  // measured miss while it is above the tolerance's tenth. A hole whose seed misses laterally
  // by more than the tolerance cannot be corrected by the depth: one simulation measures it.
  const Workspace3& w = scene_.workspace;
  Attempt best;
  for (int v = 0; v < kMaxVerifications; ++v) {
    const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
    Attempt a{lateral, tip_x, simulateImplant(lateral, tip_x), 0.0};
    ++r.simulations;
    r.simulation_cpu_s += clock.seconds();
    a.error = (a.seed - goal).norm();
    if (best.error < 0.0 || a.error < best.error) {
      best = a;
    }
    const double lateral_miss = (a.seed.tail<2>() - goal.tail<2>()).norm();
    const double depth_miss = std::abs(goal.x() - a.seed.x());
    if (a.error <= 0.1 * options_.tolerance_m ||
        (!move_lateral &&
         (lateral_miss > options_.tolerance_m || depth_miss <= 0.1 * options_.tolerance_m))) {
      break;
    }
    tip_x += goal.x() - a.seed.x();
    if (move_lateral) {
      lateral += goal.tail<2>() - a.seed.tail<2>();
    }
    if (tip_x > w.max_tip_x_m || !w.reaches(lateral)) {
      break;
    }
  }
  return best;
}

OffsetPlanner3::Attempt OffsetPlanner3::bestHole(const Vector3& goal, const Attempt& nearest,
                                                 PlanResult3& r) {
  // Lateral sensitivity: a seed moves with its hole one to one, so every hole's seed is
  // predicted at the hole plus the nearest hole's measured offset (the track's drift). Holes
  // predicted to land within the tolerance (plus half the drift, its change between nearby
  // holes) and closer than the best verified seed by a tenth of the tolerance are verified,
  // best predicted first, at most kMaxHoles in all.
  const Workspace3& w = scene_.workspace;
  const Eigen::Vector2d drift = nearest.seed.tail<2>() - nearest.lateral;
  const Eigen::Vector2i centre = w.holeIndex(goal.tail<2>() - drift);
  const int reach =
      1 + static_cast<int>(std::ceil((drift.norm() + options_.tolerance_m) / w.template_spacing_m));
  std::vector<std::pair<double, Eigen::Vector2i>> candidates;
  for (int i = std::max(0, centre.x() - reach);
       i <= std::min(w.template_rows - 1, centre.x() + reach); ++i) {
    for (int j = std::max(0, centre.y() - reach);
         j <= std::min(w.template_columns - 1, centre.y() + reach); ++j) {
      const double e = (w.hole(i, j) + drift - goal.tail<2>()).norm();
      if (Eigen::Vector2i(i, j) != r.nearest_hole &&
          e <= options_.tolerance_m + 0.5 * drift.norm()) {
        candidates.emplace_back(e, Eigen::Vector2i(i, j));
      }
    }
  }
  std::sort(candidates.begin(), candidates.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  Attempt best = nearest;
  for (const auto& [predicted, hole] : candidates) {
    if (r.holes_verified >= kMaxHoles || best.error <= 0.1 * options_.tolerance_m ||
        predicted >= best.error - 0.1 * options_.tolerance_m) {
      break;
    }
    const Eigen::Vector2d lateral = w.hole(hole.x(), hole.y());
    if (!fixedRegionOnLine(lateral, best.tip_x).empty()) {
      continue;
    }
    Attempt a;
    try {
      a = verify(goal, lateral, best.tip_x, false, r);
    } catch (const std::runtime_error&) {
      continue;  // this hole's insertion was refused; the holes verified so far stand
    }
    ++r.holes_verified;
    if (a.error >= 0.0 && a.error < best.error) {
      best = a;
      r.hole = hole;
    }
  }
  return best;
}

PlanResult3 OffsetPlanner3::plan(const Target3& target) {
  const CpuStopwatch plan_clock(CpuStopwatch::Scope::kProcess);
  PlanResult3 r;
  r.target = target.name;
  const Vector3& goal = target.position_m;
  r.refusal = physicalRefusal(target);
  const Workspace3& w = scene_.workspace;
  double excluded_cpu = 0.0;
  setup_in_plan_cpu_s_ = 0.0;
  auto finish = [&]() {
    r.plan_cpu_s = plan_clock.seconds() - excluded_cpu - setup_in_plan_cpu_s_;
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
    Eigen::Vector2d lateral = goal.tail<2>();
    double tip_x = goal.x();
    if (w.use_template) {
      r.nearest_hole = r.hole = w.holeIndex(goal.tail<2>());
      lateral = w.hole(r.hole.x(), r.hole.y());
      const std::string fixed = fixedRegionOnLine(lateral, goal.x());
      if (!fixed.empty()) {
        r.refusal = "out of reach: the nearest template hole's needle line crosses " + fixed;
        r.unreachable = true;
        return finish();
      }
    }
    Attempt plan;
    if (model_.corotational()) {
      if (!planCorotational(goal, lateral, plan, r)) {
        r.unreachable = true;
        return finish();
      }
    } else {
      if (!predict(model_, goal, lateral, tip_x, r, r.simulations, options_.max_iterations)) {
        r.unreachable = true;
        return finish();
      }
      plan = verify(goal, lateral, tip_x, !w.use_template, r);
      if (w.use_template) {
        r.holes_verified = 1;
        r.nearest_hole_error_m = plan.error;
        plan = bestHole(goal, plan, r);
      }
    }
    r.lateral_m = plan.lateral;
    r.tip_x_m = plan.tip_x;
    r.verified_seed_m = plan.seed;
    r.verified_error_m = plan.error;
    r.placed = r.verified_error_m <= options_.tolerance_m;
    r.unreachable = !r.placed && w.use_template;  // the holes are where they are
    if (!r.placed) {
      // An unverified nearest hole (corotational tissue, another hole ranked first): its miss
      // predicted with the best hole's drift.
      const double nearest_predicted = w.use_template
                                           ? (w.hole(r.nearest_hole.x(), r.nearest_hole.y()) +
                                              plan.seed.tail<2>() - plan.lateral - goal.tail<2>())
                                                 .norm()
                                           : -1.0;
      r.refusal = w.use_template ? templateRefusal(w, r, options_.tolerance_m, nearest_predicted)
                                 : "verified miss " + mm(r.verified_error_m) + " above " +
                                       mm(options_.tolerance_m);
    }
  } catch (const std::runtime_error& e) {
    r.refusal = std::string("simulation refused: ") + e.what();
  }
  return finish();
}

}  // namespace needle_guidance::tissue_3d
