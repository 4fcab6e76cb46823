// Benchmark of HDR dwell-time optimisation (dissertation 6.3): a seeded cohort of 20 synthetic
// prostate cases; per case the LP (Clp) and the simulated-annealing baseline, their objectives,
// times and dosimetric indices; the LP-vs-SA table of 6.3 (paired t-test); SA's objective gap
// against its iterations; the LP's objective error and time against dose-point density; DVHs.
// Then the dose-volume planner (dvh_optimization.h) per case: its plan on the default criteria,
// whether it dominates the annealing plan (the cohort's stand-in for a clinical plan) on every
// defined index, the indices that prevent it, and the index change when the case is turned.
// Usage: bench_hdr --out DIR [--quick]
#include <Eigen/Geometry>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <iostream>
#include <map>
#include <numeric>
#include <sstream>
#include <string>
#include <vector>

#include "hdr_validation.h"
#include "needle_guidance/dose/dicom_case.h"
#include "needle_guidance/dose/dose_indices.h"
#include "needle_guidance/dose/dvh_comparison.h"
#include "needle_guidance/dose/dwell_optimization.h"
#include "needle_guidance/dose/plan_robustness.h"
#include "needle_guidance/dose/prostate_case.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/statistics.h"
#include "needle_guidance/report/table.h"

namespace ng = needle_guidance;
namespace dose = ng::dose;

