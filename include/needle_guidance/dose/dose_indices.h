// Dosimetric evaluation of a plan (dissertation 6.3.2): dose at volume samples of each
// structure, cumulative DVHs, and dose-volume indices — prostate V100, V150, D90; urethra
// V100, V150, D10; rectum and bladder V50, V100, D2cc (V in % of the structure's volume, D in Gy).
//
// The samples lie on a lattice fixed to the structure, not to the patient frame: in each
// contour slab, planes at symmetric offsets; in each plane, a square lattice centred on the
// structure's area centroid and aligned with its in-plane principal axes. Turning the patient
// about its z axis (any angle), by 180 degrees about x or y, or moving it moves the samples with
// it, so the indices do not change. Each sample carries the volume of its slab plane's contour
// area shared among the plane's samples: the structure's volume is exact (contour area x slice
// thickness, the DICOM convention) and only the dose distribution inside is sampled.
#pragma once

#include <map>
#include <string>
#include <vector>

#include "needle_guidance/dose/dicom_rt.h"
#include "needle_guidance/dose/hdr_case.h"

namespace needle_guidance::dose {

/// Volume samples of one structure (see the file comment).
struct VolumeSample {
  std::vector<Point3> points_m;
  std::vector<double> volume_m3;  ///< the volume each point stands for; sums to the structure's
};

/// The structure-aligned lattice: in-plane spacing spacing_m, ceil(slice / dz) planes per
/// contour slab, dz = plane_spacing_m when it is > 0 and at most the slice spacing, else
/// spacing_m (plane_spacing_m = slice spacing: one plane, at the contour). A slab plane whose
/// contours hold no lattice point gets one sample at the centroid of its contours (a structure
/// smaller than the lattice keeps its volume). With plane_spacing_m larger than the slice spacing,
/// planes every plane_spacing_m instead, centred on the structure's z extent, each cut through its
/// nearest contour slice (a coarser sample for optimisation; volumes scaled to the structure's).
/// Throws std::invalid_argument for a spacing
/// <= 0 or not finite.
VolumeSample sampleStructure(const Structure& s, double spacing_m, double plane_spacing_m = 0.0);

/// The lattice spacing used for structure s when spacing_m is asked: spacing_m, finer for a
/// thin structure, coarser for a large one. A structure whose mean contour area A is below
/// thin_area_m2 gets spacing_m * sqrt(A / thin_area_m2): each of its planes holds as many samples
/// as a plane of thin_area_m2 would (400 at 0.5 mm; a 22 mm^2 rectum section gets 0.23 mm: at
/// 0.5 mm its few columns of samples alias with the isodose lines, and on the shared plan rectum
/// V75 is 1.2 pp off the converged value). Coarser so that the structure has at most about
/// max_samples samples (a 50 cm^3 prostate at 0.5 mm would need 400,000). Depends only on the
/// structure's volume and contour areas, so it moves with the patient.
double latticeSpacing(const Structure& s, double spacing_m, double max_samples = 50000,
                      double thin_area_m2 = 100e-6);

/// Dose at the volume samples of one structure.
struct StructureDose {
  std::string name;
  /// Volume of every sample when `volume_m3` is empty (a uniform grid).
  double voxel_volume_m3 = 0.0;
  std::vector<double> dose_Gy;    ///< one per sample inside the structure
  std::vector<double> volume_m3;  ///< per sample (empty: voxel_volume_m3 each)
  /// Volume of the structure without a dose (outside the dose grid it was read from) [m^3];
  /// any index of a structure with such a part is undefined.
  double outside_m3 = 0.0;
  double volume() const;  ///< sampled volume [m^3]
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

/// Dose at the volume samples of every structure of `c` from a dose grid (trilinear
/// interpolation). A sample beyond the outermost voxel centres but within half a voxel of them
/// takes the nearest voxel's dose (that voxel covers it); farther out its volume counts as
/// outside_m3. plane_spacing_m as in sampleStructure. adapt = false samples at spacing_m
/// itself instead of latticeSpacing(s, spacing_m) (a convergence study of the lattice).
std::vector<StructureDose> structureDosesFromGrid(const HdrCase& c, const DoseGrid& grid,
                                                  double spacing_m = 0.5e-3,
                                                  double plane_spacing_m = 0.0, bool adapt = true);
/// Dose of every structure of `c` on the dose grid's own discretisation, the way dicompyler-core
/// computes a DVH: the grid's in-plane voxel centres inside each contour, at the contour's
/// plane (dose linear between the grid's frames), each standing for the voxel's in-plane area
/// times the structure's slice spacing. Used to tell a discretisation difference from an error
/// when our indices are compared with dicompyler's; our own indices use the lattice above.
std::vector<StructureDose> structureDosesOnGridPixels(const HdrCase& c, const DoseGrid& grid);
// structureDoses and structureDosesFromGrid sample each structure at latticeSpacing(s, spacing).

/// V_x: % of the volume receiving at least dose_Gy; D_x: the minimum dose of the hottest x %
/// (D90, D10) or of the hottest volume_m3 (D2cc) [Gy]. A structure without samples gives 0 %
/// and 0 Gy; doseCoveringVolume of more than the structure's volume is NaN (see DoseVolumeIndex
/// for the checked form).
double volumePercentAbove(const StructureDose& s, double dose_Gy);
double doseCoveringPercent(const StructureDose& s, double percent);
double doseCoveringVolume(const StructureDose& s, double volume_m3);

/// One dose-volume index: a value, or undefined with the reason (never a number then).
struct DoseVolumeIndex {
  bool defined = false;
  double value = 0.0;  ///< Gy for D indices, % of the structure's volume for V indices
  std::string reason;  ///< why it is undefined (empty when defined)
};

/// The index `spec` of one structure: "V<p>" (% of volume at >= p % of the prescription, e.g.
/// V100, V75), "D<p>" (Gy to the hottest p %, e.g. D90) or "D<v>cc" (Gy to the hottest v cm^3,
/// e.g. D2cc, D0.1cc). Undefined when the structure has no samples, lies partly outside the dose
/// grid, or (D<v>cc) holds less than v cm^3. Throws std::invalid_argument for a malformed spec.
DoseVolumeIndex doseVolumeIndex(const StructureDose& s, const std::string& spec,
                                double prescription_Gy);

/// `specs` per structure name (lower case) -> "<structure>_<spec>" -> index, for every structure
/// of `doses` named in `specs` (case-insensitive).
std::map<std::string, DoseVolumeIndex> indexSet(
    const std::vector<StructureDose>& doses,
    const std::map<std::string, std::vector<std::string>>& specs, double prescription_Gy);

/// The defined values of an index set (undefined ones left out).
std::map<std::string, double> definedValues(const std::map<std::string, DoseVolumeIndex>& set);

/// The dissertation's index set, keyed "prostate_V100", "urethra_D10", "rectum_D2cc", ...
/// (structures found by name, case-insensitive; missing structures and undefined indices are
/// left out).
std::map<std::string, double> dosimetricIndices(const std::vector<StructureDose>& doses,
                                                double prescription_Gy);

/// Cumulative DVH: for each dose bin edge (0..max_Gy in bins), % of volume >= that dose.
std::vector<double> cumulativeDvh(const StructureDose& s, double max_Gy, int bins);

}  // namespace needle_guidance::dose
