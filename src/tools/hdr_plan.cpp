// Plans one HDR case: hdr_plan (--case DIR | --synthetic SEED) [--method lp|sa|both|dvh]
//   [--mps FILE] [--write-case DIR] [--iterations N] [--criterion "urethra D10 <= 115%"]...
// or a DICOM-RT folder: hdr_plan --dicom DIR [--case-file FILE.yaml] [--method lp|dvh]
//   [--export DIR] [--max-seconds S] [--dvh-method descent|mip]
// --dicom builds the case from RTSTRUCT + RTPLAN (dicom_case.h), plans the LP (or, with
// --method dvh, maximises target V100 under the case file's dose-volume criteria and then
// looks for a plan at least as good as the clinical one on every index), prints the clinical
// plan's and ours side by side (an index a structure cannot support is printed as undefined
// with its reason); --export writes RS/RP/RD.dcm of our plan. --criterion replaces the default
// dose-volume criteria of a case folder or synthetic case (repeat it for each).
// --case reads a plain case folder (case_folder.h), --synthetic generates cohort case SEED;
// --mps writes the case's LP (MPS) for any other solver; --write-case writes the case with the
// LP's dwell times (or SA's with --method sa) as a case folder. Prints objectives, times and
// dosimetric indices. Exit 0 on success, 2 on bad arguments or a bad case.
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <map>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "needle_guidance/dose/case_folder.h"
#include "needle_guidance/dose/dicom_case.h"
#include "needle_guidance/dose/dose_indices.h"
#include "needle_guidance/dose/dvh_comparison.h"
#include "needle_guidance/dose/dwell_optimization.h"
#include "needle_guidance/dose/prostate_case.h"
#include "needle_guidance/report/bench_args.h"

namespace dose = needle_guidance::dose;

