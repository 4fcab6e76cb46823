// Real-plan validation figures for bench_hdr (filled from the DICOM-RT validation).
#pragma once

struct RealPlanFigures {
  bool available = false;
  double gamma_3pct3mm = 0.0;
  double gamma_2pct2mm = 0.0;
  double median_relative_difference = 0.0;
  bool misregistered_flagged = false;
};

inline RealPlanFigures validateRealPlan() { return {}; }  // TODO(issue 7): DICOM-RT import
