#include <algorithm>
#include <cmath>
#include <deque>
#include <limits>
#include <random>

#include "dvh_model.h"
#include "needle_guidance/cpu_time.h"

namespace needle_guidance::dose::dvh_model {

double coveredPct(const PlanPoints& p, const VolumeCondition& v, const Eigen::VectorXd& dose) {
  const int first = p.first[static_cast<std::size_t>(v.structure)];
  double pct = 0.0;
  for (int i = first; i < first + p.count[static_cast<std::size_t>(v.structure)]; ++i)
    pct += (v.strict ? dose(i) > v.level_Gy : dose(i) >= v.level_Gy * (1.0 - 1e-9))
               ? p.pct[static_cast<std::size_t>(i)]
               : 0.0;
  return pct;
}

namespace {

/// Volume over (at most) or short of (at least) condition v's budget, given its covered %
/// (rounding of the volume sums, below 1e-9 points, is not a violation).
double slackOf(const VolumeCondition& v, double pct) {
  const double slack = v.at_most ? pct - v.budget_pct : v.budget_pct - pct;
  return slack > 1e-9 ? slack : 0.0;
}

}  // namespace

double violationPct(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
                    const Eigen::VectorXd& dose) {
  double sum = 0.0;
  for (std::size_t k = 0; k < conditions.size(); ++k) {
    if (k > 0 || conditions[k].budget_pct > 0.0)
      sum += slackOf(conditions[k], coveredPct(p, conditions[k], dose));
  }
  return sum;
}

double objectiveAt(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
                   const Eigen::VectorXd& dose, double total_s, double total_time_s,
                   const DvhPlanOptions& o) {
  if (total_s > total_time_s * (1.0 + 1e-9))
    return std::numeric_limits<double>::infinity();
  return 1e-6 / static_cast<double>(p.d.cols()) * total_s - coveredPct(p, conditions[0], dose) +
         o.violation_penalty * violationPct(p, conditions, dose);
}

namespace {

/// A plan's standing: total violation first (so a plan meeting every criterion beats any that
/// breaks one, however much more it covers), then the objective.
struct Score {
  double violation = std::numeric_limits<double>::infinity();
  double objective = std::numeric_limits<double>::infinity();
  /// Better than b, by more than `by` on the objective when the violations tie.
  bool beats(const Score& b, double by = 0.0) const {
    if (violation < b.violation - 1e-9)
      return true;
    return violation <= b.violation + 1e-9 && objective < b.objective - by;
  }
};

Score scoreOf(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
              const Eigen::VectorXd& dose, double total_s, double total_time_s,
              const DvhPlanOptions& o) {
  return {violationPct(p, conditions, dose),
          objectiveAt(p, conditions, dose, total_s, total_time_s, o)};
}

/// The penalty of one condition at point doses d, with its gradient added into coef (per point):
/// at most, the points at or above `level` beyond the hottest `budget` % are pushed down to it;
/// at least, the hottest points below `level` that make up the shortfall are pushed up to it.
/// Each pushed point costs weight * pct * ((d - level) / level)^2.
double penalty(const PlanPoints& p, const VolumeCondition& v, double level, double budget,
               double weight, const Eigen::VectorXd& d, Eigen::VectorXd* coef,
               std::vector<int>* order) {
  const int first = p.first[static_cast<std::size_t>(v.structure)];
  const int count = p.count[static_cast<std::size_t>(v.structure)];
  order->clear();
  double above = 0.0;
  for (int i = first; i < first + count; ++i) {
    const bool hot = d(i) >= level;
    above += hot ? p.pct[static_cast<std::size_t>(i)] : 0.0;
    if (hot == v.at_most)
      order->push_back(i);
  }
  if (v.at_most ? above <= budget : above >= budget)
    return 0.0;
  std::sort(order->begin(), order->end(), [&](int a, int b) { return d(a) > d(b); });
  const double scale = weight / (level * level);
  double value = 0.0, cumulative = v.at_most ? 0.0 : above;
  for (const int i : *order) {
    const double w = p.pct[static_cast<std::size_t>(i)];
    if (!v.at_most && cumulative >= budget)
      break;
    cumulative += w;
    if (v.at_most && cumulative <= budget)
      continue;
    const double diff = d(i) - level;
    value += scale * w * diff * diff;
    (*coef)(i) += 2.0 * scale * w * diff;
  }
  return value;
}

/// The descent's surrogate: every condition at its level moved by the margin towards the safe
/// side (weight violation_penalty), and target coverage of `goal` % (weight 1).
struct Surrogate {
  const PlanPoints& p;
  /// p.d row by row: D t as one dot product per point (the column-major product streams the
  /// dose vector once per dwell and took 2.5x the time of the transposed one).
  Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> rows;
  const std::vector<VolumeCondition>& conditions;
  double margin = 0.0, weight = 0.0, goal = 0.0;
  mutable Eigen::VectorXd coef;
  mutable std::vector<int> order;

