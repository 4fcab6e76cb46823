#include "needle_guidance/dose/dvh_optimization.h"

#include "dvh_model.h"
#include "needle_guidance/cpu_time.h"
#include "needle_guidance/dose/dwell_optimization.h"

#include <CbcModel.hpp>
#include <CbcSolver.hpp>
#include <CoinPackedMatrix.hpp>
#include <OsiClpSolverInterface.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <numeric>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::dose {
namespace {

using dvh_model::PlanPoints;
using dvh_model::VolumeCondition;

using Clock = std::chrono::steady_clock;

double since(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

/// The time limits count processor time of this process (CpuStopwatch::Scope::kProcess): the
/// machine's load from other processes does not shorten the search.
using CpuStopwatch = needle_guidance::CpuStopwatch;
constexpr auto kProcess = CpuStopwatch::Scope::kProcess;

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

/// Turns criterion k into a volume condition; false (with a note) if its structure cannot
/// support it (D<v>cc of a smaller structure) or is absent.
std::string lowerName(std::string n) {
  std::transform(n.begin(), n.end(), n.begin(),
                 [](unsigned char ch) { return static_cast<char>(std::tolower(ch)); });
  return n;
}

/// Index of the structure named `name` (lower case) in c, or -1.
int structureIndex(const HdrCase& c, const std::string& name) {
  for (std::size_t s = 0; s < c.structures.size(); ++s) {
    if (lowerName(c.structures[s].name) == name)
      return static_cast<int>(s);
  }
  return -1;
}

bool toCondition(const HdrCase& c, const DvhCriterion& k, std::size_t which, double rx,
                 VolumeCondition* out, std::vector<std::string>* notes) {
  const int si = structureIndex(c, k.structure);
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
    // D_x <= L: less than x of the volume above L (strictly, so the hottest x is not all above);
    // D_x >= L: at least x of the volume at L or more (doseCoveringVolume's reading).
    v.budget_pct = pct * (1.0 - 1e-6);
    v.strict = k.at_most;
    v.cc = isCc(k.index) ? x : 0.0;
  }
  *out = v;
  return true;
}

/// Dose points of every structure in `structures`. For the MIP (`coarse`): the structure lattice
/// at min_spacing_m in all three directions, coarser so that no structure has more than
/// max_points. Otherwise the evaluation lattice itself (sampleStructure at latticeSpacing, as
/// structureDoses samples), so that the plan is judged on the points it was optimised on.
PlanPoints planPoints(const HdrCase& c, const Tg43Source& source,
                      const std::vector<int>& structures, double min_spacing_m, int max_points,
                      bool coarse) {
  PlanPoints p;
  p.first.assign(c.structures.size(), -1);
  p.count.assign(c.structures.size(), 0);
  std::vector<Point3> points;
  for (const int si : structures) {
    const std::size_t s = static_cast<std::size_t>(si);
    if (p.first[s] >= 0)
      continue;
    const Structure& st = c.structures[s];
    const VolumeSample sample =
        coarse
            ? sampleStructure(st, std::max(min_spacing_m, std::cbrt(st.volume_m3() / max_points)),
                              std::max(min_spacing_m, std::cbrt(st.volume_m3() / max_points)))
            : sampleStructure(st, latticeSpacing(st, min_spacing_m));
    const double total = std::accumulate(sample.volume_m3.begin(), sample.volume_m3.end(), 0.0);
    p.first[s] = static_cast<int>(points.size());
    p.count[s] = static_cast<int>(sample.points_m.size());
    for (std::size_t i = 0; i < sample.points_m.size(); ++i) {
      points.push_back(sample.points_m[i]);
      p.pct.push_back(100.0 * sample.volume_m3[i] / total);
      p.volume_m3.push_back(sample.volume_m3[i]);
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

/// % of the condition's structure at dose >= its level under times t.
double coveredPct(const PlanPoints& p, const VolumeCondition& v, const std::vector<double>& t) {
  return dvh_model::coveredPct(p, v, pointDoses(p, t));
}

/// The planner's objective at times t (objectiveAt).
double objectiveOf(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
                   const std::vector<double>& t, double total_time_s, const DvhPlanOptions& o) {
  return dvh_model::objectiveAt(p, conditions, pointDoses(p, t),
                                std::accumulate(t.begin(), t.end(), 0.0), total_time_s, o);
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
/// elastic slack. Condition 0 is the objective's (target coverage at the prescription). CBC
/// starts from the incumbent `start` (its objective is the cutoff) and runs for `cbc_seconds`.
MipSolution solveMip(const PlanPoints& p, const std::vector<VolumeCondition>& conditions,
                     double total_time_s, const Eigen::VectorXd& reference_Gy,
                     const DvhPlanOptions& o, const std::vector<double>& start,
                     double cbc_seconds) {
  const int n = static_cast<int>(p.d.cols());
  MipSolution out;
  std::vector<double> best_t = start;
  double best = objectiveOf(p, conditions, best_t, total_time_s, o);
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

/// How far index `got` misses criterion k (> 0: violated), in its unit.
double excess(const DvhCriterion& k, const DoseVolumeIndex& got) {
  if (!got.defined)
    return 0.0;
  return k.at_most ? got.value - k.limit : k.limit - got.value;
}

/// The problem as both methods see it: the criteria (0: the target's V100, the objective), their
/// volume conditions, and the evaluation lattice on which plans are judged.
struct Problem {
  std::vector<DvhCriterion> all;
  std::vector<VolumeCondition> conditions;  ///< as stated (before any tightening)
  std::map<std::string, std::vector<std::string>> specs;
  std::string target_name;
  PlanPoints eval;            ///< the evaluation lattice of every structure a criterion names
  double total_time_s = 0.0;  ///< bound on the total dwell time
  double equal_time_s = 0.0;  ///< equal times giving the target its prescription on average
};

Problem setUp(const HdrCase& c, const Tg43Source& source, const std::vector<DvhCriterion>& criteria,
              const DvhPlanOptions& o, std::vector<std::string>* notes) {
  Problem pr;
  int target = -1;
  for (std::size_t s = 0; s < c.structures.size() && target < 0; ++s)
    target = c.structures[s].role == StructureRole::kTarget ? static_cast<int>(s) : -1;
  if (target < 0)
    throw std::invalid_argument("optimizeDvh: case '" + c.name + "' has no target structure");
  pr.target_name = lowerName(c.structures[static_cast<std::size_t>(target)].name);
  // Condition 0: the objective, target V100 (at least the criterion's budget if there is one).
  pr.all = {{pr.target_name, "V100", 0.0, false}};
  for (const DvhCriterion& k : criteria) {
    if (k.structure == pr.target_name && k.index == "V100" && !k.at_most)
      pr.all[0].limit = k.limit;
    else
      pr.all.push_back(k);
  }
  std::vector<int> structures;
  for (std::size_t k = 0; k < pr.all.size(); ++k) {
    VolumeCondition v;
    if (toCondition(c, pr.all[k], k, c.prescription_Gy, &v, notes))
      pr.conditions.push_back(v);
    const int si = structureIndex(c, pr.all[k].structure);
    if (si >= 0)
      structures.push_back(si);
  }
  pr.specs = criteriaSpecs(pr.all);
  pr.eval = planPoints(c, source, structures, o.eval_spacing_m, 0, false);
  for (VolumeCondition& v : pr.conditions) {
    // D<v>cc: v as a share of the volume the lattice holds, as the index reads it.
    const int first = pr.eval.first[static_cast<std::size_t>(v.structure)];
    const auto begin = pr.eval.volume_m3.begin() + first;
    const double sampled =
        std::accumulate(begin, begin + pr.eval.count[static_cast<std::size_t>(v.structure)], 0.0);
    if (v.cc > 0.0 && sampled > 0.0)
      v.budget_pct = std::min(100.0, 100.0 * v.cc * 1e-6 / sampled) * (1.0 - 1e-6);
  }
  // Bound on the total time: 4x what gives the target its prescription on average with equal
  // times, or twice the case's own plan if more (reported if a plan reaches it).
  const PlanPoints& p = pr.eval;
  const int tf = p.first[static_cast<std::size_t>(target)];
  const Eigen::VectorXd rate =
      p.d.middleRows(tf, p.count[static_cast<std::size_t>(target)]).rowwise().sum();
  double mean_rate = 0.0;
  for (int i = 0; i < rate.size(); ++i)
    mean_rate += rate(i) * p.pct[static_cast<std::size_t>(tf + i)] / 100.0;
  pr.equal_time_s = c.prescription_Gy / std::max(mean_rate, 1e-300);
  pr.total_time_s = 4.0 * pr.equal_time_s * static_cast<double>(c.dwells.size());
  if (c.dwell_times_s.size() == c.dwells.size())  // the case's own plan stays within the bound
    pr.total_time_s = std::max(pr.total_time_s, 2.0 * std::accumulate(c.dwell_times_s.begin(),
                                                                      c.dwell_times_s.end(), 0.0));
  return pr;
}

/// Structure doses of times t on the evaluation lattice (what structureDoses computes).
std::vector<StructureDose> latticeDoses(const HdrCase& c, const PlanPoints& p,
                                        const std::vector<double>& t) {
  const Eigen::VectorXd d = pointDoses(p, t);
  std::vector<StructureDose> out;
  for (std::size_t s = 0; s < c.structures.size(); ++s) {
    if (p.first[s] < 0)
      continue;
    StructureDose sd;
    sd.name = c.structures[s].name;
    for (int i = p.first[s]; i < p.first[s] + p.count[s]; ++i) {
      sd.dose_Gy.push_back(d(i));
      sd.volume_m3.push_back(p.volume_m3[static_cast<std::size_t>(i)]);
    }
    out.push_back(std::move(sd));
  }
  return out;
}

/// Plan t judged on the evaluation lattice: its indices and the criteria that give way (with
/// the index each reached). With `tighten`, each missed condition is tightened by its miss.
struct Judgement {
  std::map<std::string, DoseVolumeIndex> indices;
  std::vector<std::string> violated;
  double v100_pct = 0.0;
};

Judgement judge(const HdrCase& c, const Problem& pr, const std::vector<double>& t,
                std::vector<VolumeCondition>* tighten) {
  Judgement j;
  j.indices = indexSet(latticeDoses(c, pr.eval, t), pr.specs, c.prescription_Gy);
  for (std::size_t q = 0; q < pr.conditions.size(); ++q) {
    const DvhCriterion& k = pr.all[pr.conditions[q].criterion];
    const std::string key = k.structure + "_" + k.index;
    const double miss = q == 0 && k.limit <= 0.0 ? 0.0 : excess(k, j.indices.at(key));
    const bool is_v = k.index[0] == 'V';
    if (miss <= (is_v ? 0.1 : 0.02))
      continue;
    j.violated.push_back(describe(k) + " (" + number(j.indices.at(key).value) + ")");
    if (tighten != nullptr) {
      // Tighten by what the evaluation lattice shows (the MIP's points under-sample it).
      VolumeCondition& v = (*tighten)[q];
      const double step = (v.at_most ? -1.0 : 1.0) * miss;
      (is_v ? v.budget_pct : v.level_Gy) += step;
      v.budget_pct = std::clamp(v.budget_pct, 0.0, 100.0);
      v.level_Gy = std::max(v.level_Gy, 0.0);
    }
  }
  j.v100_pct = j.indices.at(pr.target_name + "_V100").value;
  return j;
}

/// Records plan t with its judgement in r.
void record(const Problem& pr, const std::vector<double>& t, Judgement j, const DvhPlanOptions& o,
            DvhPlanResult* r) {
  r->times_s = t;
  r->indices = std::move(j.indices);
  r->violated = std::move(j.violated);
  r->v100_pct = j.v100_pct;
  r->mip_v100_pct = coveredPct(pr.eval, pr.conditions[0], t);
  r->objective = objectiveOf(pr.eval, pr.conditions, t, pr.total_time_s, o);
}

/// The MIP (IPIP-style freeing heuristic, then CBC when cbc_seconds > 0) on a coarse lattice,
/// re-solved with conditions tightened by what the evaluation lattice shows.
void planByMip(const HdrCase& c, const Tg43Source& source, const Problem& pr,
               const DvhPlanOptions& o, const CpuStopwatch& cpu, DvhPlanResult* r) {
  std::vector<int> structures;
  for (const VolumeCondition& v : pr.conditions)
    structures.push_back(v.structure);
  const PlanPoints points =
      planPoints(c, source, structures, o.plan_spacing_m, o.max_points_per_structure, true);
  // Reference plan for choosing which organ points need a binary: equal times, target mean Rx.
  const Eigen::VectorXd reference_Gy = points.d.rowwise().sum() * pr.equal_time_s;
  std::vector<VolumeCondition> conditions = pr.conditions;
  int best_violations = 1 << 30;
  for (int round = 0; round < o.rounds; ++round) {
    const double left = o.max_seconds - cpu.seconds();
    if (round > 0 && left < 0.5)
      break;
    const CpuStopwatch round_cpu(kProcess);
    const std::vector<double> start =
        freeingHeuristic(points, conditions, pr.total_time_s, o, o.heuristic_rounds);
    const double cbc = std::min(o.cbc_seconds, left / (o.rounds - round) - round_cpu.seconds());
    const MipSolution m =
        solveMip(points, conditions, pr.total_time_s, reference_Gy, o, start, cbc);
    ++r->rounds;
    if (!m.found)
      continue;
    Judgement j = judge(c, pr, m.times_s, &conditions);
    const int nv = static_cast<int>(j.violated.size());
    if (nv < best_violations || (nv == best_violations && j.v100_pct > r->v100_pct)) {
      best_violations = nv;
      const bool done = j.violated.empty();
      record(pr, m.times_s, std::move(j), o, r);
      r->mip_gap_pct = m.gap_pct;
      r->mip_optimal = m.optimal;
      r->mip_bound_known = m.bound_known;
      r->binaries = m.binaries;
      r->rows = m.rows;
      if (done)
        break;
    }
  }
}

/// The descent on the criteria over the evaluation lattice (descendOnCriteria), from the case's
/// own times, the IPSA LP's and equal times; with cbc_seconds > 0, CBC then bounds it on the
/// same points.
void planByDescent(const HdrCase& c, const Tg43Source& source, const Problem& pr,
                   const DvhPlanOptions& o, const CpuStopwatch& cpu, DvhPlanResult* r) {
  std::vector<std::vector<double>> starts;
  if (c.dwell_times_s.size() == c.dwells.size())
    starts.push_back(c.dwell_times_s);
  if (!c.points.empty()) {
    const DwellResult lp = optimizeLp(c, doseRateMatrix(c, source));
    if (lp.ok())
      starts.push_back(lp.times_s);
  }
  starts.emplace_back(c.dwells.size(), pr.equal_time_s);
  const dvh_model::DescentResult dr = dvh_model::descendOnCriteria(
      pr.eval, pr.conditions, pr.total_time_s, starts, o, o.max_seconds - cpu.seconds());
  r->rounds = 1;
  r->descent_iterations = dr.iterations;
  r->descent_objective = dr.objective;
  r->start_objective = dr.start_objective;
  std::vector<double> t = dr.times_s;
  if (t.empty())
    return;
  if (o.cbc_seconds > 0.0) {
    const Eigen::VectorXd reference_Gy = pr.eval.d.rowwise().sum() * pr.equal_time_s;
    const MipSolution m =
        solveMip(pr.eval, pr.conditions, pr.total_time_s, reference_Gy, o, t, o.cbc_seconds);
    t = m.times_s;
    r->mip_gap_pct = m.gap_pct;
    r->mip_optimal = m.optimal;
    r->mip_bound_known = m.bound_known;
    r->binaries = m.binaries;
    r->rows = m.rows;
  }
  record(pr, t, judge(c, pr, t, nullptr), o, r);
}

}  // namespace

DvhPlanResult optimizeDvh(const HdrCase& c, const Tg43Source& source,
                          const std::vector<DvhCriterion>& criteria, const DvhPlanOptions& o) {
  const auto t0 = Clock::now();
  const CpuStopwatch cpu(kProcess);
  if (c.dwells.empty())
    throw std::invalid_argument("optimizeDvh: case '" + c.name + "' has no dwell positions");
  if (!(o.plan_spacing_m > 0.0) || !(o.eval_spacing_m > 0.0) || !(o.max_seconds > 0.0) ||
      o.rounds < 1 || !(o.violation_penalty > 0.0))
    throw std::invalid_argument(
        "optimizeDvh: spacings, time limit, rounds and penalty must be > 0");
  if (o.method != "descent" && o.method != "mip")
    throw std::invalid_argument("optimizeDvh: method '" + o.method + "': expected descent or mip");
  DvhPlanResult r;
  const Problem pr = setUp(c, source, criteria, o, &r.notes);
  r.points = static_cast<int>(pr.eval.d.rows());
  r.setup_cpu_seconds = cpu.seconds();
  if (c.dwell_times_s.size() == c.dwells.size()) {
    // The case's own dwell times on the planner's points: a plan the planner should match.
    r.case_times_objective =
        objectiveOf(pr.eval, pr.conditions, c.dwell_times_s, pr.total_time_s, o);
    r.case_times_v100_pct = coveredPct(pr.eval, pr.conditions[0], c.dwell_times_s);
  }
  if (o.method == "mip")
    planByMip(c, source, pr, o, cpu, &r);
  else
    planByDescent(c, source, pr, o, cpu, &r);
  r.seconds = since(t0);
  r.cpu_seconds = cpu.seconds();
  if (r.times_s.empty()) {
    r.status = "no plan found within " + number(o.max_seconds) + " s";
    return r;
  }
  const double total = std::accumulate(r.times_s.begin(), r.times_s.end(), 0.0);
  if (total > 0.99 * pr.total_time_s)
    r.notes.push_back("the plan reaches the total-time bound of " + number(pr.total_time_s) + " s");
  return r;
}

}  // namespace needle_guidance::dose
