#include "needle_guidance/dose/dwell_optimization.h"

#include <ClpSimplex.hpp>
#include <CoinPackedMatrix.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <random>
#include <stdexcept>

namespace needle_guidance::dose {
namespace {

using Clock = std::chrono::steady_clock;
/// Default starting temperature as a fraction of the starting objective: measured on the cohort
/// (bench hdr), 10 % leaves a 10-100 % gap after 100,000 moves, 0.2 % a 0.1-2.4 % gap.
constexpr double kDefaultT0Fraction = 0.002;

double since(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

void checkSizes(const HdrCase& c, const Eigen::MatrixXd& d, const char* who) {
  if (c.dwells.empty()) {
    throw std::invalid_argument(std::string(who) + ": case '" + c.name +
                                "' has no active dwell positions");
  }
  if (d.rows() != static_cast<Eigen::Index>(c.points.size()) ||
      d.cols() != static_cast<Eigen::Index>(c.dwells.size())) {
    throw std::invalid_argument(
        std::string(who) + ": dose-rate matrix is " + std::to_string(d.rows()) + " x " +
        std::to_string(d.cols()) + ", the case has " + std::to_string(c.points.size()) +
        " points and " + std::to_string(c.dwells.size()) + " dwell positions");
  }
  if (!d.allFinite() || d.minCoeff() < 0.0) {
    throw std::invalid_argument(std::string(who) +
                                ": dose-rate matrix has a negative or non-finite entry");
  }
}

/// Per-point penalty of dose D.
inline double pointPenalty(const PenaltyModel& m, Eigen::Index i, double dose) {
  if (dose < m.lo[i])
    return m.w_under[i] * (m.lo[i] - dose);
  if (dose > m.hi[i])
    return m.w_over[i] * (dose - m.hi[i]);
  return 0.0;
}

/// The LP of optimizeLp as a Clp model.
void buildLp(const Eigen::MatrixXd& d, const PenaltyModel& pm, ClpSimplex& model) {
  const int m = static_cast<int>(d.rows());
  const int n = static_cast<int>(d.cols());
  const double inf = COIN_DBL_MAX;
  std::vector<double> row_lo(m), row_hi(m);
  std::vector<int> starts{0}, rows;
  std::vector<double> values, col_lo, col_hi, cost;
  // Dwell-time columns: the dose-rate columns (entries below 1e-12 of the column max dropped).
  for (int j = 0; j < n; ++j) {
    const double cutoff = 1e-12 * d.col(j).maxCoeff();
    for (int i = 0; i < m; ++i) {
      if (d(i, j) > cutoff) {
        rows.push_back(i);
        values.push_back(d(i, j));
      }
    }
    starts.push_back(static_cast<int>(rows.size()));
    col_lo.push_back(0.0);
    col_hi.push_back(inf);
    cost.push_back(0.0);
  }
  // Under- and overdose columns, one per point that has a weight for it.
  for (int i = 0; i < m; ++i) {
    row_lo[i] = pm.w_under[i] > 0.0 ? pm.lo[i] : -inf;
    row_hi[i] = pm.w_over[i] > 0.0 ? pm.hi[i] : inf;
    if (pm.w_under[i] > 0.0) {
      rows.push_back(i);
      values.push_back(1.0);
      starts.push_back(static_cast<int>(rows.size()));
      col_lo.push_back(0.0);
      col_hi.push_back(inf);
      cost.push_back(pm.w_under[i]);
    }
    if (pm.w_over[i] > 0.0) {
      rows.push_back(i);
      values.push_back(-1.0);
      starts.push_back(static_cast<int>(rows.size()));
      col_lo.push_back(0.0);
      col_hi.push_back(inf);
      cost.push_back(pm.w_over[i]);
    }
  }
  const int columns = static_cast<int>(cost.size());
  std::vector<int> lengths(columns);
  for (int k = 0; k < columns; ++k) {
    lengths[k] = starts[k + 1] - starts[k];
  }
  CoinPackedMatrix matrix(true, m, columns, static_cast<CoinBigIndex>(values.size()), values.data(),
                          rows.data(), starts.data(), lengths.data());
  model.loadProblem(matrix, col_lo.data(), col_hi.data(), cost.data(), row_lo.data(),
                    row_hi.data());
  model.setOptimizationDirection(1.0);
  model.setLogLevel(0);
}

/// The dual of that LP: one row per dwell position (the basis is n x n, n = a few hundred,
/// whatever the number of points), two bounded columns per point:
///   min  sum_i -lo_i a_i + hi_i b_i   s.t.  sum_i d_ij (a_i - b_i) <= 0  (j = 1..n),
///        0 <= a_i <= w_under_i,  0 <= b_i <= w_over_i.
/// By strong duality its optimum is minus the primal optimum; the dwell times are minus the
/// duals of its rows.
void buildDualLp(const Eigen::MatrixXd& d, const PenaltyModel& pm, ClpSimplex& model) {
  const int m = static_cast<int>(d.rows());
  const int n = static_cast<int>(d.cols());
  std::vector<int> starts{0}, rows;
  std::vector<double> values, col_lo, col_hi, cost;
  for (int i = 0; i < m; ++i) {
    for (int side = 0; side < 2; ++side) {  // a_i (under), b_i (over)
      const double bound = side == 0 ? pm.w_under[i] : pm.w_over[i];
      if (!(bound > 0.0)) {
        continue;
      }
      const double sign = side == 0 ? 1.0 : -1.0;
      for (int j = 0; j < n; ++j) {
        if (d(i, j) > 0.0) {
          rows.push_back(j);
          values.push_back(sign * d(i, j));
        }
      }
      starts.push_back(static_cast<int>(rows.size()));
      col_lo.push_back(0.0);
      col_hi.push_back(bound);
      cost.push_back(side == 0 ? -pm.lo[i] : pm.hi[i]);
    }
  }
  const int columns = static_cast<int>(cost.size());
  std::vector<int> lengths(columns);
  for (int k = 0; k < columns; ++k) {
    lengths[k] = starts[k + 1] - starts[k];
  }
  const std::vector<double> row_lo(n, -COIN_DBL_MAX), row_hi(n, 0.0);
  CoinPackedMatrix matrix(true, n, columns, static_cast<CoinBigIndex>(values.size()), values.data(),
                          rows.data(), starts.data(), lengths.data());
  model.loadProblem(matrix, col_lo.data(), col_hi.data(), cost.data(), row_lo.data(),
                    row_hi.data());
  model.setLogLevel(0);
}

}  // namespace

double PenaltyModel::operator()(const Eigen::VectorXd& dose) const {
  double e = 0.0;
  for (Eigen::Index i = 0; i < dose.size(); ++i) {
    e += pointPenalty(*this, i, dose[i]);
  }
  return e;
}

PenaltyModel penaltyModel(const HdrCase& c) {
  const Eigen::Index m = static_cast<Eigen::Index>(c.points.size());
  PenaltyModel pm;
  pm.lo = Eigen::VectorXd::Zero(m);
  pm.hi = Eigen::VectorXd::Constant(m, std::numeric_limits<double>::infinity());
  pm.w_under = Eigen::VectorXd::Zero(m);
  pm.w_over = Eigen::VectorXd::Zero(m);
  for (std::size_t k = 0; k < c.criteria.size(); ++k) {
    const Criterion& cr = c.criteria[k];
    const std::string where =
        "case '" + c.name + "' criterion " + std::to_string(k) + " (" + cr.structure + ")";
    if (!std::isfinite(cr.min_Gy) || !std::isfinite(cr.max_Gy) || cr.min_Gy < 0.0) {
      throw std::invalid_argument(where + ": doses must be finite and >= 0");
    }
    if (cr.min_Gy > cr.max_Gy) {
      throw std::invalid_argument(where + ": D_min " + std::to_string(cr.min_Gy) + " Gy > D_max " +
                                  std::to_string(cr.max_Gy) + " Gy");
    }
    if (!(cr.weight_under >= 0.0) || !(cr.weight_over >= 0.0) || !std::isfinite(cr.weight_under) ||
        !std::isfinite(cr.weight_over)) {
      throw std::invalid_argument(where + ": penalty weights must be finite and >= 0");
    }
    const int s = c.structureIndex(cr.structure);
    if (s < 0) {
      throw std::invalid_argument(where + ": no structure named '" + cr.structure + "'");
    }
    std::vector<Eigen::Index> members;
    for (std::size_t i = 0; i < c.points.size(); ++i) {
      if (c.points[i].structure == s && c.points[i].kind == cr.kind) {
        members.push_back(static_cast<Eigen::Index>(i));
      }
    }
    if (members.empty()) {
      pm.notes.push_back(where + ": no " + (cr.kind == PointKind::kSurface ? "surface" : "volume") +
                         " dose points; the criterion contributes nothing");
      continue;
    }
    const double per_point = 1.0 / static_cast<double>(members.size());  // eq. 6.2: average
    for (Eigen::Index i : members) {
      pm.lo[i] = cr.min_Gy;
      pm.hi[i] = cr.max_Gy;
      pm.w_under[i] = cr.weight_under * per_point;
      pm.w_over[i] = cr.weight_over * per_point;
    }
  }
  return pm;
}

void writeLpMps(const HdrCase& c, const Eigen::MatrixXd& d, const std::string& path) {
  checkSizes(c, d, "writeLpMps");
  ClpSimplex model;
  buildLp(d, penaltyModel(c), model);
  if (model.writeMps(path.c_str(), 0, 1) != 0) {
    throw std::runtime_error("writeLpMps: cannot write '" + path + "'");
  }
}

DwellResult optimizeLp(const HdrCase& c, const Eigen::MatrixXd& d, const LpOptions& options) {
  checkSizes(c, d, "optimizeLp");
  const auto start = Clock::now();
  const PenaltyModel pm = penaltyModel(c);
  const int n = static_cast<int>(d.cols());
  if (!options.mps_path.empty()) {
    writeLpMps(c, d, options.mps_path);
  }
  ClpSimplex model;
  DwellResult r;
  r.method = "lp";
  if (options.dual_formulation) {
    buildDualLp(d, pm, model);
    model.setMaximumSeconds(options.max_seconds);
    model.dual();
    const double* y = model.dualRowSolution();
    for (int j = 0; j < n; ++j) {
      r.times_s.push_back(std::max(0.0, -y[j]));  // t_j = -dual of dwell row j (round-off clipped)
    }
    r.lower_bound = -model.objectiveValue();  // weak duality: no dwell times do better
  } else {
    buildLp(d, pm, model);
    model.setMaximumSeconds(options.max_seconds);
    model.dual();
    const double* x = model.primalColumnSolution();
    for (int j = 0; j < n; ++j) {
      r.times_s.push_back(std::max(0.0, x[j]));
    }
    r.lower_bound = model.objectiveValue();
  }
  r.iterations = model.numberIterations();
  if (model.status() != 0) {
    r.status = "Clp status " + std::to_string(model.status()) + " (secondary " +
               std::to_string(model.secondaryStatus()) + ")";
  }
  const Eigen::VectorXd t = Eigen::Map<const Eigen::VectorXd>(r.times_s.data(), n);
  r.objective = pm(d * t);
  r.seconds = since(start);
  return r;
}

DwellResult optimizeAnnealing(const HdrCase& c, const Eigen::MatrixXd& d,
                              const AnnealingOptions& o) {
  checkSizes(c, d, "optimizeAnnealing");
  if (o.iterations < 1 || !(o.final_temperature_ratio > 0.0 && o.final_temperature_ratio < 1.0) ||
      !(o.initial_temperature >= 0.0)) {
    throw std::invalid_argument("optimizeAnnealing: iterations >= 1, 0 < final ratio < 1, T0 >= 0");
  }
  const auto start = Clock::now();
  const PenaltyModel pm = penaltyModel(c);
  const Eigen::Index m = d.rows();
  const Eigen::Index n = d.cols();
  // Start: equal times giving the target's points the prescription on average.
  double target_rate = 0.0;
  int target_points = 0;
  for (std::size_t i = 0; i < c.points.size(); ++i) {
    const int s = c.points[i].structure;
    if (s >= 0 && static_cast<std::size_t>(s) < c.structures.size() &&
        c.structures[static_cast<std::size_t>(s)].role == StructureRole::kTarget) {
      target_rate += d.row(static_cast<Eigen::Index>(i)).sum();
      ++target_points;
    }
  }
  const double mean_rate =
      target_points > 0 ? target_rate / target_points : d.rowwise().sum().mean();
  const double t0 = mean_rate > 0.0 ? c.prescription_Gy / mean_rate : 1.0;
  Eigen::VectorXd t = Eigen::VectorXd::Constant(n, t0);
  Eigen::VectorXd dose = d * t;
  double e = pm(dose);
  Eigen::VectorXd best_t = t;
  double best_e = e;
  const double temp0 =
      o.initial_temperature > 0.0 ? o.initial_temperature : std::max(1e-9, kDefaultT0Fraction * e);
  const double cooling =
      std::pow(o.final_temperature_ratio, 1.0 / static_cast<double>(o.iterations));
  std::mt19937 rng(o.seed);
  std::uniform_int_distribution<Eigen::Index> pick(0, n - 1);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  double temperature = temp0;
  for (long k = 0; k < o.iterations; ++k, temperature *= cooling) {
    const Eigen::Index j = pick(rng);
    // Step: up to the start time, shrinking with the temperature (never below 5 %).
    const double scale = t0 * (0.05 + 0.95 * temperature / temp0);
    const double proposed = std::max(0.0, t[j] + (2.0 * unit(rng) - 1.0) * scale);
    const double delta_t = proposed - t[j];
    if (delta_t == 0.0) {
      continue;
    }
    double delta_e = 0.0;
    for (Eigen::Index i = 0; i < m; ++i) {
      const double before = dose[i];
      const double after = before + d(i, j) * delta_t;
      delta_e += pointPenalty(pm, i, after) - pointPenalty(pm, i, before);
    }
    if (delta_e <= 0.0 || unit(rng) < std::exp(-delta_e / temperature)) {
      dose += d.col(j) * delta_t;
      t[j] = proposed;
      e += delta_e;
      if (e < best_e) {
        best_e = e;
        best_t = t;
      }
    }
  }
  DwellResult r;
  r.method = "sa";
  r.iterations = o.iterations;
  r.times_s.assign(best_t.data(), best_t.data() + n);
  r.objective = pm(d * best_t);  // recomputed: no drift from the incremental sums
  r.seconds = since(start);
  return r;
}

}  // namespace needle_guidance::dose