namespace {

constexpr const char* kSource = "microselectron_v2_hdr";

using ng::report::mean;
using ng::report::median;
using ng::report::sampleSd;

/// Regularised incomplete beta I_x(a, b) by its continued fraction (Lentz), for the t-test.
double incompleteBeta(double a, double b, double x) {
  if (x <= 0.0)
    return 0.0;
  if (x >= 1.0)
    return 1.0;
  if (x > (a + 1.0) / (a + b + 2.0))
    return 1.0 - incompleteBeta(b, a, 1.0 - x);
  const double front = std::exp(std::lgamma(a + b) - std::lgamma(a) - std::lgamma(b) +
                                a * std::log(x) + b * std::log(1.0 - x)) /
                       a;
  double f = 1.0, c = 1.0, d = 0.0;
  for (int i = 0; i <= 400; ++i) {
    const int m = i / 2;
    double numerator;
    if (i == 0)
      numerator = 1.0;
    else if (i % 2 == 0)
      numerator = (m * (b - m) * x) / ((a + 2.0 * m - 1.0) * (a + 2.0 * m));
    else
      numerator = -((a + m) * (a + b + m) * x) / ((a + 2.0 * m) * (a + 2.0 * m + 1.0));
    d = 1.0 + numerator * d;
    d = std::abs(d) < 1e-30 ? 1e-30 : d;
    d = 1.0 / d;
    c = 1.0 + numerator / c;
    c = std::abs(c) < 1e-30 ? 1e-30 : c;
    f *= c * d;
    if (std::abs(1.0 - c * d) < 1e-12)
      break;
  }
  return front * (f - 1.0);
}

/// Two-sided p-value of the paired t-test of differences v (0 differences: p = 1).
double pairedTTestP(const std::vector<double>& v) {
  const double s = sampleSd(v);
  if (v.size() < 2)
    return 1.0;
  if (s == 0.0)
    return mean(v) == 0.0 ? 1.0 : 0.0;
  const double t = mean(v) / (s / std::sqrt(static_cast<double>(v.size())));
  const double dof = static_cast<double>(v.size() - 1);
  return incompleteBeta(0.5 * dof, 0.5, dof / (dof + t * t));
}

/// Figures 6.5-6.6 for one case: the LP and SA DVHs, and the isodose lines of both plans on the
/// transverse slice through the gland's centre (CSV for plot_bench.py).
void writeDvhAndIsodose(const dose::HdrCase& hdr_case, const dose::Tg43Source& source,
                        const std::vector<double>& lp_times, const std::vector<double>& sa_times,
                        const std::string& out_dir) {
  const dose::HdrCase& c = hdr_case;
  ng::report::Table dvh({"dose_Gy", "volume_pct", "curve"}, 6);
  const double max_Gy = 2.0 * c.prescription_Gy;
  const int bins = 80;
  for (int method = 0; method < 2; ++method) {
    const auto doses = dose::structureDoses(c, source, method == 0 ? lp_times : sa_times);
    for (const auto& s : doses) {
      const auto curve = dose::cumulativeDvh(s, max_Gy, bins);
      for (int b = 0; b <= bins; ++b) {
        dvh.addRow({max_Gy * b / bins, curve[static_cast<std::size_t>(b)],
                    s.name + (method == 0 ? " LP" : " SA")});
      }
    }
  }
  dvh.writeCsv(out_dir + "/dvh.csv");
  // Isodose lines on the transverse slice through the gland's centre (figure 6.6).
  const dose::Structure& gland = c.structures.front();
  dose::Point3 lo, hi;
  gland.bounds(lo, hi);
  double z = gland.contours.front().z_m;
  for (const auto& contour : gland.contours) {
    if (std::abs(contour.z_m - 0.5 * (lo.z() + hi.z())) < std::abs(z - 0.5 * (lo.z() + hi.z())))
      z = contour.z_m;
  }
  ng::report::Table outlines({"structure", "contour", "x_mm", "y_mm"}, 6);
  for (const auto& s : c.structures) {
    for (std::size_t k = 0; k < s.contours.size(); ++k) {
      if (std::abs(s.contours[k].z_m - z) < 1e-9) {
        for (const auto& p : s.contours[k].xy_m) {
          outlines.addRow({s.name, double(k), 1e3 * p.x(), 1e3 * p.y()});
        }
      }
    }
  }
  outlines.writeCsv(out_dir + "/isodose_outlines.csv");
  ng::report::Table catheters({"x_mm", "y_mm"}, 6);
  for (const auto& dw : c.dwells) {
    if (std::abs(dw.position_m.z() - z) < 2.5e-3)
      catheters.addRow({1e3 * dw.position_m.x(), 1e3 * dw.position_m.y()});
  }
  catheters.writeCsv(out_dir + "/isodose_dwells.csv");
  for (int method = 0; method < 2; ++method) {
    const auto& times = method == 0 ? lp_times : sa_times;
    ng::report::Table grid({"x_mm", "y_mm", "dose_pct"}, 5);
    for (double y = lo.y() - 0.02; y <= hi.y() + 0.02 + 1e-9; y += 1e-3) {
      for (double x = lo.x() - 0.02; x <= hi.x() + 0.02 + 1e-9; x += 1e-3) {
        const double total = dose::doseAt(c, source, times, dose::Point3(x, y, z));
        grid.addRow({1e3 * x, 1e3 * y, 100.0 * total / c.prescription_Gy});
      }
    }
    grid.writeCsv(out_dir + (method == 0 ? "/isodose_lp.csv" : "/isodose_sa.csv"));
  }
}

/// Simulated annealing's objective gap to the LP optimum against its iteration count.
ng::report::Table annealingConvergence(const dose::HdrCase& c, const Eigen::MatrixXd& d,
                                       double optimum, bool quick) {
  ng::report::Table sa_conv({"iterations", "seconds", "gap_pct"}, 6);
  const std::vector<long> iterations =
      quick ? std::vector<long>{1000, 10000, 100000}
            : std::vector<long>{1000, 3000, 10000, 30000, 100000, 300000};
  for (long it : iterations) {
    dose::AnnealingOptions o;
    o.iterations = it;
    const auto r = dose::optimizeAnnealing(c, d, o);
    sa_conv.addRow({double(it), r.seconds, 100.0 * (r.objective - optimum) / optimum});
  }
  return sa_conv;
}

/// The LP's time against its objective error (evaluated on the densest point set) over the
/// dose-point count.
ng::report::Table pointDensity(const dose::HdrCase& base, const dose::Tg43Source& source,
                               bool quick) {
  ng::report::Table density({"points", "lp_s", "objective_error_pct"}, 6);
  const std::vector<double> factors =
      quick ? std::vector<double>{0.5, 1.0, 4.0} : std::vector<double>{0.25, 0.5, 1.0, 2.0, 4.0};
  auto withDensity = [&](double f) {
    dose::HdrCase c = base;
    dose::DosePointOptions o;
    o.seed = 7;
    o.surface_spacing_m = 4e-3 / std::sqrt(f);
    o.volume_points = static_cast<int>(1500 * f);
    o.min_per_structure = 10;
    c.points = dose::makeDosePoints(c, o);
    return c;
  };
  const dose::HdrCase reference = withDensity(factors.back());
  const Eigen::MatrixXd d_ref = dose::doseRateMatrix(reference, source);
  const dose::PenaltyModel pm_ref = dose::penaltyModel(reference);
  std::vector<std::pair<double, std::pair<double, double>>>
      rows;  // points, (time, objective on reference)
  double best = 0.0;
  for (double f : factors) {
    const dose::HdrCase c = withDensity(f);
    const auto r = dose::optimizeLp(c, dose::doseRateMatrix(c, source));
    const Eigen::VectorXd t = Eigen::Map<const Eigen::VectorXd>(
        r.times_s.data(), static_cast<Eigen::Index>(r.times_s.size()));
    const double e_ref = pm_ref(d_ref * t);
    rows.push_back({double(c.points.size()), {r.seconds, e_ref}});
    best = e_ref;  // the densest set is last: its own optimum
  }
  for (const auto& [points, te] : rows) {
    density.addRow({points, te.first, 100.0 * (te.second - best) / best});
  }
  return density;
}

/// The figures plot_bench.py draws from the CSVs.
constexpr const char* kPlots =
    R"json([{"csv": "sa_convergence.csv", "x": "seconds", "y": "gap_pct", "annotate": "iterations", "logx": true,
  "logy": true, "title": "Simulated annealing: objective gap to the LP optimum vs time", "png": "sa_convergence.png"},
 {"csv": "point_density.csv", "x": "lp_s", "y": "objective_error_pct", "annotate": "points", "points": true,
  "title": "LP time vs objective error (on the densest points) over dose-point count", "png": "point_density.png"},
 {"csv": "hdr.csv", "x": "lp_objective", "y": "sa_objective", "annotate": "case", "points": true,
  "title": "Objective per case: LP (optimum) vs simulated annealing", "png": "lp_vs_sa.png"},
 {"kind": "isodose", "csv": "isodose_lp.csv", "contours": "isodose_outlines.csv", "points_csv": "isodose_dwells.csv",
  "levels": [50, 100, 150, 200], "invert_y": true, "title": "Isodose lines (% Rx), LP plan, mid-gland slice (anterior up)", "png": "isodose_lp.png"},
 {"kind": "isodose", "csv": "isodose_sa.csv", "contours": "isodose_outlines.csv", "points_csv": "isodose_dwells.csv",
  "levels": [50, 100, 150, 200], "invert_y": true, "title": "Isodose lines (% Rx), SA plan, mid-gland slice (anterior up)", "png": "isodose_sa.png"},
 {"csv": "dvh.csv", "x": "dose_Gy", "y": "volume_pct", "group": "curve",
  "title": "Cumulative DVH, LP vs SA (case with the largest index difference)", "png": "dvh.png"}])json";

