// Benchmark of HDR planning from a DICOM-RT case: import (dicom_case.h), dose-rate matrix, LP,
// export (RS/RP/RD.dcm) and their times; the clinical plan's and the LP's indices on the same
// engine, points and index lattice; both DVHs; the urethra-weight front with the clinical plan
// as a point; the export checked by dciodvfy, pydicom (scripts/check_rt_export.py), the round
// trip of the dwell times and our RTDOSE validation. Then the dose-volume planner
// (dvh_optimization.h): its plan, the plan that dominates the clinical one (or the indices that
// prevent it), its V100 / urethra D10 front, the indices' invariance to turning and moving the
// case, our indices from the RTDOSE against dicompyler-core and the stored DVHs
// (scripts/check_dvh_dicompyler.py), and every index's spread under +-1 mm catheter shifts.
// Runs on NG_SHARED_DATA/hdr_example_plan when present, else on synthetic case 1 written out as
// DICOM (its "clinical" plan = SA's).
// Usage: bench_hdr_dicom --out DIR [--quick]
#include <Eigen/Geometry>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/dose/dicom_case.h"
#include "needle_guidance/dose/dvh_comparison.h"
#include "needle_guidance/dose/dwell_optimization.h"
#include "needle_guidance/dose/plan_robustness.h"
#include "needle_guidance/package_paths.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/table.h"

namespace ng = needle_guidance;
namespace dose = ng::dose;
namespace fs = std::filesystem;