namespace {

/// Prints two index sets side by side; undefined indices as "undefined" with the reason.
void printIndices(const std::map<std::string, dose::DoseVolumeIndex>& reference,
                  const std::map<std::string, dose::DoseVolumeIndex>& ours,
                  const std::string& reference_name, const std::string& ours_name) {
  std::printf("  %-16s %10s %10s\n", "index", reference_name.c_str(), ours_name.c_str());
  for (const auto& [name, value] : ours) {
    const auto it = reference.find(name);
    const auto cell = [](const dose::DoseVolumeIndex* i) {
      char text[32];
      if (i == nullptr || !i->defined)
        return std::string("undefined");
      std::snprintf(text, sizeof text, "%.2f", i->value);
      return std::string(text);
    };
    std::printf("  %-16s %10s %10s %s\n", name.c_str(),
                cell(it == reference.end() ? nullptr : &it->second).c_str(), cell(&value).c_str(),
                name.find("_V") != std::string::npos ? "%" : "Gy");
    if (!value.defined)
      std::printf("    (%s)\n", value.reason.c_str());
  }
}

/// CBC's gap to the MIP optimum, or that it is unknown (CBC not run).
std::string gapText(const dose::DvhPlanResult& r) {
  if (!r.mip_bound_known)
    return "gap to the MIP optimum unknown (heuristic only)";
  return "CBC gap " + std::to_string(r.mip_gap_pct) + " V100 points" +
         (r.mip_optimal ? " (optimal)" : "");
}

/// hdr_plan --dicom --method dvh: plans on the criteria, then tries to dominate the clinical plan.
std::vector<double> planDicomDvh(const dose::DicomCase& dc, const dose::DicomCaseSettings& settings,
                                 const dose::Tg43Source& source,
                                 const dose::DvhPlanOptions& options) {
  const dose::HdrCase& c = dc.planning;
  const auto criteria = dose::dvhCriteria(settings, c.prescription_Gy);
  // The clinical times on our dwells: a start the planner never does worse than.
  const dose::HdrCase with_clinical = dose::planningWithClinicalTimes(dc);
  const auto clinical = dose::comparisonIndexSet(
      dose::structureDoses(dc.clinical, source, dc.clinical.dwell_times_s, options.eval_spacing_m),
      c.prescription_Gy);
  const dose::DvhPlanResult r = dose::optimizeDvh(with_clinical, source, criteria, options);
  for (const auto& note : r.notes)
    std::cout << "note: " << note << "\n";
  if (!r.ok())
    throw std::runtime_error("dose-volume planning: " + r.status);
  std::cout << "DVH plan on " << criteria.size() << " criteria: V100 " << r.v100_pct << " %, "
            << r.seconds << " s (" << r.cpu_seconds << " s processor, of which "
            << r.setup_cpu_seconds << " s for the dose-rate matrix of " << r.points << " points; "
            << r.descent_iterations << " descent iterations), " << gapText(r) << "\n";
  for (const auto& v : r.violated)
    std::cout << "  gives way: " << v << "\n";
  std::cout << "on the planner's dose points: objective " << r.objective << " (V100 "
            << r.mip_v100_pct << " %); the clinical plan's " << r.case_times_objective << " (V100 "
            << r.case_times_v100_pct << " %)"
            << (r.case_times_objective < r.objective ? ": the clinical plan scores better" : "")
            << "\n";
  const auto ours = dose::comparisonIndexSet(
      dose::structureDoses(c, source, r.times_s, options.eval_spacing_m), c.prescription_Gy);
  printIndices(clinical, ours, "clinical", "DVH");
  const dose::Dominance d = dose::dominate(with_clinical, source, clinical, "prostate", options);
  std::cout << "plan at least as good as the clinical one on every defined index: "
            << (d.dominated ? "found" : "not found") << " (" << d.plan.seconds << " s)\n";
  for (const auto& w : d.worse)
    std::cout << "  worse: " << w << "\n";
  if (d.dominated) {
    printIndices(clinical, d.indices, "clinical", "dominant");
    return d.plan.times_s;
  }
  return r.times_s;
}

/// Writes RS.dcm, RP.dcm and (with the case's RTDOSE grid) RD.dcm of `plan` into `dir`.
void exportPlan(const dose::HdrCase& plan, const dose::DicomCase& dc,
                const dose::Tg43Source& source, const std::string& dir) {
  std::unique_ptr<dose::DoseGrid> grid;
  if (!dc.files.dose.empty())
    grid = std::make_unique<dose::DoseGrid>(dose::readRtDose(dc.files.dose));
  dose::exportDicomRtPlan(plan, source, grid.get(), dir, dc.files.structure_set);
  std::cout << "exported RS.dcm, RP.dcm" << (grid ? ", RD.dcm" : "") << " to " << dir << "\n";
}

/// hdr_plan --dicom: plan a DICOM-RT folder and compare with its clinical plan.
int planDicom(const std::string& dir, const std::string& case_file, const std::string& export_dir,
              const std::string& method, const dose::DvhPlanOptions& dvh_options) {
  const dose::DicomCaseSettings settings =
      case_file.empty() ? dose::DicomCaseSettings{} : dose::readDicomCaseSettings(case_file);
  const dose::DicomCase dc = dose::loadDicomCase(dir, settings);
  const dose::HdrCase& c = dc.planning;
  for (const auto& note : dc.notes)
    std::cout << "note: " << note << "\n";
  std::cout << c.name << ": " << c.structures.size() << " structures, " << c.catheters.size()
            << " catheters, " << c.dwells.size() << " candidate dwells (step " << dc.step_m * 1e3
            << " mm), " << c.points.size() << " dose points, Rx " << c.prescription_Gy
            << " Gy, source " << c.source << "\n"
            << "clinical plan: " << dc.clinical.dwells.size() << " dwells, " << dc.clinical_active
            << " active, " << dc.clinical_active_on_candidates
            << " of them on candidate positions (largest offset " << dc.clinical_max_offset_m * 1e3
            << " mm)\n";
  const dose::Tg43Source source = dose::loadSource(c.source);
  if (method == "dvh") {
    dose::HdrCase plan = c;
    plan.dwell_times_s = planDicomDvh(dc, settings, source, dvh_options);
    if (!export_dir.empty())
      exportPlan(plan, dc, source, export_dir);
    return 0;
  }
  const auto cmp = dose::compareWithClinical(dc, source, {});
  std::cout << "LP: objective " << cmp.lp.objective << ", " << cmp.lp.seconds
            << " s; clinical objective " << cmp.clinical.objective << "\n";
  std::printf("  %-16s %10s %10s\n", "index", "clinical", "LP");
  for (const auto& [name, value] : cmp.ours.indices) {
    const auto it = cmp.clinical.indices.find(name);
    std::printf("  %-16s %10.2f %10.2f %s\n", name.c_str(),
                it == cmp.clinical.indices.end() ? 0.0 : it->second, value,
                name.find("_V") != std::string::npos ? "%" : "Gy");
  }
  if (!export_dir.empty()) {
    dose::HdrCase plan = c;
    plan.dwell_times_s = cmp.lp.times_s;
    exportPlan(plan, dc, source, export_dir);
  }
  return 0;
}

}  // namespace