/// Volume of each organ inside the target's contours ("bladder 1.23 cm3"; organs with none are
/// left out): the target's coverage needs about the prescription there, so an organ criterion
/// below it on at least that much volume (D2cc, D0.1cc, V75) cannot hold with full coverage.
std::string organVolumeInTarget(const dose::HdrCase& c, double spacing_m) {
  const auto target = std::find_if(c.structures.begin(), c.structures.end(), [](const auto& s) {
    return s.role == dose::StructureRole::kTarget;
  });
  std::string out;
  if (target == c.structures.end())
    return out;
  for (const dose::Structure& s : c.structures) {
    if (s.role == dose::StructureRole::kTarget)
      continue;
    const dose::VolumeSample v = dose::sampleStructure(s, dose::latticeSpacing(s, spacing_m));
    double inside_m3 = 0.0;
    for (std::size_t i = 0; i < v.points_m.size(); ++i)
      inside_m3 += target->contains(v.points_m[i]) ? v.volume_m3[i] : 0.0;
    if (inside_m3 > 0.0) {
      std::ostringstream text;
      text.precision(3);
      text << s.name << " " << inside_m3 * 1e6 << " cm3";
      out += (out.empty() ? "" : "; ") + text.str();
    }
  }
  return out;
}

/// The dose-volume planner on every cohort case against its annealing plan; rows into
/// dvh_cohort.csv, headline figures as JSON members.
std::string dvhCohort(const std::vector<dose::HdrCase>& cohort, const dose::Tg43Source& source,
                      const std::vector<std::vector<double>>& sa_times,
                      const std::string& out_dir) {
  constexpr double kSpacing_m = 1e-3;  // index lattice of the cohort (prostates up to 103 cc)
  dose::DvhPlanOptions o;
  o.eval_spacing_m = kSpacing_m;
  o.max_seconds = 3.0;  // per plan: 20 cases x 2 plans on a shared 2-core machine
  ng::report::Table t(
      {"case", "dvh_plan_s", "dvh_v100_pct", "dvh_urethra_D10_Gy", "dvh_criteria_met",
       "sa_v100_pct", "sa_urethra_D10_Gy", "dominating_plan_s", "sa_dominated", "prevented_by",
       "dvh_criteria_giving_way", "organ_in_target", "rotation_change_Gy", "rotation_change_pp"},
      6);
  std::vector<double> plan_s, plan_cpu_s, dom_s, dom_cpu_s, v100, v100_gain, rot_gy, rot_pp;
  int dominated = 0, met = 0;
  std::map<std::string, int> preventing, giving_way;
  for (std::size_t k = 0; k < cohort.size(); ++k) {
    const dose::HdrCase& c = cohort[k];
    const double rx = c.prescription_Gy;
    const dose::DvhPlanResult r = dose::optimizeDvh(c, source, dose::defaultDvhCriteria(rx), o);
    if (!r.ok())
      throw std::runtime_error(c.name + ": dose-volume planning: " + r.status);
    const auto sa =
        dose::comparisonIndexSet(dose::structureDoses(c, source, sa_times[k], kSpacing_m), rx);
    const auto dvh =
        dose::comparisonIndexSet(dose::structureDoses(c, source, r.times_s, kSpacing_m), rx);
    dose::HdrCase with_sa = c;  // the annealing times: a start the planner never does worse than
    with_sa.dwell_times_s = sa_times[k];
    const dose::Dominance d = dose::dominate(with_sa, source, sa, "prostate", o);
    Eigen::Isometry3d turn = Eigen::Isometry3d::Identity();
    turn.linear() = Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    turn.translation() = Eigen::Vector3d(41.5e-3, -17.3e-3, 63e-3);
    const auto turned = dose::comparisonIndexSet(
        dose::structureDoses(dose::transformedCase(c, turn), source, sa_times[k], kSpacing_m), rx);
    const dose::IndexChange ch = dose::indexChange(sa, turned);
    std::string prevented;
    for (const auto& w : d.worse) {
      const std::string key = w.substr(0, w.find(' '));
      ++preventing[key];
      prevented += (prevented.empty() ? "" : "; ") + w;
    }
    // The criteria the plan breaks, each with the value it reached ("urethra V125 <= 10.00 %
    // (12.31)"); counted per criterion as structure_index.
    std::string broken;
    for (const auto& v : r.violated) {
      const std::size_t space = v.find(' ');
      ++giving_way[v.substr(0, space) + "_" +
                   v.substr(space + 1, v.find(' ', space + 1) - space - 1)];
      broken += (broken.empty() ? "" : "; ") + v;
    }
    const auto value = [](const std::map<std::string, dose::DoseVolumeIndex>& m, const char* key) {
      const auto it = m.find(key);
      return it != m.end() && it->second.defined ? it->second.value : std::nan("");
    };
    t.addRow({c.name, r.seconds, r.v100_pct, value(dvh, "urethra_D10"),
              r.violated.empty() ? 1.0 : 0.0, value(sa, "prostate_V100"), value(sa, "urethra_D10"),
              d.plan.seconds, d.dominated ? 1.0 : 0.0, prevented, broken,
              organVolumeInTarget(c, kSpacing_m), ch.dose_Gy, ch.volume_pp});
    plan_s.push_back(r.seconds);
    plan_cpu_s.push_back(r.cpu_seconds);
    dom_s.push_back(d.plan.seconds);
    dom_cpu_s.push_back(d.plan.cpu_seconds);
    if (d.dominated)
      v100_gain.push_back(value(d.indices, "prostate_V100") - value(sa, "prostate_V100"));
    v100.push_back(r.v100_pct);
    rot_gy.push_back(ch.dose_Gy);
    rot_pp.push_back(ch.volume_pp);
    dominated += d.dominated ? 1 : 0;
    met += r.violated.empty() ? 1 : 0;
    std::cout << c.name << ": DVH plan V100 " << r.v100_pct << " % in " << r.seconds
              << " s; annealing plan "
              << (d.dominated ? "dominated" : "not dominated: " + prevented) << "\n"
              << std::flush;
  }
  t.writeCsv(out_dir + "/dvh_cohort.csv");
  std::ostringstream json;
  json << ",\n  \"dvh_plan_s_median\": " << median(plan_s)
       << ",\n  \"dvh_plan_s_max\": " << *std::max_element(plan_s.begin(), plan_s.end())
       << ",\n  \"dvh_plan_cpu_s_median\": " << median(plan_cpu_s)
       << ",\n  \"dvh_plan_cpu_s_max\": " << *std::max_element(plan_cpu_s.begin(), plan_cpu_s.end())
       << ",\n  \"dominating_plan_s_max\": " << *std::max_element(dom_s.begin(), dom_s.end())
       << ",\n  \"dominating_plan_cpu_s_max\": "
       << *std::max_element(dom_cpu_s.begin(), dom_cpu_s.end())
       << ",\n  \"dominating_v100_gain_pp_median\": "
       << (v100_gain.empty() ? std::string("null") : std::to_string(median(v100_gain)))
       << ",\n  \"dvh_cases\": " << cohort.size()
       << ",\n  \"dvh_v100_pct_median\": " << median(v100)
       << ",\n  \"dvh_criteria_met_cases\": " << met
       << ",\n  \"sa_dominated_dvh_cases\": " << dominated
       << ",\n  \"index_rotation_change_max_gy\": "
       << *std::max_element(rot_gy.begin(), rot_gy.end())
       << ",\n  \"index_rotation_change_max_pp\": "
       << *std::max_element(rot_pp.begin(), rot_pp.end()) << ",\n  \"dominance_prevented_by\": {";
  bool first = true;
  for (const auto& [key, n] : preventing) {
    json << (first ? "" : ", ") << "\"" << key << "\": " << n;
    first = false;
  }
  json << "},\n  \"dvh_criteria_giving_way\": {";
  first = true;
  for (const auto& [key, n] : giving_way) {
    json << (first ? "" : ", ") << "\"" << key << "\": " << n;
    first = false;
  }
  json << "}";
  return json.str();
}

}  // namespace