namespace {

double since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

/// Writes synthetic case 1 as RS/RP/RD.dcm with simulated-annealing times as its "clinical" plan.
void writeSyntheticDicom(const std::string& dir) {
  dose::SyntheticCaseOptions o;
  o.seed = 1;
  o.prescription_Gy = 9.5;
  dose::HdrCase c = dose::syntheticProstateCase(o);
  c.source = "gammamed_plus_hdr";
  const dose::Tg43Source source = dose::loadSource(c.source);
  dose::AnnealingOptions sa;
  sa.iterations = 20000;
  c.dwell_times_s = dose::optimizeAnnealing(c, dose::doseRateMatrix(c, source), sa).times_s;
  dose::DoseGrid g;
  Eigen::Vector3d lo, hi;
  c.structures.front().bounds(lo, hi);
  g.spacing_m = Eigen::Vector3d::Constant(2e-3);
  g.origin_m = lo - Eigen::Vector3d::Constant(10e-3);
  for (int a = 0; a < 3; ++a)
    g.sizes[a] = static_cast<int>((hi[a] - lo[a] + 20e-3) / 2e-3) + 1;
  for (int k = 0; k < g.sizes[2]; ++k)
    g.z_offsets_m.push_back(k * 2e-3);
  g.dose_Gy.assign(static_cast<std::size_t>(g.sizes[0]) * g.sizes[1] * g.sizes[2], 0.0);
  dose::exportDicomRtPlan(c, source, &g, dir);
}

/// Largest |t_ours - t_reimported| over dwell positions matched by position (1e9 if unmatched).
double roundTripError(const dose::HdrCase& ours, const std::string& dir) {
  const dose::HdrCase back =
      dose::importDicomRt((fs::path(dir) / "RP.dcm").string(), (fs::path(dir) / "RS.dcm").string());
  double worst = 0.0;
  for (std::size_t j = 0; j < ours.dwells.size(); ++j) {
    double best_d = 1e9, t = 0.0;
    for (std::size_t k = 0; k < back.dwells.size(); ++k) {
      const double d = (back.dwells[k].position_m - ours.dwells[j].position_m).norm();
      if (d < best_d) {
        best_d = d;
        t = back.dwell_times_s[k];
      }
    }
    worst = std::max(worst, best_d < 0.1e-3 ? std::abs(t - ours.dwell_times_s[j]) : 1e9);
  }
  return worst;
}

/// dciodvfy errors over the exported files (-1 if dciodvfy is not installed).
int dciodvfyErrors(const std::string& dir, const std::string& log) {
  if (std::system("command -v dciodvfy > /dev/null 2>&1") != 0)
    return -1;
  std::system(("rm -f '" + log + "'").c_str());
  for (const char* f : {"RS.dcm", "RP.dcm", "RD.dcm"}) {
    const fs::path p = fs::path(dir) / f;
    if (fs::exists(p))
      std::system(("dciodvfy '" + p.string() + "' >> '" + log + "' 2>&1").c_str());
  }
  std::ifstream in(log);
  int errors = 0;
  for (std::string line; std::getline(in, line);)
    errors += line.rfind("Error", 0) == 0 ? 1 : 0;
  return errors;
}

std::string jsonMap(const std::map<std::string, double>& m) {
  std::ostringstream o;
  o << "{";
  bool first = true;
  for (const auto& [k, v] : m) {
    o << (first ? "" : ", ") << "\"" << k << "\": " << ng::report::jsonNumber(v);
    first = false;
  }
  return o.str() + "}";
}

double at(const std::map<std::string, double>& m, const std::string& k) {
  const auto it = m.find(k);
  return it == m.end() ? std::nan("") : it->second;
}

constexpr double kEvalSpacing_m = 0.5e-3;  // index lattice (dose_indices.h)

/// CSV of an index set, undefined ones with their reason, and the same index on the dose grid's
/// own discretisation (on_grid; empty where undefined).
void writeIndexCsv(const std::map<std::string, dose::DoseVolumeIndex>& set,
                   const std::map<std::string, dose::DoseVolumeIndex>& on_grid, double rx,
                   const std::string& path) {
  std::ofstream out(path);
  out << "index,rx_gy,ours,ours_on_dose_grid,reason\n";
  for (const auto& [k, v] : set) {
    out << k << "," << rx << ",";
    if (v.defined)
      out << ng::report::jsonNumber(v.value, 6);
    out << ",";
    const auto it = on_grid.find(k);
    if (it != on_grid.end() && it->second.defined)
      out << ng::report::jsonNumber(it->second.value, 6);
    out << ",\"" << v.reason << "\"\n";
  }
}

/// Our indices from the RTDOSE as the lattice is refined: in-plane spacing 2 to 0.125 mm and
/// sample planes per contour slab 1 (at the contour, dicompyler's model) to 8, at exactly that
/// spacing (latticeSpacing's adaptation off). Rows spacing_mm, planes_per_slice, index, value
/// (empty where undefined).
void writeConvergenceCsv(const dose::DicomCase& dc, const dose::DoseGrid& grid,
                         const std::string& path) {
  std::ofstream out(path);
  out << "spacing_mm,planes_per_slice,index,value\n";
  double slice_m = 0.0;
  for (const dose::Structure& s : dc.clinical.structures)
    slice_m = std::max(slice_m, s.sliceSpacing());
  for (const double spacing_mm : {2.0, 1.0, 0.5, 0.25, 0.125}) {
    for (const int planes : {1, 2, 4, 8}) {
      const auto set = dose::comparisonIndexSet(
          dose::structureDosesFromGrid(dc.clinical, grid, spacing_mm * 1e-3,
                                       slice_m > 0.0 ? slice_m / planes : 0.0, false),
          dc.clinical.prescription_Gy);
      for (const auto& [k, v] : set) {
        out << spacing_mm << "," << planes << "," << k << ",";
        if (v.defined)
          out << ng::report::jsonNumber(v.value, 6);
        out << "\n";
      }
    }
  }
}

/// Our indices from the RTDOSE and dicompyler-core's (scripts/check_dvh_dicompyler.py); the
/// script's JSON line, or "" when it did not run (dicompyler-core missing or no RTDOSE).
std::string dicompylerCheck(const dose::DicomCase& dc, const std::string& dir,
                            const std::string& out_dir) {
  if (dc.files.dose.empty())
    return "";
  const dose::DoseGrid grid = dose::readRtDose(dc.files.dose);
  const auto ours = dose::comparisonIndexSet(
      dose::structureDosesFromGrid(dc.clinical, grid, kEvalSpacing_m), dc.clinical.prescription_Gy);
  const auto on_grid = dose::comparisonIndexSet(dose::structureDosesOnGridPixels(dc.clinical, grid),
                                                dc.clinical.prescription_Gy);
  writeIndexCsv(ours, on_grid, dc.clinical.prescription_Gy, out_dir + "/indices_rtdose_ours.csv");
  writeConvergenceCsv(dc, grid, out_dir + "/indices_convergence_ours.csv");
  const std::string json_path = out_dir + "/dicompyler.json";
  const int rc =
      std::system(("/usr/bin/python3 " + needle_guidance::packageDir().string() +
                   "/scripts/check_dvh_dicompyler.py '" + dir + "' '" + out_dir +
                   "/indices_rtdose_ours.csv' '" + out_dir + "/indices_vs_dicompyler.csv' '" +
                   out_dir + "/indices_convergence_ours.csv' '" + out_dir +
                   "/indices_convergence.csv' > '" + json_path + "' 2> /dev/null")
                      .c_str());
  if (rc != 0)
    return "";
  std::ifstream in(json_path);
  std::string line;
  std::getline(in, line);
  return line;
}

/// The number after "key": in a one-line JSON object (NaN if absent).
double jsonField(const std::string& json, const std::string& key) {
  const std::size_t at = json.find("\"" + key + "\":");
  return at == std::string::npos ? std::nan("") : std::atof(json.c_str() + at + key.size() + 3);
}

/// The case turned 90 degrees about z, 180 degrees about y, and moved; largest index changes
/// of the plan `times_s` (same times: the physics does not move) over the three copies.
dose::IndexChange rotationChange(const dose::HdrCase& c, const dose::Tg43Source& source,
                                 const std::vector<double>& times_s) {
  const auto indices = [&](const dose::HdrCase& x) {
    return dose::comparisonIndexSet(dose::structureDoses(x, source, times_s, kEvalSpacing_m),
                                    x.prescription_Gy);
  };
  const auto base = indices(c);
  dose::IndexChange worst;
  Eigen::Isometry3d turn_z = Eigen::Isometry3d::Identity(), turn_y = turn_z, move = turn_z;
  turn_z.linear() = Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  turn_y.linear() = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitY()).toRotationMatrix();
  move.translation() = Eigen::Vector3d(41.5e-3, -17.3e-3, 63e-3);
  for (const auto& pose : {turn_z, turn_y, move}) {
    const dose::IndexChange ch = dose::indexChange(base, indices(dose::transformedCase(c, pose)));
    if (ch.dose_Gy > worst.dose_Gy) {
      worst.dose_Gy = ch.dose_Gy;
      worst.worst_dose = ch.worst_dose;
    }
    if (ch.volume_pp > worst.volume_pp) {
      worst.volume_pp = ch.volume_pp;
      worst.worst_volume = ch.worst_volume;
    }
  }
  return worst;
}

