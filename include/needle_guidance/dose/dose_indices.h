// Dosimetric evaluation of a plan (dissertation 6.3.2): dose on a regular grid inside each
// structure, cumulative DVHs, and the standard indices — prostate V100, V150, D90; urethra
// V100, V150, D10; rectum and bladder V50, V100, D2cc (V in % of the structure's volume, D in Gy).
#pragma once

#include <map>
#include <string>
#include <vector>

#include "needle_guidance/dose/hdr_case.h"

namespace needle_guidance::dose {

/// Dose at the centres of a regular grid (spacing_m) inside every structure.
struct StructureDose {
  std::string name;
  double voxel_volume_m3 = 0.0;
  std::vector<double> dose_Gy;  ///< one per grid point inside the structure
};
std::vector<StructureDose> structureDoses(const HdrCase& c, const Tg43Source& source,
                                          const std::vector<double>& times_s,
                                          double spacing_m = 2e-3);

/// A source stop that is not one of the case's dwell positions (e.g. the source in transit
/// through a catheter, tripTransitSamples in delivery/schedule.h), with its time at the case's
/// S_K c.air_kerma_strength_U [s].
struct ExtraDwell {
  DwellPosition dwell;
  double time_s = 0.0;
};

/// Same, plus the dose of the `extra` stops at every grid point. The grid depends only on the
/// case's structures and spacing_m, so the doses of two calls on one case can be added point by
/// point. Throws std::invalid_argument for a times size mismatch, spacing <= 0, or an extra stop
/// with a negative or non-finite time, or a non-finite position or axis.
std::vector<StructureDose> structureDoses(const HdrCase& c, const Tg43Source& source,
                                          const std::vector<double>& times_s,
                                          const std::vector<ExtraDwell>& extra,
                                          double spacing_m = 2e-3);

/// V_x: % of the volume receiving at least `fraction` x prescription; D_x: the minimum dose of
/// the hottest x % (D90, D10) or of the hottest `cc` cubic centimetres (D2cc) [Gy]. A structure
/// without grid points gives NaN-free zeros with a note.
double volumePercentAbove(const StructureDose& s, double dose_Gy);
double doseCoveringPercent(const StructureDose& s, double percent);
double doseCoveringVolume(const StructureDose& s, double volume_m3);

/// The dissertation's index set, keyed "prostate_V100", "urethra_D10", "rectum_D2cc", ...
/// (structures found by name, case-insensitive; missing structures are skipped).
std::map<std::string, double> dosimetricIndices(const std::vector<StructureDose>& doses,
                                                double prescription_Gy);

/// Cumulative DVH: for each dose bin edge (0..max_Gy in bins), % of volume >= that dose.
std::vector<double> cumulativeDvh(const StructureDose& s, double max_Gy, int bins);

}  // namespace needle_guidance::dose
