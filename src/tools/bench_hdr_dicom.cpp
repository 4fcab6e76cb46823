// Benchmark of HDR planning from a DICOM-RT case: import (dicom_case.h), dose-rate
// matrix, LP, export (RS/RP/RD.dcm) and their times; the clinical plan's and the LP's indices on
// the same engine, points and 1 mm grid; both DVHs; the urethra-weight front with the clinical
// plan as a point; the export checked by dciodvfy, pydicom (scripts/check_rt_export.py), the
// round trip of the dwell times and our RTDOSE validation. Runs on NG_SHARED_DATA/hdr_example_plan
// when present, else on synthetic case 1 written out as DICOM (its "clinical" plan = SA's).
// Usage: bench_hdr_dicom --out DIR [--quick]
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
#include "needle_guidance/dose/dwell_optimization.h"
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
        dose::compareWithClinical(dc, source, scales, 1e-3, max_factors);
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
         << ",\n  \"clinical_indices\": " << jsonMap(cmp.clinical.indices)
         << ",\n  \"lp_indices\": " << jsonMap(cmp.ours.indices) << "\n}\n";
    ng::report::writeTextFile(args->out_dir + "/summary.json", json.str());
    ng::report::writeTextFile(
        args->out_dir + "/plot.json",
        R"json([{"csv": "dvh.csv", "x": "dose_Gy", "y": "volume_pct", "group": "curve",
  "title": "Cumulative DVH: clinical plan vs our LP (same engine, 1 mm grid)", "png": "dvh.png"},
 {"csv": "front.csv", "x": "urethra_D10_Gy", "y": "prostate_V100_pct", "group": "plan", "annotate": "urethra_weight_scale",
  "title": "LP trade-off front (urethra weight sweep) and the clinical plan", "png": "front.png"}])json");
    std::cout << json.str();
    return 0;
  } catch (const std::exception& e) {
    std::cerr << "bench_hdr_dicom: " << e.what() << "\n";
    return 1;
  }
}