/// Spread of every index under +-1 mm catheter shifts for each plan; rows into `table`, the
/// largest 5-95 % half-range of D [Gy] and V [pp] indices per plan into the JSON.
struct NamedPlan {
  std::string name;
  const dose::HdrCase* c;
  std::vector<double> times_s;
};
std::string robustness(const dose::Tg43Source& source, const std::vector<NamedPlan>& plans,
                       int samples, ng::report::Table& table) {
  std::ostringstream json;
  for (const auto& [name, c, times] : plans) {
    const auto spread =
        dose::shiftSpread(*c, source, times, dose::comparisonIndexSpecs(), 1e-3, samples, 1, 1e-3);
    double d_worst = 0.0, v_worst = 0.0;
    for (const auto& [k, sp] : spread) {
      table.addRow(
          {name, k, sp.nominal, sp.p5, sp.p95, sp.sd, sp.worst, static_cast<double>(sp.samples)});
      const double half = 0.5 * (sp.p95 - sp.p5);
      (k.find("_D") != std::string::npos ? d_worst : v_worst) =
          std::max(k.find("_D") != std::string::npos ? d_worst : v_worst, half);
    }
    json << ",\n  \"robust_" << name << "_d_halfrange_max_gy\": " << ng::report::jsonNumber(d_worst)
         << ",\n  \"robust_" << name
         << "_v_halfrange_max_pp\": " << ng::report::jsonNumber(v_worst);
  }
  return json.str();
}

