// Plans one HDR case: hdr_plan (--case DIR | --synthetic SEED) [--method lp|sa|both]
//   [--mps FILE] [--write-case DIR] [--iterations N]
// or a DICOM-RT folder: hdr_plan --dicom DIR [--case-file FILE.yaml] [--export DIR]
// --dicom builds the case from RTSTRUCT + RTPLAN (dicom_case.h), plans the LP, prints the
// clinical plan's and the LP's indices side by side; --export writes RS/RP/RD.dcm.
// --case reads a plain case folder (case_folder.h), --synthetic generates cohort case SEED;
// --mps writes the case's LP (MPS) for any other solver; --write-case writes the case with the
// LP's dwell times (or SA's with --method sa) as a case folder. Prints objectives, times and
// dosimetric indices. Exit 0 on success, 2 on bad arguments or a bad case.
#include <cstdio>
#include <iostream>
#include <memory>
#include <string>

#include "needle_guidance/dose/case_folder.h"
#include "needle_guidance/dose/dicom_case.h"
#include "needle_guidance/dose/dose_indices.h"
#include "needle_guidance/dose/dwell_optimization.h"
#include "needle_guidance/dose/prostate_case.h"
#include "needle_guidance/report/bench_args.h"

namespace dose = needle_guidance::dose;

namespace {

/// hdr_plan --dicom: plan a DICOM-RT folder and compare with its clinical plan.
int planDicom(const std::string& dir, const std::string& case_file, const std::string& export_dir) {
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
    std::unique_ptr<dose::DoseGrid> grid;
    if (!dc.files.dose.empty())
      grid = std::make_unique<dose::DoseGrid>(dose::readRtDose(dc.files.dose));
    dose::exportDicomRtPlan(plan, source, grid.get(), export_dir, dc.files.structure_set);
    std::cout << "exported RS.dcm, RP.dcm" << (grid ? ", RD.dcm" : "") << " to " << export_dir
              << "\n";
  }
  return 0;
}

}  // namespace

constexpr const char* kUsage =
    "usage: hdr_plan (--case DIR | --synthetic SEED) [--method lp|sa|both] [--mps FILE] "
    "[--write-case DIR] [--iterations N]\n       hdr_plan --dicom DIR [--case-file FILE.yaml] "
    "[--export DIR]\n";

int main(int argc, char** argv) {
  if (needle_guidance::report::helpRequested(argc, argv)) {
    std::cout << kUsage;
    return 0;
  }
  std::string case_dir, method = "both", mps, write_dir, dicom_dir, case_file, export_dir;
  long iterations = 100000;
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
    else {
      std::cerr << kUsage;
      return 2;
    }
  }
  if (!dicom_dir.empty()) {
    try {
      return planDicom(dicom_dir, case_file, export_dir);
    } catch (const std::invalid_argument& e) {
      std::cerr << "hdr_plan: " << e.what() << "\n";
      return 2;
    } catch (const std::exception& e) {
      std::cerr << "hdr_plan: " << e.what() << "\n";
      return 1;
    }
  }
  if ((case_dir.empty() == (synthetic < 0)) ||
      (method != "lp" && method != "sa" && method != "both")) {
    std::cerr
        << "hdr_plan: give exactly one of --case DIR or --synthetic SEED; --method lp|sa|both\n";
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
    if (method != "sa") {
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
    if (method != "lp") {
      dose::AnnealingOptions o;
      o.iterations = iterations;
      const auto sa = dose::optimizeAnnealing(c, d, o);
      std::cout << "SA: objective " << sa.objective << ", " << sa.seconds << " s, " << sa.iterations
                << " moves\n";
      if (method == "sa")
        chosen = sa.times_s;
    }
    for (const auto& [name, value] :
         dose::dosimetricIndices(dose::structureDoses(c, source, chosen), c.prescription_Gy)) {
      std::cout << "  " << name << " = " << value
                << (name.find("_V") != std::string::npos ? " %" : " Gy") << "\n";
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