  double level(const VolumeCondition& v) const {
    return v.level_Gy * (v.at_most ? 1.0 - margin : 1.0 + margin);
  }
  /// F(t); d = D t and g = dF/dt.
  double operator()(const Eigen::VectorXd& t, Eigen::VectorXd* d, Eigen::VectorXd* g) const {
    d->noalias() = rows * t;
    coef.setZero(p.d.rows());
    double f = 0.0;
    for (std::size_t k = 0; k < conditions.size(); ++k) {
      const VolumeCondition& v = conditions[k];
      if (k > 0 || v.budget_pct > 0.0)
        f += penalty(p, v, level(v), v.budget_pct, weight, *d, &coef, &order);
      if (k == 0 && goal > v.budget_pct)
        f += penalty(p, v, level(v), goal, 1.0, *d, &coef, &order);
    }
    g->noalias() = p.d.transpose() * coef;
    return f;
  }
};

/// The best start on the exact objective, each start scaled by 0.7-1.5 (doses scale with it).
Eigen::VectorXd bestStart(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
                          double total_time_s, const std::vector<std::vector<double>>& starts,
                          const DvhPlanOptions& o, Score* best) {
  Eigen::VectorXd out;
  *best = Score{};
  for (const std::vector<double>& s : starts) {
    if (static_cast<Eigen::Index>(s.size()) != p.d.cols())
      continue;
    const Eigen::VectorXd t = Eigen::Map<const Eigen::VectorXd>(s.data(), p.d.cols());
    if (!t.allFinite() || (t.array() < 0.0).any() || !(t.sum() > 0.0))
      continue;
    const Eigen::VectorXd d = p.d * t;
    for (int percent = 70; percent <= 150; ++percent) {  // 100: the start itself, exactly
      const double scale = percent / 100.0;
      const Score value = scoreOf(p, conditions, scale * d, scale * t.sum(), total_time_s, o);
      if (value.beats(*best)) {
        *best = value;
        out = scale * t;
      }
    }
  }
  return out;
}

}  // namespace

DescentResult descendOnCriteria(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
                                double total_time_s, const std::vector<std::vector<double>>& starts,
                                const DvhPlanOptions& o, double seconds) {
  const CpuStopwatch cpu(CpuStopwatch::Scope::kProcess);
  DescentResult r;
  Score best;
  Eigen::VectorXd best_t = bestStart(p, conditions, total_time_s, starts, o, &best);
  r.start_objective = best.objective;
  if (best_t.size() == 0)
    return r;
  Surrogate f{p, p.d, conditions, o.descent_level_margin, o.violation_penalty, 0.0, {}, {}};
  double step = o.descent_goal_step_pp;
  const auto coverage = [&](const Eigen::VectorXd& d) { return coveredPct(p, conditions[0], d); };
  Eigen::VectorXd t = best_t, d, g, t_new, d_new, g_new;
  f.goal = std::max(conditions[0].budget_pct, coverage(p.d * t) + step);
  double value = f(t, &d, &g);
  double alpha = 0.05 * std::max(t.mean(), 1e-9) / std::max(g.cwiseAbs().maxCoeff(), 1e-300);
  std::deque<double> recent{value};
  int stalled = 0, shakes = 0;
  constexpr int kShakes = 8;
  std::mt19937 rng(1);
  while (cpu.seconds() < seconds) {
    double value_new = value;
    for (int tries = 0; tries < 30; ++tries) {
      t_new = (t - alpha * g).cwiseMax(0.0);
      value_new = f(t_new, &d_new, &g_new);
      const double worst = *std::max_element(recent.begin(), recent.end());
      if (value_new <= worst - 1e-4 * g.dot(t - t_new))
        break;
      alpha *= 0.5;
    }
    ++r.iterations;
    const Score exact = scoreOf(p, conditions, d_new, t_new.sum(), total_time_s, o);
    // Progress: a better plan by a fifth of the smallest goal step (smaller gains are kept
    // but do not hold off the goal's drop).
    stalled = exact.beats(best, 0.2 * o.descent_min_step_pp) ? 0 : stalled + 1;
    if (exact.beats(best)) {
      best = exact;
      best_t = t_new;
    }
    const double covered = coverage(d_new);
    if (exact.violation <= 0.0 && covered >= f.goal - 0.5 * step)
      f.goal = covered + step;  // reached: ask for more
    // Barzilai-Borwein step length for the next iteration.
    const Eigen::VectorXd s = t_new - t, y = g_new - g;
    const double sy = s.dot(y);
    alpha = sy > 1e-300 ? s.squaredNorm() / sy : 2.0 * alpha;
    t.swap(t_new);
    d.swap(d_new);
    g.swap(g_new);
    value = value_new;
    recent.push_back(value);
    if (recent.size() > 8)
      recent.pop_front();
    if (stalled >= o.descent_patience) {
      // The goal is out of reach from here: ask for less, from the best plan. Below the
      // smallest step, the descent has settled in a local optimum of the step-function indices:
      // with time left, it starts again from the best plan with every dwell time scaled by a
      // seeded factor in [0.5, 1.5] and the first goal step (at most kShakes times).
      step *= 0.5;
      t = best_t;
      if (step < o.descent_min_step_pp) {
        if (++shakes > kShakes)
          break;
        step = o.descent_goal_step_pp;
        std::uniform_real_distribution<double> factor(0.5, 1.5);
        for (Eigen::Index i = 0; i < t.size(); ++i)
          t[i] *= factor(rng);
      }
      ++r.restarts;
      f.goal = std::max(conditions[0].budget_pct, coverage(p.d * t) + step);
      value = f(t, &d, &g);
      recent.assign(1, value);
      alpha = 0.05 * std::max(t.mean(), 1e-9) / std::max(g.cwiseAbs().maxCoeff(), 1e-300);
      stalled = 0;
    }
  }
  r.times_s.assign(best_t.data(), best_t.data() + best_t.size());
  r.objective = best.objective;
  return r;
}

}  // namespace needle_guidance::dose::dvh_model