std::string jsonList(const std::vector<std::string>& v) {
  std::string out = "[";
  for (std::size_t i = 0; i < v.size(); ++i)
    out += (i ? ", \"" : "\"") + v[i] + "\"";
  return out + "]";
}

/// JSON object of an index set: numbers, and null for undefined indices (reasons separately).
std::string jsonIndexSet(const std::map<std::string, dose::DoseVolumeIndex>& m) {
  std::ostringstream o;
  o << "{";
  bool first = true;
  for (const auto& [k, v] : m) {
    o << (first ? "" : ", ") << "\"" << k
      << "\": " << (v.defined ? ng::report::jsonNumber(v.value) : "null");
    first = false;
  }
  return o.str() + "}";
}

/// The dose-volume planner on the case: its plan on the case file's criteria, the plan that
/// dominates the clinical one (or the indices that prevent it), the V100 / urethra D10 front,
/// index invariance, the dicompyler-core check and the robustness table.
std::string dvhStudy(const dose::DicomCase& dc, const std::string& dir,
                     const dose::Tg43Source& source, const std::vector<double>& lp_times,
                     const ng::report::BenchArgs& args) {
  const dose::HdrCase& c = dc.planning;
  const double rx = c.prescription_Gy;
  dose::DvhPlanOptions options;
  options.eval_spacing_m = kEvalSpacing_m;
  const auto criteria = dose::defaultDvhCriteria(rx);
  const auto clinical = dose::comparisonIndexSet(
      dose::structureDoses(dc.clinical, source, dc.clinical.dwell_times_s, kEvalSpacing_m), rx);
  const auto clinical_fine = dose::comparisonIndexSet(
      dose::structureDoses(dc.clinical, source, dc.clinical.dwell_times_s, 0.25e-3), rx);
  const dose::IndexChange lattice = dose::indexChange(clinical, clinical_fine);
  // The clinical times on our dwells: a start the planner never does worse than.
  const dose::HdrCase with_clinical = dose::planningWithClinicalTimes(dc);
  const dose::DvhPlanResult plan = dose::optimizeDvh(with_clinical, source, criteria, options);
  if (!plan.ok())
    throw std::runtime_error("dose-volume planning: " + plan.status);
  const auto ours =
      dose::comparisonIndexSet(dose::structureDoses(c, source, plan.times_s, kEvalSpacing_m), rx);
  const dose::Dominance dom = dose::dominate(with_clinical, source, clinical, "prostate", options);
  // Where the dominating plan is strictly better ("clinical worse": reference and ours swapped).
  const std::vector<std::string> better =
      dom.dominated ? dose::worseIndices(clinical, dom.indices, "prostate")
                    : std::vector<std::string>{};
  // Front: urethra D10 limit swept around the clinical plan's, the rectum at its criteria.
  std::vector<double> limits;
  const double u0 = clinical.count("urethra_D10") && clinical.at("urethra_D10").defined
                        ? clinical.at("urethra_D10").value
                        : 1.1 * rx;
  for (const double f : (args.quick ? std::vector<double>{0.9, 1.0, 1.1}
                                    : std::vector<double>{0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.2}))
    limits.push_back(f * u0);
  dose::DvhPlanOptions front_options = options;
  front_options.max_seconds = 4.0;
  const auto front = dose::dvhFront(with_clinical, source, criteria, limits, front_options);
  ng::report::Table ft({"plan", "urethra_D10_limit_Gy", "urethra_D10_Gy", "prostate_V100_pct",
                        "plan_s", "criteria_met"},
                       6);
  for (const auto& p : front)
    ft.addRow({std::string("DVH plan"), p.urethra_d10_limit_Gy, p.urethra_d10_Gy, p.v100_pct,
               p.seconds, p.criteria_met ? 1.0 : 0.0});
  const auto value = [](const std::map<std::string, dose::DoseVolumeIndex>& m, const char* k) {
    const auto it = m.find(k);
    return it != m.end() && it->second.defined ? it->second.value : std::nan("");
  };
  ft.addRow({std::string("clinical"), 0.0, value(clinical, "urethra_D10"),
             value(clinical, "prostate_V100"), 0.0, 0.0});
  if (dom.plan.ok())
    ft.addRow({std::string("dominating"), 0.0, value(dom.indices, "urethra_D10"),
               value(dom.indices, "prostate_V100"), dom.plan.seconds, dom.dominated ? 1.0 : 0.0});
  ft.writeCsv(args.out_dir + "/dvh_front.csv");
  const dose::IndexChange rot_clinical =
      rotationChange(dc.clinical, source, dc.clinical.dwell_times_s);
  const dose::IndexChange rot_dvh = rotationChange(c, source, plan.times_s);
  const std::string dpy = dicompylerCheck(dc, dir, args.out_dir);
  ng::report::Table rt({"plan", "index", "nominal", "change_p5", "change_p95", "change_sd",
                        "change_worst", "samples"},
                       6);
  const std::string robust_json = robustness(source,
                                             {{"clinical", &dc.clinical, dc.clinical.dwell_times_s},
                                              {"lp", &c, lp_times},
                                              {"dvh", &c, plan.times_s}},
                                             args.quick ? 5 : 20, rt);
  rt.writeCsv(args.out_dir + "/robustness.csv");
  std::ostringstream json;
  using ng::report::jsonNumber;
  json << ",\n  \"dvh_plan_s\": " << jsonNumber(plan.seconds)
       << ",\n  \"dvh_v100_pct\": " << jsonNumber(plan.v100_pct)
       << ",\n  \"dvh_urethra_d10_gy\": " << jsonNumber(value(ours, "urethra_D10"))
       << ",\n  \"dvh_plan_cpu_s\": " << jsonNumber(plan.cpu_seconds)
       << ",\n  \"dvh_matrix_cpu_s\": " << jsonNumber(plan.setup_cpu_seconds)
       << ",\n  \"dvh_points\": " << plan.points
       << ",\n  \"dvh_descent_iterations\": " << plan.descent_iterations
       << ",\n  \"dvh_method\": \"" << options.method << "\""
       << ",\n  \"dvh_mip_gap_v100_pp\": "
       << (plan.mip_bound_known ? jsonNumber(plan.mip_gap_pct) : std::string("null"))
       << ",\n  \"dvh_mip_binaries\": " << plan.binaries
       << ",\n  \"dvh_criteria_giving_way\": " << jsonList(plan.violated)
       << ",\n  \"clinical_dominated_dvh\": " << (dom.dominated ? 1 : 0)
       << ",\n  \"dominating_plan_s\": " << jsonNumber(dom.plan.seconds)
       << ",\n  \"dominating_plan_cpu_s\": " << jsonNumber(dom.plan.cpu_seconds)
       << ",\n  \"dominating_v100_pct\": " << jsonNumber(value(dom.indices, "prostate_V100"))
       << ",\n  \"dominating_better_on\": " << jsonList(better)
       << ",\n  \"dominance_prevented_by\": " << jsonList(dom.worse)
       << ",\n  \"index_rotation_change_max_gy\": "
       << jsonNumber(std::max(rot_clinical.dose_Gy, rot_dvh.dose_Gy))
       << ",\n  \"index_rotation_change_max_pp\": "
       << jsonNumber(std::max(rot_clinical.volume_pp, rot_dvh.volume_pp))
       << ",\n  \"index_lattice_change_gy\": " << jsonNumber(lattice.dose_Gy)
       << ",\n  \"index_lattice_change_pp\": " << jsonNumber(lattice.volume_pp)
       << ",\n  \"index_lattice_worst\": " << jsonList({lattice.worst_dose, lattice.worst_volume});
  if (!dpy.empty()) {
    // name in the summary -> name in the script's JSON (max_diff_<name>_gy / _pp).
    const std::vector<std::pair<std::string, std::string>> keys = {
        {"index_vs_dicompyler", "matched"},
        {"index_vs_dicompyler_reported", "ours_vs_converged"},
        {"index_vs_dicompyler_converged", "converged"},
        {"index_vs_dicompyler_default", "default"},
        {"index_vs_dicompyler_as_shipped", "as_shipped"},
        {"index_vs_dicompyler_on_its_grid", "on_grid"},
        {"index_vs_stored_dvh", "stored"}};
    for (const auto& [name, field] : keys) {
      for (const char* unit : {"gy", "pp"})
        json << ",\n  \"" << name << "_max_" << unit
             << "\": " << jsonNumber(jsonField(dpy, "max_diff_" + field + "_" + unit));
    }
    json << ",\n  \"dicompyler\": " << dpy;
  }
  std::map<std::string, std::string> reasons;
  for (const auto& [k, v] : clinical) {
    if (!v.defined)
      reasons[k] = v.reason;
  }
  json << robust_json << ",\n  \"clinical_indices_05mm\": " << jsonIndexSet(clinical)
       << ",\n  \"dvh_indices\": " << jsonIndexSet(ours)
       << ",\n  \"dominating_indices\": " << jsonIndexSet(dom.indices) << ",\n  \"undefined\": {";
  bool first = true;
  for (const auto& [k, r] : reasons) {
    json << (first ? "" : ", ") << "\"" << k << "\": \"" << r << "\"";
    first = false;
  }
  json << "}";
  return json.str();
}

}  // namespace

