#include "needle_guidance/dose/dvh_optimization.h"

#include <CbcModel.hpp>
#include <CbcSolver.hpp>
#include <CoinPackedMatrix.hpp>
#include <OsiClpSolverInterface.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <limits>
#include <numeric>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::dose {
namespace {

using Clock = std::chrono::steady_clock;

double since(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

/// Processor time of this process since `start` [s] (what the time limits count: the machine's
/// load from other processes does not shorten the search).
double cpuSince(std::clock_t start) {
  return static_cast<double>(std::clock() - start) / CLOCKS_PER_SEC;
}

std::string number(double v) {
  char text[32];
  std::snprintf(text, sizeof text, "%.2f", v);
  return text;
}

bool isCc(const std::string& index) {
  return index.size() > 3 && index.compare(index.size() - 2, 2, "cc") == 0;
}

/// The number in an index spec: p of V<p> / D<p>, v of D<v>cc.
double specNumber(const std::string& index) {
  return std::stod(index.substr(1, index.size() - 1 - (isCc(index) ? 2 : 0)));
}

/// A criterion as a volume condition on the dose points of its structure: the volume at dose
/// >= level_Gy is at most (at_most) or at least budget_pct of the structure's volume.
struct VolumeCondition {
  std::size_t criterion = 0;
  int structure = 0;
  double level_Gy = 0.0;
  double budget_pct = 0.0;
  bool at_most = true;
};

/// Turns criterion k into a volume condition; false (with a note) if its structure cannot
/// support it (D<v>cc of a smaller structure) or is absent.
bool toCondition(const HdrCase& c, const DvhCriterion& k, std::size_t which, double rx,
                 VolumeCondition* out, std::vector<std::string>* notes) {
  int si = -1;
  for (std::size_t s = 0; s < c.structures.size(); ++s) {
    std::string n = c.structures[s].name;
    std::transform(n.begin(), n.end(), n.begin(),
                   [](unsigned char ch) { return std::tolower(ch); });
    if (n == k.structure)
      si = static_cast<int>(s);
  }
  if (si < 0) {
    notes->push_back(describe(k) + ": no structure '" + k.structure + "', criterion skipped");
    return false;
  }
  const double volume = c.structures[static_cast<std::size_t>(si)].volume_m3();
  const double x = specNumber(k.index);
  VolumeCondition v;
  v.criterion = which;
  v.structure = si;
  v.at_most = k.at_most;
  if (k.index[0] == 'V') {
    v.level_Gy = x / 100.0 * rx;
    v.budget_pct = k.limit;
  } else {
    v.level_Gy = k.limit;
    const double pct = isCc(k.index) ? 100.0 * x * 1e-6 / std::max(volume, 1e-300) : x;
    if (pct > 100.0 + 1e-9 || !(volume > 0.0)) {
      notes->push_back(describe(k) + ": undefined (the structure holds " + number(volume * 1e6) +
                       " cm3), criterion skipped");
      return false;
    }
    // D_x <= L: less than x of the volume above L (strictly, so the hottest x is not all above).
    v.budget_pct = k.at_most ? pct * (1.0 - 1e-6) : pct;
  }
  *out = v;
  return true;
}

/// Dose points of the MIP: the coarse structure lattice of every structure a condition names.
struct PlanPoints {
  std::vector<int> first;  ///< per structure: index of its first point (-1 if unused)
  std::vector<int> count;
  std::vector<double> pct;  ///< per point: % of its structure's volume
  Eigen::MatrixXd d;        ///< dose rate [Gy/s] per point and dwell
};

PlanPoints planPoints(const HdrCase& c, const Tg43Source& source,
                      const std::vector<VolumeCondition>& conditions, double min_spacing_m,
                      int max_points) {
  PlanPoints p;
  p.first.assign(c.structures.size(), -1);
  p.count.assign(c.structures.size(), 0);
  std::vector<Point3> points;
  for (const VolumeCondition& v : conditions) {
    const std::size_t s = static_cast<std::size_t>(v.structure);
    if (p.first[s] >= 0)
      continue;
    // The lattice coarsens for a large structure so that the MIP stays small.
    const double spacing_m =
        std::max(min_spacing_m, std::cbrt(c.structures[s].volume_m3() / max_points));
    const VolumeSample sample = sampleStructure(c.structures[s], spacing_m, spacing_m);
    const double total = std::accumulate(sample.volume_m3.begin(), sample.volume_m3.end(), 0.0);
    p.first[s] = static_cast<int>(points.size());
    p.count[s] = static_cast<int>(sample.points_m.size());
    for (std::size_t i = 0; i < sample.points_m.size(); ++i) {
      points.push_back(sample.points_m[i]);
      p.pct.push_back(100.0 * sample.volume_m3[i] / total);
    }
  }
  p.d.resize(static_cast<Eigen::Index>(points.size()), static_cast<Eigen::Index>(c.dwells.size()));
  for (std::size_t j = 0; j < c.dwells.size(); ++j) {
    for (std::size_t i = 0; i < points.size(); ++i)
      p.d(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(j)) =
          dwellDoseRate(c, source, c.dwells[j], points[i]);
  }
  return p;
}

/// Doses at the MIP's points [Gy].
Eigen::VectorXd pointDoses(const PlanPoints& p, const std::vector<double>& t) {
  return p.d * Eigen::Map<const Eigen::VectorXd>(t.data(), static_cast<Eigen::Index>(t.size()));
}

/// % of the condition's structure at dose >= its level.
double coveredPct(const PlanPoints& p, const VolumeCondition& v, const std::vector<double>& t) {
  const Eigen::VectorXd d = pointDoses(p, t);
  const int first = p.first[static_cast<std::size_t>(v.structure)];
  double pct = 0.0;
  for (int i = first; i < first + p.count[static_cast<std::size_t>(v.structure)]; ++i)
    pct += d(i) >= v.level_Gy * (1.0 - 1e-9) ? p.pct[static_cast<std::size_t>(i)] : 0.0;
  return pct;
}

/// The MIP's objective at times t with the binaries and elastic slacks the doses imply
/// (infinite if t breaks the total-time bound).
double objectiveOf(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
                   const std::vector<double>& t, double total_time_s, const DvhPlanOptions& o) {
  double total = 0.0;
  for (double v : t)
    total += v;
  if (total > total_time_s * (1.0 + 1e-9))
    return std::numeric_limits<double>::infinity();
  double value = 1e-6 / static_cast<double>(t.size()) * total;
  for (std::size_t k = 0; k < conditions.size(); ++k) {
    const VolumeCondition& v = conditions[k];
    const double pct = coveredPct(p, v, t);
    if (k == 0)
      value -= pct;
    const double slack = v.at_most ? pct - v.budget_pct : v.budget_pct - pct;
    if (slack > 0.0 && !(k == 0 && v.budget_pct <= 0.0))
      value += o.violation_penalty * slack;
  }
  return value;
}

/// The freeing LP heuristic (in the manner of IPIP): every organ point is held below its
/// criterion's level by a linear row except a "freed" set within the criterion's volume budget;
/// target coverage is relaxed to sum_i w_i min(d_i / Rx, 1). Each round frees, per criterion,
/// up to half its remaining budget among the held points whose rows bind hardest (largest row
/// price per volume), and re-solves (warm start). Returns the round with the best MIP objective.
std::vector<double> freeingHeuristic(const PlanPoints& p,
                                     const std::vector<VolumeCondition>& conditions,
                                     double total_time_s, const DvhPlanOptions& o, int rounds) {
  const int n = static_cast<int>(p.d.cols());
  const double inf = COIN_DBL_MAX;
  OsiClpSolverInterface lp;
  lp.messageHandler()->setLogLevel(0);
  // Columns: t (n), then per at-least condition its points' coverage fractions, then slacks.
  for (int j = 0; j < n; ++j)
    lp.addCol(0, nullptr, nullptr, 0.0, total_time_s, 1e-6 / n);
  std::vector<std::vector<int>> held_row(conditions.size());  // per at-most condition, per point
  for (std::size_t k = 0; k < conditions.size(); ++k) {
    const VolumeCondition& v = conditions[k];
    const int first = p.first[static_cast<std::size_t>(v.structure)];
    const int count = p.count[static_cast<std::size_t>(v.structure)];
    std::vector<int> idx(static_cast<std::size_t>(n));
    for (int j = 0; j < n; ++j)
      idx[static_cast<std::size_t>(j)] = j;
    if (v.at_most) {
      for (int i = first; i < first + count; ++i) {
        Eigen::VectorXd r = p.d.row(i).transpose();
        held_row[k].push_back(lp.getNumRows());
        lp.addRow(n, idx.data(), r.data(), -inf, v.level_Gy);
      }
      continue;
    }
    // At least: u_i <= d_i / level, u in [0, 1]; budget row sum pct_i u_i + s >= budget.
    std::vector<int> u_cols;
    for (int i = first; i < first + count; ++i) {
      const double w = p.pct[static_cast<std::size_t>(i)];
      u_cols.push_back(lp.getNumCols());
      lp.addCol(0, nullptr, nullptr, 0.0, 1.0, k == 0 ? -w : 0.0);
      std::vector<int> ri(idx);
      Eigen::VectorXd r = -p.d.row(i).transpose() / v.level_Gy;
      std::vector<double> rv(r.data(), r.data() + n);
      ri.push_back(u_cols.back());
      rv.push_back(1.0);
      lp.addRow(n + 1, ri.data(), rv.data(), -inf, 0.0);
    }
    if (!(k == 0 && v.budget_pct <= 0.0)) {
      const int s_col = lp.getNumCols();
      lp.addCol(0, nullptr, nullptr, 0.0, inf, o.violation_penalty);
      std::vector<int> ri(u_cols);
      std::vector<double> rv;
      for (int i = first; i < first + count; ++i)
        rv.push_back(p.pct[static_cast<std::size_t>(i)]);
      ri.push_back(s_col);
      rv.push_back(1.0);
      lp.addRow(static_cast<int>(ri.size()), ri.data(), rv.data(), v.budget_pct, inf);
    }
  }
  std::vector<int> idx(static_cast<std::size_t>(n));
  std::vector<double> ones(static_cast<std::size_t>(n), 1.0);
  for (int j = 0; j < n; ++j)
    idx[static_cast<std::size_t>(j)] = j;
  lp.addRow(n, idx.data(), ones.data(), -inf, total_time_s);
  std::vector<double> freed_pct(conditions.size(), 0.0), best_t(static_cast<std::size_t>(n), 0.0);
  double best = objectiveOf(p, conditions, best_t, total_time_s, o);
  for (int round = 0; round < rounds; ++round) {
    round == 0 ? lp.initialSolve() : lp.resolve();
    if (!lp.isProvenOptimal())
      break;
    std::vector<double> t(lp.getColSolution(), lp.getColSolution() + n);
    for (double& x : t)
      x = std::max(0.0, x);
    const double value = objectiveOf(p, conditions, t, total_time_s, o);
    if (value < best) {
      best = value;
      best_t = t;
    }
    bool freed = false;
    const double* price = lp.getRowPrice();
    for (std::size_t k = 0; k < conditions.size(); ++k) {
      const VolumeCondition& v = conditions[k];
      if (!v.at_most)
        continue;
      const int first = p.first[static_cast<std::size_t>(v.structure)];
      std::vector<std::pair<double, int>> binding;  // (price per volume, point)
      for (std::size_t q = 0; q < held_row[k].size(); ++q) {
        const int row = held_row[k][q];
        const double pct = p.pct[static_cast<std::size_t>(first) + q];
        if (lp.getRowUpper()[row] < inf && std::abs(price[row]) > 1e-12)
          binding.emplace_back(std::abs(price[row]) / pct, row);
      }
      std::sort(binding.rbegin(), binding.rend());
      double allowance =
          round + 1 == rounds ? v.budget_pct - freed_pct[k] : 0.5 * (v.budget_pct - freed_pct[k]);
      for (const auto& [score, row] : binding) {
        const double pct = p.pct[static_cast<std::size_t>(first + (row - held_row[k][0]))];
        if (pct > allowance)
          continue;
        lp.setRowUpper(row, inf);
        freed_pct[k] += pct;
        allowance -= pct;
        freed = true;
      }
    }
    if (!freed)
      break;
  }
  // Scaled copies of the best round: coverage against the budgets, judged on the MIP objective.
  const std::vector<double> base = best_t;
  for (double scale = 0.8; scale <= 1.5 + 1e-9; scale += 0.02) {
    std::vector<double> t = base;
    for (double& x : t)
      x *= scale;
    const double value = objectiveOf(p, conditions, t, total_time_s, o);
    if (value < best) {
      best = value;
      best_t = t;
    }
  }
  return best_t;
}

/// The MIP's solution.
struct MipSolution {
  std::vector<double> times_s;
  double v100_pct = 0.0, gap_pct = 0.0;
  bool optimal = false, found = false, bound_known = false;
  int binaries = 0, rows = 0;
};

/// Column layout: dwell times, then per condition its point binaries, then per condition its
/// elastic slack. Condition 0 is the objective's (target coverage at the prescription).
MipSolution solveMip(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
                     double total_time_s, const Eigen::VectorXd& reference_Gy,
                     const DvhPlanOptions& o, double seconds) {
  const std::clock_t start = std::clock();
  const int n = static_cast<int>(p.d.cols());
  MipSolution out;
  // Incumbent: the freeing LP heuristic; CBC then looks for better within its time.
  std::vector<double> best_t = freeingHeuristic(p, conditions, total_time_s, o, o.heuristic_rounds);
  double best = objectiveOf(p, conditions, best_t, total_time_s, o);
  const double cbc_seconds = std::min(o.cbc_seconds, seconds - cpuSince(start));
  if (!(cbc_seconds > 0.0)) {
    out.found = std::isfinite(best);
    out.times_s = best_t;
    out.v100_pct = coveredPct(p, conditions[0], best_t);
    return out;
  }
  std::vector<double> lb, ub, obj;
  std::vector<std::vector<std::pair<int, double>>> cols;  // per column: (row, value)
  std::vector<double> row_lo, row_hi;
  const double inf = COIN_DBL_MAX;
  for (int j = 0; j < n; ++j) {
    lb.push_back(0.0);
    ub.push_back(total_time_s);
    obj.push_back(1e-6 / n);  // ties broken towards less total time
    cols.emplace_back();
  }
  const int time_row = 0;
  row_lo.push_back(-inf);
  row_hi.push_back(total_time_s);
  for (int j = 0; j < n; ++j)
    cols[static_cast<std::size_t>(j)].emplace_back(time_row, 1.0);
  std::vector<int> slack_rows;
  for (std::size_t k = 0; k < conditions.size(); ++k) {
    const VolumeCondition& v = conditions[k];
    const int first = p.first[static_cast<std::size_t>(v.structure)];
    const int count = p.count[static_cast<std::size_t>(v.structure)];
    const int budget_row = static_cast<int>(row_lo.size());
    row_lo.push_back(v.at_most ? -inf : v.budget_pct);
    row_hi.push_back(v.at_most ? v.budget_pct : inf);
    slack_rows.push_back(budget_row);
    for (int i = first; i < first + count; ++i) {
      const int row = static_cast<int>(row_lo.size());
      const double max_dose = p.d.row(i).maxCoeff() * total_time_s;
      for (int j = 0; j < n; ++j) {
        const double dij = p.d(i, j);
        if (dij > 0.0)
          cols[static_cast<std::size_t>(j)].emplace_back(row, dij);
      }
      if (v.at_most && reference_Gy(i) < o.binary_dose_ratio * v.level_Gy) {
        // Cold under the reference plan: held below the level without a binary.
        row_lo.push_back(-inf);
        row_hi.push_back(v.level_Gy);
        continue;
      }
      // at most: d_i - M b_i <= level (b_i = 1 lets the point exceed the level);
      // at least: d_i - level b_i >= 0 (b_i = 1 only if the point reaches the level).
      row_lo.push_back(v.at_most ? -inf : 0.0);
      row_hi.push_back(v.at_most ? v.level_Gy : inf);
      lb.push_back(0.0);
      ub.push_back(1.0);
      obj.push_back(k == 0 ? -p.pct[static_cast<std::size_t>(i)] : 0.0);
      cols.push_back({{row, v.at_most ? -std::max(max_dose - v.level_Gy, 0.0) : -v.level_Gy},
                      {budget_row, p.pct[static_cast<std::size_t>(i)]}});
      ++out.binaries;
    }
  }
  for (std::size_t k = 0; k < conditions.size(); ++k) {  // elastic budgets
    lb.push_back(0.0);
    ub.push_back(inf);
    obj.push_back(k == 0 && !conditions[0].at_most && conditions[0].budget_pct <= 0.0
                      ? 0.0
                      : o.violation_penalty);
    cols.push_back({{slack_rows[k], conditions[k].at_most ? -1.0 : 1.0}});
  }
  std::vector<CoinBigIndex> starts{0};
  std::vector<int> index;
  std::vector<double> value;
  for (const auto& col : cols) {
    for (const auto& [row, v] : col) {
      index.push_back(row);
      value.push_back(v);
    }
    starts.push_back(static_cast<CoinBigIndex>(index.size()));
  }
  const int ncols = static_cast<int>(cols.size());
  std::vector<int> lengths(static_cast<std::size_t>(ncols));
  for (int j = 0; j < ncols; ++j)
    lengths[static_cast<std::size_t>(j)] =
        starts[static_cast<std::size_t>(j) + 1] - starts[static_cast<std::size_t>(j)];
  CoinPackedMatrix matrix(true, static_cast<int>(row_lo.size()), ncols,
                          static_cast<CoinBigIndex>(value.size()), value.data(), index.data(),
                          starts.data(), lengths.data());
  OsiClpSolverInterface solver;
  solver.loadProblem(matrix, lb.data(), ub.data(), obj.data(), row_lo.data(), row_hi.data());
  solver.messageHandler()->setLogLevel(0);
  out.rows = static_cast<int>(row_lo.size());
  for (int j = n; j < n + out.binaries; ++j)
    solver.setInteger(j);
  CbcModel model(solver);
  CbcSolverUsefulData data;
  data.noPrinting_ = true;
  CbcMain0(model, data);
  const std::string sec = number(cbc_seconds), gap = std::to_string(o.relative_gap);
  const std::string cutoff = std::to_string(best);
  const char* argv[] = {"cbc",          "-log",   "0",         "-sec",
                        sec.c_str(),    "-ratio", gap.c_str(), "-cutoff",
                        cutoff.c_str(), "-solve", "-quit"};
  CbcMain1(
      11, argv, model, [](CbcModel*, int) { return 0; }, data);
  if (model.bestSolution() != nullptr) {
    std::vector<double> t(model.bestSolution(), model.bestSolution() + n);
    for (double& v : t)
      v = std::max(0.0, v);
    const double value = objectiveOf(p, conditions, t, total_time_s, o);
    if (value <= best) {
      best = value;
      best_t = t;
    }
  }
  out.found = std::isfinite(best);
  out.times_s = best_t;
  out.v100_pct = coveredPct(p, conditions[0], best_t);
  const double bound = model.getBestPossibleObjValue();
  out.optimal = model.isProvenOptimal() || (model.isProvenInfeasible() && std::isfinite(best));
  out.bound_known = true;
  out.gap_pct = out.optimal ? 0.0 : std::max(0.0, best - bound);
  return out;
}

}  // namespace

std::vector<DvhCriterion> defaultDvhCriteria(double rx) {
  return {{"prostate", "V100", 90.0, false},
          {"prostate", "V150", 35.0},
          {"prostate", "V200", 11.0},
          {"urethra", "D10", 1.15 * rx},
          {"urethra", "D0.1cc", 1.18 * rx},
          {"urethra", "V125", 1.0},
          {"rectum", "D2cc", 0.75 * rx},
          {"rectum", "D0.1cc", 0.80 * rx},
          {"rectum", "V75", 5.0},
          {"bladder", "D2cc", 0.75 * rx},
          {"bladder", "D0.1cc", 0.80 * rx},
          {"bladder", "V75", 5.0}};
}

DvhCriterion parseDvhCriterion(const std::string& text, double rx) {
  std::istringstream in(text);
  DvhCriterion k;
  std::string op, limit;
  if (!(in >> k.structure >> k.index >> op >> limit) || (op != "<=" && op != ">=")) {
    throw std::invalid_argument("DVH criterion '" + text +
                                "': expected '<structure> <index> <= | >= <limit>[%|Gy]'");
  }
  std::transform(k.structure.begin(), k.structure.end(), k.structure.begin(),
                 [](unsigned char ch) { return std::tolower(ch); });
  k.at_most = op == "<=";
  StructureDose probe;
  doseVolumeIndex(probe, k.index, rx);  // throws for a malformed index
  std::size_t used = 0;
  try {
    k.limit = std::stod(limit, &used);
  } catch (const std::exception&) {
    throw std::invalid_argument("DVH criterion '" + text + "': limit '" + limit +
                                "' is not a number");
  }
  const std::string unit = limit.substr(used);
  const bool dose = k.index[0] == 'D';
  if (dose && unit == "%")
    k.limit *= rx / 100.0;
  else if (!(dose && unit == "Gy") && !(!dose && (unit == "%" || unit.empty())))
    throw std::invalid_argument("DVH criterion '" + text + "': unit '" + unit + "' does not fit " +
                                k.index + " (D: % of Rx or Gy; V: %)");
  if (!std::isfinite(k.limit) || k.limit < 0.0)
    throw std::invalid_argument("DVH criterion '" + text + "': limit must be finite and >= 0");
  return k;
}

std::string describe(const DvhCriterion& k) {
  return k.structure + " " + k.index + (k.at_most ? " <= " : " >= ") + number(k.limit) +
         (k.index[0] == 'D' ? " Gy" : " %");
}

std::map<std::string, std::vector<std::string>> criteriaSpecs(
    const std::vector<DvhCriterion>& criteria) {
  std::map<std::string, std::vector<std::string>> out;
  for (const DvhCriterion& k : criteria) {
    auto& specs = out[k.structure];
    if (std::find(specs.begin(), specs.end(), k.index) == specs.end())
      specs.push_back(k.index);
  }
  return out;
}

std::vector<DvhCriterion> criteriaAt(const std::map<std::string, DoseVolumeIndex>& indices,
                                     const std::vector<std::string>& at_most_keys,
                                     const std::vector<std::string>& at_least_keys) {
  std::vector<DvhCriterion> out;
  for (const auto* keys : {&at_most_keys, &at_least_keys}) {
    for (const std::string& key : *keys) {
      const auto it = indices.find(key);
      if (it == indices.end() || !it->second.defined)
        continue;  // an undefined index constrains nothing
      const std::size_t cut = key.rfind('_');
      out.push_back(
          {key.substr(0, cut), key.substr(cut + 1), it->second.value, keys == &at_most_keys});
    }
  }
  return out;
}

namespace {

/// Structure doses on the evaluation lattice (samples kept between rounds).
struct Evaluator {
  const HdrCase& c;
  const Tg43Source& source;
  std::vector<VolumeSample> samples;
  Evaluator(const HdrCase& hc, const Tg43Source& s, double spacing) : c(hc), source(s) {
    for (const Structure& st : c.structures)
      samples.push_back(sampleStructure(st, latticeSpacing(st, spacing)));
  }
  std::vector<StructureDose> doses(const std::vector<double>& times) const {
    std::vector<StructureDose> out;
    for (std::size_t s = 0; s < c.structures.size(); ++s) {
      StructureDose sd;
      sd.name = c.structures[s].name;
      sd.volume_m3 = samples[s].volume_m3;
      for (const Point3& p : samples[s].points_m)
        sd.dose_Gy.push_back(doseAt(c, source, times, p));
      out.push_back(std::move(sd));
    }
    return out;
  }
};

/// How far index `got` misses criterion k (> 0: violated), in its unit.
double excess(const DvhCriterion& k, const DoseVolumeIndex& got) {
  if (!got.defined)
    return 0.0;
  return k.at_most ? got.value - k.limit : k.limit - got.value;
}

}  // namespace

DvhPlanResult optimizeDvh(const HdrCase& c, const Tg43Source& source,
                          const std::vector<DvhCriterion>& criteria, const DvhPlanOptions& o) {
  const auto t0 = Clock::now();
  const std::clock_t cpu0 = std::clock();
  if (c.dwells.empty())
    throw std::invalid_argument("optimizeDvh: case '" + c.name + "' has no dwell positions");
  if (!(o.plan_spacing_m > 0.0) || !(o.eval_spacing_m > 0.0) || !(o.max_seconds > 0.0) ||
      o.rounds < 1 || !(o.violation_penalty > 0.0))
    throw std::invalid_argument(
        "optimizeDvh: spacings, time limit, rounds and penalty must be > 0");
  const double rx = c.prescription_Gy;
  DvhPlanResult r;
  int target = -1;
  for (std::size_t s = 0; s < c.structures.size() && target < 0; ++s)
    target = c.structures[s].role == StructureRole::kTarget ? static_cast<int>(s) : -1;
  if (target < 0)
    throw std::invalid_argument("optimizeDvh: case '" + c.name + "' has no target structure");
  std::string target_name = c.structures[static_cast<std::size_t>(target)].name;
  std::transform(target_name.begin(), target_name.end(), target_name.begin(),
                 [](unsigned char ch) { return std::tolower(ch); });
  // Condition 0: the objective, target V100 (at least the criterion's budget if there is one).
  std::vector<DvhCriterion> all = {{target_name, "V100", 0.0, false}};
  for (const DvhCriterion& k : criteria) {
    if (k.structure == target_name && k.index == "V100" && !k.at_most)
      all[0].limit = k.limit;
    else
      all.push_back(k);
  }
  std::vector<VolumeCondition> conditions;
  for (std::size_t k = 0; k < all.size(); ++k) {
    VolumeCondition v;
    if (toCondition(c, all[k], k, rx, &v, &r.notes))
      conditions.push_back(v);
  }
  const PlanPoints points =
      planPoints(c, source, conditions, o.plan_spacing_m, o.max_points_per_structure);
  // Bound on the total time: 4x what gives the target its prescription on average with equal
  // times (reported if a plan reaches it).
  const int tf = points.first[static_cast<std::size_t>(target)];
  const double mean_rate = points.d.middleRows(tf, points.count[static_cast<std::size_t>(target)])
                               .rowwise()
                               .sum()
                               .mean();
  const double equal_time_s = rx / std::max(mean_rate, 1e-300);
  const double total_time_s = 4.0 * equal_time_s * c.dwells.size();
  // Reference plan for choosing which organ points need a binary: equal times, target mean Rx.
  const Eigen::VectorXd reference_Gy = points.d.rowwise().sum() * equal_time_s;
  const Evaluator eval(c, source, o.eval_spacing_m);
  const std::vector<VolumeCondition> stated = conditions;  // before any tightening
  if (c.dwell_times_s.size() == c.dwells.size()) {
    // The case's own dwell times on the planner's points: a plan the planner should match.
    r.case_times_objective = objectiveOf(points, conditions, c.dwell_times_s, total_time_s, o);
    r.case_times_v100_pct = coveredPct(points, conditions[0], c.dwell_times_s);
  }
  const auto specs = criteriaSpecs(all);
  int best_violations = 1 << 30;
  for (int round = 0; round < o.rounds; ++round) {
    const double left = o.max_seconds - cpuSince(cpu0);
    if (round > 0 && left < 0.5)
      break;
    const MipSolution m =
        solveMip(points, conditions, total_time_s, reference_Gy, o, left / (o.rounds - round));
    ++r.rounds;
    if (!m.found)
      continue;
    const auto indices = indexSet(eval.doses(m.times_s), specs, rx);
    std::vector<std::string> violated;
    for (VolumeCondition& v : conditions) {
      const DvhCriterion& k = all[v.criterion];
      const std::string key = k.structure + "_" + k.index;
      const double miss = v.criterion == 0 && k.limit <= 0.0 ? 0.0 : excess(k, indices.at(key));
      const bool is_v = k.index[0] == 'V';
      if (miss > (is_v ? 0.1 : 0.02)) {
        violated.push_back(describe(k) + " (" + number(indices.at(key).value) + ")");
        // Tighten by what the fine lattice shows (the MIP's points under-sample the structure).
        const double step = (v.at_most ? -1.0 : 1.0) * miss;
        (is_v ? v.budget_pct : v.level_Gy) += step;
        v.budget_pct = std::clamp(v.budget_pct, 0.0, 100.0);
        v.level_Gy = std::max(v.level_Gy, 0.0);
      }
    }
    const double v100 = indices.at(target_name + "_V100").value;
    const int nv = static_cast<int>(violated.size());
    const double best_v100 = r.indices.count(target_name + "_V100") != 0
                                 ? r.indices.at(target_name + "_V100").value
                                 : -1.0;
    if (nv < best_violations || (nv == best_violations && v100 > best_v100)) {
      best_violations = nv;
      r.times_s = m.times_s;
      r.indices = indices;
      r.v100_pct = v100;
      r.violated = violated;
      r.mip_v100_pct = m.v100_pct;
      r.objective = objectiveOf(points, stated, m.times_s, total_time_s, o);
      r.mip_gap_pct = m.gap_pct;
      r.mip_optimal = m.optimal;
      r.mip_bound_known = m.bound_known;
      r.binaries = m.binaries;
      r.rows = m.rows;
    }
    if (violated.empty())
      break;
  }
  r.seconds = since(t0);
  r.cpu_seconds = cpuSince(cpu0);
  if (r.times_s.empty()) {
    r.status = "CBC found no plan within " + number(o.max_seconds) + " s";
    return r;
  }
  const double total = std::accumulate(r.times_s.begin(), r.times_s.end(), 0.0);
  if (total > 0.99 * total_time_s)
    r.notes.push_back("the plan reaches the total-time bound of " + number(total_time_s) + " s");
  return r;
}

}  // namespace needle_guidance::dose
