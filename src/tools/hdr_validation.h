// Real-plan validation figures for bench_hdr: our TG-43 dose of the imported example plan
// against its vendor RTDOSE (dicom_rt.h), and whether the misregistered copy is flagged. The
// data is third-party and optional: $NG_SHARED_DATA (scripts/bench sets ../shared/data).
#pragma once

#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <string>

#include "needle_guidance/dose/dicom_rt.h"

struct RealPlanFigures {
  bool available = false;
  double gamma_3pct3mm = 0.0;
  double gamma_2pct2mm = 0.0;
  double median_relative_difference = 0.0;
  bool misregistered_flagged = false;
};

inline needle_guidance::dose::RtDoseValidation validatePlanDir(const std::string& dir) {
  namespace dose = needle_guidance::dose;
  dose::DicomRtImportReport report;
  const dose::HdrCase c = dose::importDicomRt(dir, &report);
  const dose::Tg43Source source = dose::loadSource("gammamed_plus_hdr");  // reproduces the RTDOSE
  const dose::DoseGrid grid = dose::readRtDose(dose::findDicomRtFiles(dir).dose);
  return dose::validateAgainstRtDose(c, source, grid, report.fractions_planned);
}

inline RealPlanFigures validateRealPlan() {
  const char* env = std::getenv("NG_SHARED_DATA");
  const std::string data = env ? env : "../shared/data";
  RealPlanFigures out;
  if (!std::filesystem::is_directory(data + "/hdr_example_plan")) {
    std::cout << "real-plan validation skipped: " << data << "/hdr_example_plan not found\n";
    return out;
  }
  const auto good = validatePlanDir(data + "/hdr_example_plan");
  out.available = true;
  out.gamma_3pct3mm = good.gamma3pct3mm();
  out.gamma_2pct2mm = good.gamma2pct2mm();
  out.median_relative_difference = good.median_relative_difference;
  if (std::filesystem::is_directory(data + "/hdr_example_plan_misregistered_dose")) {
    out.misregistered_flagged =
        !validatePlanDir(data + "/hdr_example_plan_misregistered_dose").pass;
  }
  std::cout << "real plan: gamma 3%/3mm " << out.gamma_3pct3mm << ", 2%/2mm " << out.gamma_2pct2mm
            << ", median relative difference " << out.median_relative_difference
            << "; misregistered plan " << (out.misregistered_flagged ? "flagged" : "NOT flagged")
            << "\n";
  return out;
}