int main(int argc, char** argv) {
  const auto args = ng::report::parseBenchArgs(argc, argv, "bench_hdr");
  if (!args) {
    return 2;
  }
  try {
    const dose::Tg43Source source = dose::loadSource(kSource);
    const int n_cases = args->quick ? 3 : 20;
    const auto cohort = dose::syntheticCohort(n_cases, 1);
    ng::report::Table cases({"case", "prostate_cc", "catheters", "dwells", "points", "matrix_s",
                             "lp_s", "lp_iterations", "lp_objective", "sa_s", "sa_objective",
                             "sa_gap_pct", "lp_total_time_s", "sa_total_time_s"},
                            6);
    std::vector<double> lp_s, sa_s, lp_obj, sa_obj, gaps, matrix_s;
    int lp_le_sa = 0;
    std::map<std::string, std::vector<double>> improvement;  // index -> LP minus SA, per case
    std::map<std::string, std::vector<double>> lp_index_values, sa_index_values;
    ng::report::Table index_table({"case", "index", "lp", "sa"}, 6);
    dose::AnnealingOptions sa_options;  // 100,000 moves, seed 1
    std::size_t dvh_case = 0;
    double dvh_case_diff = -1.0;
    std::vector<std::vector<double>> lp_times_all, sa_times_all;
    Eigen::MatrixXd first_matrix;
    for (int k = 0; k < n_cases; ++k) {
      const dose::HdrCase& c = cohort[static_cast<std::size_t>(k)];
      const auto t0 = std::chrono::steady_clock::now();
      const Eigen::MatrixXd d = dose::doseRateMatrix(c, source);
      if (k == 0)
        first_matrix = d;
      const double m_s =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      const dose::DwellResult lp = dose::optimizeLp(c, d);
      sa_options.seed = static_cast<unsigned>(k + 1);
      const dose::DwellResult sa = dose::optimizeAnnealing(c, d, sa_options);
      if (!lp.ok()) {
        throw std::runtime_error(c.name + ": LP " + lp.status);
      }
      const double gap = 100.0 * (sa.objective - lp.objective) / std::max(1e-12, sa.objective);
      lp_le_sa += lp.objective <= sa.objective * (1.0 + 1e-9) + 1e-12 ? 1 : 0;
      const auto lp_doses = dose::structureDoses(c, source, lp.times_s);
      const auto sa_doses = dose::structureDoses(c, source, sa.times_s);
      const auto lp_idx = dose::dosimetricIndices(lp_doses, c.prescription_Gy);
      const auto sa_idx = dose::dosimetricIndices(sa_doses, c.prescription_Gy);
      double largest = 0.0;
      for (const auto& [name, value] : lp_idx) {
        const double s = sa_idx.at(name);
        // Improvement as in Table 6.3: positive = better for LP (more coverage of the target,
        // less dose to organs at risk and less prostate V150).
        const bool higher_better = name == "prostate_V100" || name == "prostate_D90";
        improvement[name].push_back(higher_better ? value - s : s - value);
        lp_index_values[name].push_back(value);
        sa_index_values[name].push_back(s);
        index_table.addRow({c.name, name, value, s});
        if (name.find("_V") != std::string::npos)
          largest = std::max(largest, std::abs(value - s));
      }
      if (largest > dvh_case_diff) {
        dvh_case_diff = largest;
        dvh_case = static_cast<std::size_t>(k);
      }
      lp_times_all.push_back(lp.times_s);
      sa_times_all.push_back(sa.times_s);
      const double cc = 1e6 * c.structures.front().volume_m3();
      const double lp_total = std::accumulate(lp.times_s.begin(), lp.times_s.end(), 0.0);
      const double sa_total = std::accumulate(sa.times_s.begin(), sa.times_s.end(), 0.0);
      cases.addRow({c.name, cc, double(c.catheters.size()), double(c.dwells.size()),
                    double(c.points.size()), m_s, lp.seconds, double(lp.iterations), lp.objective,
                    sa.seconds, sa.objective, gap, lp_total, sa_total});
      lp_s.push_back(lp.seconds);
      sa_s.push_back(sa.seconds);
      lp_obj.push_back(lp.objective);
      sa_obj.push_back(sa.objective);
      gaps.push_back(gap);
      matrix_s.push_back(m_s);
      std::cout << c.name << ": " << cc << " cc, " << c.catheters.size() << " catheters, "
                << c.dwells.size() << " dwells, " << c.points.size() << " points; LP "
                << lp.objective << " in " << lp.seconds << " s (" << lp.iterations << " it), SA "
                << sa.objective << " in " << sa.seconds << " s; SA gap " << gap << " %\n"
                << std::flush;
    }
    cases.writeCsv(args->out_dir + "/hdr.csv");
    index_table.writeCsv(args->out_dir + "/indices.csv");

    // Table 6.3: improvement of LP over SA per index.
    ng::report::Table comparison({"index", "lp_mean", "sa_mean", "improvement_mean",
                                  "improvement_min", "improvement_max", "p_paired_t"},
                                 6);
    for (const auto& [name, values] : improvement) {
      comparison.addRow({name, mean(lp_index_values[name]), mean(sa_index_values[name]),
                         mean(values), *std::min_element(values.begin(), values.end()),
                         *std::max_element(values.begin(), values.end()), pairedTTestP(values)});
    }
    std::vector<double> objective_diff;
    for (std::size_t i = 0; i < lp_obj.size(); ++i)
      objective_diff.push_back(sa_obj[i] - lp_obj[i]);
    comparison.addRow({std::string("objective_E"), mean(lp_obj), mean(sa_obj), mean(objective_diff),
                       *std::min_element(objective_diff.begin(), objective_diff.end()),
                       *std::max_element(objective_diff.begin(), objective_diff.end()),
                       pairedTTestP(objective_diff)});
    comparison.writeCsv(args->out_dir + "/lp_vs_sa.csv");

    // DVHs and isodose lines of the case whose indices differ most between LP and SA.
    writeDvhAndIsodose(cohort[dvh_case], source, lp_times_all[dvh_case], sa_times_all[dvh_case],
                       args->out_dir);

    // SA: objective gap to the LP optimum against iterations (case 1).
    const ng::report::Table sa_conv =
        annealingConvergence(cohort.front(), first_matrix, lp_obj.front(), args->quick);
    sa_conv.writeCsv(args->out_dir + "/sa_convergence.csv");

    // LP: dose-point density against objective error, evaluated on the densest point set.
    const ng::report::Table density = pointDensity(cohort.front(), source, args->quick);
    density.writeCsv(args->out_dir + "/point_density.csv");

    // Real-plan validation (when the third-party data is on this machine).
    const RealPlanFigures real = validateRealPlan();
    const std::string dvh_json = dvhCohort(cohort, source, sa_times_all, args->out_dir);

    std::ostringstream json;
    json.precision(6);
    json << "{\n  \"benchmark\": \"hdr\",\n  \"source\": \"" << kSource
         << "\",\n  \"quick\": " << (args->quick ? "true" : "false")
         << ",\n  \"n_cases\": " << n_cases << ",\n  \"lp_s_median\": " << median(lp_s)
         << ",\n  \"lp_s_max\": " << *std::max_element(lp_s.begin(), lp_s.end())
         << ",\n  \"sa_s_median\": " << median(sa_s)
         << ",\n  \"matrix_s_median\": " << median(matrix_s)
         << ",\n  \"lp_objective_mean\": " << mean(lp_obj)
         << ",\n  \"sa_objective_mean\": " << mean(sa_obj)
         << ",\n  \"sa_gap_pct_mean\": " << mean(gaps)
         << ",\n  \"sa_gap_pct_min\": " << *std::min_element(gaps.begin(), gaps.end())
         << ",\n  \"sa_gap_pct_max\": " << *std::max_element(gaps.begin(), gaps.end())
         << ",\n  \"objective_p_paired_t\": " << pairedTTestP(objective_diff)
         << ",\n  \"lp_le_sa_cases\": " << lp_le_sa
         << ",\n  \"real_plan_available\": " << (real.available ? "true" : "false")
         << ",\n  \"gamma_3pct3mm\": "
         << (real.available ? std::to_string(real.gamma_3pct3mm) : "null")
         << ",\n  \"gamma_2pct2mm\": "
         << (real.available ? std::to_string(real.gamma_2pct2mm) : "null")
         << ",\n  \"real_plan_median_relative_difference\": "
         << (real.available ? std::to_string(real.median_relative_difference) : "null")
         << ",\n  \"misregistered_plan_flagged\": "
         << (real.available ? (real.misregistered_flagged ? "true" : "false") : "null") << dvh_json
         << "\n}\n";
    ng::report::writeTextFile(args->out_dir + "/summary.json", json.str());
    ng::report::writeTextFile(args->out_dir + "/plot.json", kPlots);
    std::cout << cases.toText() << comparison.toText() << json.str();
  } catch (const std::exception& e) {
    std::cerr << "bench_hdr: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
