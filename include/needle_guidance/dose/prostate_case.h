// Synthetic prostate HDR cases spanning the dissertation's cohort (6.3.1: prostate 23-103 cc,
// 14-18 transperineal catheters, 1,781-3,510 dose points), the two kinds of dose calculation
// points per structure (6.2.1) and Table 6.1's clinical criteria as the default class solution.
#pragma once

#include <vector>

#include "needle_guidance/dose/hdr_case.h"

namespace needle_guidance::dose {

struct SyntheticCaseOptions {
  unsigned seed = 1;             ///< everything random derives from it
  double prostate_cc = 0.0;      ///< 0: drawn in [23, 103] cc
  int catheters = 0;             ///< 0: drawn in [14, 18]
  int dose_points = 0;           ///< total surface + volume points; 0: drawn in [1781, 3510]
  double slice_m = 3e-3;         ///< contour slice spacing (6.3.1: 3 mm CT slices)
  double dwell_step_m = 5e-3;    ///< dwell step along a catheter
  double prescription_Gy = 9.5;  ///< Table 6.1: D_min of the prostate (950 cGy)
};

/// Table 6.1 (cGy converted to Gy), scaled to a prescription: prostate and urethra surface and
/// volume points, rectum and bladder surface and volume points.
std::vector<Criterion> table61Criteria(double prescription_Gy = 9.5);

/// Dose calculation points: "surface" points along every contour every surface_spacing_m,
/// "volume" points uniformly inside each structure (seeded), volume_points in total shared by
/// structure volume (at least min_per_structure each). Points of a structure exclude the
/// structures listed after it that lie inside it (the urethra inside the prostate).
struct DosePointOptions {
  double surface_spacing_m = 4e-3;
  int volume_points = 1500;
  int min_per_structure = 50;
  unsigned seed = 1;
};
std::vector<DosePoint> makeDosePoints(const HdrCase& c, const DosePointOptions& options);

/// Dwell positions every step_m from each catheter's tip whose position lies inside the target
/// structure or within margin_m of it along the catheter. Axis: towards the catheter tip.
std::vector<DwellPosition> makeDwellPositions(const HdrCase& c, double step_m,
                                              double margin_m = 2.5e-3);

/// One synthetic case: prostate (ellipsoid), urethra through it, rectum behind and bladder
/// above, catheters, dwell positions, dose points and Table 6.1 criteria.
HdrCase syntheticProstateCase(const SyntheticCaseOptions& options);

/// n cases with seeds seed, seed + 1, ...: the default benchmark cohort (n = 20).
std::vector<HdrCase> syntheticCohort(int n, unsigned seed = 1);

}  // namespace needle_guidance::dose
