// Moving a case and its catheters: the whole case turned or moved (the patient lies
// differently; every index must stay the same) and each catheter shifted along and across
// itself (the reconstruction and treatment-day uncertainty a robust plan must tolerate).
#pragma once

#include <Eigen/Geometry>
#include <map>
#include <string>
#include <vector>

#include "needle_guidance/dose/dose_indices.h"
#include "needle_guidance/dose/hdr_case.h"

namespace needle_guidance::dose {

/// The case moved rigidly by `pose` (x_new = pose * x): contours, catheters, dwell positions
/// and axes, dose points. The rotation must keep the contour planes axial (turns about z, 180
/// degrees about x or y): throws std::invalid_argument otherwise. Dwell times are kept.
HdrCase transformedCase(const HdrCase& c, const Eigen::Isometry3d& pose);

/// Largest change between two index sets over the keys defined in both: D indices [Gy] and V
/// indices [percentage points] separately. A key defined in only one counts as infinite change.
struct IndexChange {
  double dose_Gy = 0.0, volume_pp = 0.0;
  std::string worst_dose, worst_volume;  ///< the keys that changed most
};
IndexChange indexChange(const std::map<std::string, DoseVolumeIndex>& a,
                        const std::map<std::string, DoseVolumeIndex>& b);

/// Per catheter, a rigid shift: along the catheter uniform in [-max, max], across it uniform
/// in a disc of radius max. Dwell positions move with their catheter.
HdrCase shiftedCatheters(const HdrCase& c, double max_shift_m, unsigned seed);

/// One index's spread under catheter shifts: the index minus its nominal value over the
/// samples (Gy or percentage points).
struct IndexSpread {
  double nominal = 0.0, p5 = 0.0, p95 = 0.0, sd = 0.0, worst = 0.0;  ///< worst: largest |change|
  int samples = 0;  ///< samples in which the index is defined
};

/// Evaluates `times_s` on `samples` seeded catheter-shift copies of c (seeds seed .. seed +
/// samples - 1) with the index `specs` on a spacing_m structure lattice.
std::map<std::string, IndexSpread> shiftSpread(
    const HdrCase& c, const Tg43Source& source, const std::vector<double>& times_s,
    const std::map<std::string, std::vector<std::string>>& specs, double max_shift_m, int samples,
    unsigned seed, double spacing_m);

}  // namespace needle_guidance::dose