int main(int argc, char** argv) {
  const auto args = ng::report::parseBenchArgs(argc, argv, "bench_hdr_dicom");
  if (!args)
    return 2;
  try {
    const char* shared = std::getenv("NG_SHARED_DATA");
    std::string dir = shared ? std::string(shared) + "/hdr_example_plan" : "";
    std::string case_source = "shared hdr_example_plan (RobustBrachy example, real clinical plan)";
    if (dir.empty() || !fs::is_directory(dir)) {
      dir = args->out_dir + "/synthetic_dicom";
      fs::create_directories(dir);
      writeSyntheticDicom(dir);
      case_source = "synthetic case 1 written as DICOM (shared plan absent); clinical plan = SA";
    }
    const std::string out_dicom = args->out_dir + "/export";
    fs::remove_all(out_dicom);

    // DICOM in -> RTPLAN out, timed end to end.
    const auto t_total = std::chrono::steady_clock::now();
    auto t0 = std::chrono::steady_clock::now();
    const dose::DicomCase dc = dose::loadDicomCase(dir);
    const double import_s = since(t0);
    const dose::Tg43Source source = dose::loadSource(dc.planning.source);
    t0 = std::chrono::steady_clock::now();
    const Eigen::MatrixXd d = dose::doseRateMatrix(dc.planning, source);
    const double matrix_s = since(t0);
    const dose::DwellResult lp = dose::optimizeLp(dc.planning, d);
    if (!lp.ok())
      throw std::runtime_error("LP: " + lp.status);
    dose::HdrCase plan = dc.planning;
    plan.dwell_times_s = lp.times_s;
    t0 = std::chrono::steady_clock::now();
    dose::exportDicomRtPlan(plan, source, nullptr, out_dicom, dc.files.structure_set);
    const double export_s = since(t0);
    const double total_s = since(t_total);  // DICOM in -> RTPLAN (+ RTSTRUCT) out
    t0 = std::chrono::steady_clock::now();  // our RTDOSE on the clinical grid, rewritten with it
    const dose::DoseGrid clinical_grid = dose::readRtDose(dc.files.dose);
    dose::exportDicomRtPlan(plan, source, &clinical_grid, out_dicom, dc.files.structure_set);
    const double rtdose_s = since(t0);

    // Comparison and front.
    std::vector<double> scales = {0.1, 0.3, 1, 2, 3, 5, 10, 20, 50, 100, 300};
    if (args->quick)
      scales = {0.3, 1, 3, 10, 100};
    // Front 1: Table 6.1's urethra D_max (19.2 Gy at Rx 16 Gy), weight swept; front 2 and 3:
    // the same with the urethra's D_max lowered to 0.9 and 0.8 of it (clamped to its D_min).
    const std::vector<double> max_factors = {1.0, 0.9, 0.8};
    const dose::ClinicalComparison cmp =
        dose::compareWithClinical(dc, source, scales, kEvalSpacing_m, max_factors);
    bool dominated_table61 = false;
    for (const auto& p : cmp.front)
      dominated_table61 =
          dominated_table61 || (p.dominates_clinical && p.urethra_max_factor == 1.0);
    ng::report::Table indices({"index", "clinical", "lp"}, 6);
    for (const auto& [k, v] : cmp.ours.indices)
      indices.addRow({k, at(cmp.clinical.indices, k), v});
    indices.writeCsv(args->out_dir + "/indices.csv");
    ng::report::Table front(
        {"plan", "urethra_max_factor", "urethra_weight_scale", "prostate_V100_pct",
         "urethra_D10_Gy", "rectum_D2cc_Gy", "lp_s", "dominates_clinical"},
        6);
    for (const auto& p : cmp.front) {
      front.addRow({"LP, urethra Dmax x " + ng::report::jsonNumber(p.urethra_max_factor, 2),
                    p.urethra_max_factor, p.urethra_weight_scale, p.v100_pct, p.urethra_d10_Gy,
                    p.rectum_d2cc_Gy, p.lp_s, p.dominates_clinical ? 1.0 : 0.0});
    }
    front.addRow({"clinical", 0.0, 0.0, at(cmp.clinical.indices, "prostate_V100"),
                  at(cmp.clinical.indices, "urethra_D10"), at(cmp.clinical.indices, "rectum_D2cc"),
                  0.0, 0.0});
    front.writeCsv(args->out_dir + "/front.csv");
    ng::report::Table dvh({"dose_Gy", "volume_pct", "curve"}, 6);
    const double max_Gy = 2.5 * dc.planning.prescription_Gy;
    const int bins = 100;
    for (const auto* e : {&cmp.clinical, &cmp.ours}) {
      for (const auto& s : e->doses) {
        const auto curve = dose::cumulativeDvh(s, max_Gy, bins);
        for (int b = 0; b <= bins; ++b) {
          dvh.addRow({max_Gy * b / bins, curve[static_cast<std::size_t>(b)],
                      s.name + (e == &cmp.clinical ? " clinical" : " LP")});
        }
      }
    }
    dvh.writeCsv(args->out_dir + "/dvh.csv");

    // Export checks.
    const double roundtrip = roundTripError(plan, out_dicom);
    const int dcio = dciodvfyErrors(out_dicom, args->out_dir + "/dciodvfy.txt");
    const bool pydicom_ok = std::system(("/usr/bin/python3 " + ng::packageDir().string() +
                                         "/scripts/check_rt_export.py '" + out_dicom + "' > '" +
                                         args->out_dir + "/pydicom.txt' 2>&1")
                                            .c_str()) == 0;
    dose::DicomRtImportReport rep;
    const dose::HdrCase back = dose::importDicomRt(out_dicom, &rep);
    const auto validation = dose::validateAgainstRtDose(
        back, source, dose::readRtDose(out_dicom + "/RD.dcm"), rep.fractions_planned);
    const bool validates = dcio == 0 && pydicom_ok && validation.pass && roundtrip <= 0.01;

    std::ostringstream json;
    json.precision(6);
    using ng::report::jsonNumber;
    json << "{\n  \"benchmark\": \"hdr_dicom\",\n  \"case\": \"" << case_source
         << "\",\n  \"quick\": " << (args->quick ? "true" : "false")
         << ",\n  \"candidate_dwells\": " << dc.planning.dwells.size()
         << ",\n  \"clinical_dwells\": " << dc.clinical.dwells.size()
         << ",\n  \"clinical_active\": " << dc.clinical_active
         << ",\n  \"clinical_active_on_candidates\": " << dc.clinical_active_on_candidates
         << ",\n  \"dose_points\": " << dc.planning.points.size()
         << ",\n  \"step_mm\": " << jsonNumber(dc.step_m * 1e3)
         << ",\n  \"import_s\": " << jsonNumber(import_s)
         << ",\n  \"matrix_s\": " << jsonNumber(matrix_s)
         << ",\n  \"lp_s\": " << jsonNumber(lp.seconds)
         << ",\n  \"export_s\": " << jsonNumber(export_s)
         << ",\n  \"export_with_rtdose_s\": " << jsonNumber(rtdose_s)
         << ",\n  \"total_s\": " << jsonNumber(total_s)
         << ",\n  \"lp_objective\": " << jsonNumber(cmp.ours.objective)
         << ",\n  \"clinical_objective\": " << jsonNumber(cmp.clinical.objective)
         << ",\n  \"lp_v100_pct\": " << jsonNumber(at(cmp.ours.indices, "prostate_V100"))
         << ",\n  \"clinical_v100_pct\": " << jsonNumber(at(cmp.clinical.indices, "prostate_V100"))
         << ",\n  \"lp_urethra_d10_gy\": " << jsonNumber(at(cmp.ours.indices, "urethra_D10"))
         << ",\n  \"clinical_urethra_d10_gy\": "
         << jsonNumber(at(cmp.clinical.indices, "urethra_D10"))
         << ",\n  \"lp_rectum_d2cc_gy\": " << jsonNumber(at(cmp.ours.indices, "rectum_D2cc"))
         << ",\n  \"clinical_rectum_d2cc_gy\": "
         << jsonNumber(at(cmp.clinical.indices, "rectum_D2cc"))
         << ",\n  \"clinical_dominated\": " << (cmp.clinical_dominated ? 1 : 0)
         << ",\n  \"clinical_dominated_table61_urethra_max\": " << (dominated_table61 ? 1 : 0)
         << ",\n  \"roundtrip_max_dwell_error_s\": " << jsonNumber(roundtrip)
         << ",\n  \"dciodvfy_errors\": " << dcio << ",\n  \"pydicom_ok\": " << (pydicom_ok ? 1 : 0)
         << ",\n  \"export_rtdose_validation_pass\": " << (validation.pass ? 1 : 0)
         << ",\n  \"export_validates\": " << (validates ? 1 : 0)
         << dvhStudy(dc, dir, source, lp.times_s, *args)
         << ",\n  \"clinical_indices\": " << jsonMap(cmp.clinical.indices)
         << ",\n  \"lp_indices\": " << jsonMap(cmp.ours.indices) << "\n}\n";
    ng::report::writeTextFile(args->out_dir + "/summary.json", json.str());
    ng::report::writeTextFile(
        args->out_dir + "/plot.json",
        R"json([{"csv": "dvh.csv", "x": "dose_Gy", "y": "volume_pct", "group": "curve",
  "title": "Cumulative DVH: clinical plan vs our LP (same engine, 1 mm grid)", "png": "dvh.png"},
 {"csv": "front.csv", "x": "urethra_D10_Gy", "y": "prostate_V100_pct", "group": "plan", "annotate": "urethra_weight_scale",
  "title": "LP trade-off front (urethra weight sweep) and the clinical plan", "png": "front.png"},
 {"csv": "dvh_front.csv", "x": "urethra_D10_Gy", "y": "prostate_V100_pct", "group": "plan",
  "title": "Dose-volume front: V100 maximised at each urethra D10 limit (rectum at its criteria)", "png": "dvh_front.png"}])json");
    std::cout << json.str();
    return 0;
  } catch (const std::exception& e) {
    std::cerr << "bench_hdr_dicom: " << e.what() << "\n";
    return 1;
  }
}