constexpr const char* kUsage =
    "usage: hdr_plan (--case DIR | --synthetic SEED) [--method lp|sa|both|dvh] [--mps FILE] "
    "[--write-case DIR] [--iterations N] [--criterion TEXT]...\n"
    "       hdr_plan --dicom DIR [--case-file FILE.yaml] [--method lp|dvh] [--export DIR]\n"
    "  with --method dvh: [--max-seconds S] (processor time per plan, default 5)\n"
    "                     [--dvh-method descent|mip] (default descent)\n";

int main(int argc, char** argv) {
  if (needle_guidance::report::helpRequested(argc, argv)) {
    std::cout << kUsage;
    return 0;
  }
  std::string case_dir, method = "both", mps, write_dir, dicom_dir, case_file, export_dir;
  std::vector<std::string> criteria_text;
  long iterations = 100000;
  dose::DvhPlanOptions dvh_options;
  int synthetic = -1;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::cerr << "hdr_plan: " << a << " needs a value\n";
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--case")
      case_dir = value();
    else if (a == "--synthetic")
      synthetic = std::stoi(value());
    else if (a == "--method")
      method = value();
    else if (a == "--mps")
      mps = value();
    else if (a == "--write-case")
      write_dir = value();
    else if (a == "--iterations")
      iterations = std::stol(value());
    else if (a == "--dicom")
      dicom_dir = value();
    else if (a == "--case-file")
      case_file = value();
    else if (a == "--export")
      export_dir = value();
    else if (a == "--criterion")
      criteria_text.push_back(value());
    else if (a == "--max-seconds") {
      const std::string text = value();
      char* end = nullptr;
      dvh_options.max_seconds = std::strtod(text.c_str(), &end);
      if (end == text.c_str() || *end != '\0' || !(dvh_options.max_seconds > 0.0)) {
        std::cerr << "hdr_plan: --max-seconds needs a number > 0, got '" << text << "'\n";
        return 2;
      }
    } else if (a == "--dvh-method")
      dvh_options.method = value();
    else {
      std::cerr << kUsage;
      return 2;
    }
  }
  if (!dicom_dir.empty()) {
    try {
      if (method != "both" && method != "lp" && method != "dvh") {
        std::cerr << "hdr_plan: --dicom plans with --method lp or dvh\n";
        return 2;
      }
      return planDicom(dicom_dir, case_file, export_dir, method, dvh_options);
    } catch (const std::invalid_argument& e) {
      std::cerr << "hdr_plan: " << e.what() << "\n";
      return 2;
    } catch (const std::exception& e) {
      std::cerr << "hdr_plan: " << e.what() << "\n";
      return 1;
    }
  }
  if ((case_dir.empty() == (synthetic < 0)) ||
      (method != "lp" && method != "sa" && method != "both" && method != "dvh")) {
    std::cerr << "hdr_plan: give exactly one of --case DIR or --synthetic SEED; --method "
                 "lp|sa|both|dvh\n";
    return 2;
  }
  try {
    dose::HdrCase c;
    if (!case_dir.empty()) {
      c = dose::readCaseFolder(case_dir);
    } else {
      dose::SyntheticCaseOptions o;
      o.seed = static_cast<unsigned>(synthetic);
      c = dose::syntheticProstateCase(o);
    }
    const dose::Tg43Source source = dose::loadSource(c.source);
    const Eigen::MatrixXd d = dose::doseRateMatrix(c, source);
    for (const auto& note : dose::penaltyModel(c).notes) {
      std::cout << "note: " << note << "\n";
    }
    std::cout << c.name << ": " << c.structures.size() << " structures, " << c.catheters.size()
              << " catheters, " << c.dwells.size() << " dwell positions, " << c.points.size()
              << " dose points, source " << c.source << ", S_K " << c.air_kerma_strength_U
              << " U, Rx " << c.prescription_Gy << " Gy\n";
    std::vector<double> chosen;
    if (method == "dvh") {
      std::vector<dose::DvhCriterion> criteria = dose::defaultDvhCriteria(c.prescription_Gy);
      if (!criteria_text.empty()) {
        criteria.clear();
        for (const auto& text : criteria_text)
          criteria.push_back(dose::parseDvhCriterion(text, c.prescription_Gy));
      }
      const auto r = dose::optimizeDvh(c, source, criteria, dvh_options);
      for (const auto& note : r.notes)
        std::cout << "note: " << note << "\n";
      if (!r.ok()) {
        std::cerr << "hdr_plan: dose-volume planning: " << r.status << "\n";
        return 1;
      }
      std::cout << "DVH: V100 " << r.v100_pct << " %, " << r.seconds << " s (" << r.cpu_seconds
                << " s processor), " << gapText(r) << "\n";
      for (const auto& v : r.violated)
        std::cout << "  gives way: " << v << "\n";
      chosen = r.times_s;
    }
    if (method != "sa" && method != "dvh") {
      dose::LpOptions o;
      o.mps_path = mps;
      const auto lp = dose::optimizeLp(c, d, o);
      std::cout << "LP: objective " << lp.objective << " (solver optimum " << lp.lower_bound
                << "), " << lp.seconds << " s, " << lp.iterations << " iterations, " << lp.status
                << "\n";
      if (!lp.ok())
        return 1;
      chosen = lp.times_s;
      if (!mps.empty())
        std::cout << "LP written to " << mps << "\n";
    }
    if (method != "lp" && method != "dvh") {
      dose::AnnealingOptions o;
      o.iterations = iterations;
      const auto sa = dose::optimizeAnnealing(c, d, o);
      std::cout << "SA: objective " << sa.objective << ", " << sa.seconds << " s, " << sa.iterations
                << " moves\n";
      if (method == "sa")
        chosen = sa.times_s;
    }
    for (const auto& [name, value] : dose::comparisonIndexSet(
             dose::structureDoses(c, source, chosen, 1e-3), c.prescription_Gy)) {
      if (value.defined)
        std::cout << "  " << name << " = " << value.value
                  << (name.find("_V") != std::string::npos ? " %" : " Gy") << "\n";
      else
        std::cout << "  " << name << " undefined: " << value.reason << "\n";
    }
    if (!write_dir.empty()) {
      c.dwell_times_s = chosen;
      dose::writeCaseFolder(c, write_dir);
      std::cout << "case written to " << write_dir << "\n";
    }
  } catch (const std::invalid_argument& e) {
    std::cerr << "hdr_plan: " << e.what() << "\n";
    return 2;
  } catch (const std::exception& e) {
    std::cerr << "hdr_plan: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
