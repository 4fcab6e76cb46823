// DICOM-RT import and export of HDR brachytherapy cases (RTPLAN, RTSTRUCT, RTDOSE; DCMTK inside,
// never in this header) and the gamma index used to validate our TG-43 dose against a vendor
// RTDOSE. Frame: the DICOM patient frame; DICOM millimetres become metres on import and metres
// become millimetres on export (docs/architecture.md, "Frames and units").
//
// Errors: every bad input (missing or unreadable file, wrong modality / SOP class, missing or
// malformed tag, inconsistent sizes) throws std::invalid_argument (or std::runtime_error for I/O
// failures) whose message names the file, the tag and the reason. No NaN is ever returned.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/dose/hdr_case.h"

namespace needle_guidance::dose {

/// How an RTPLAN channel writes its CumulativeTimeWeight (300A,02D6). Each dwell position is a
/// pair of control points at the same position; the dwell time of position k is
///   t_k = (CTW[2k+1] - CTW[2k]) * ChannelTotalTime / FinalCumulativeTimeWeight
/// in both encodings, but they differ between pairs:
enum class DwellTimeEncoding {
  kNoActiveDwells,        ///< no channel has a non-zero weight: nothing to tell
  kStandardCumulative,    ///< DICOM PS3.3 C.8.8.15: monotonic, no time between pairs
                          ///< (0, 2.1, 2.1, 3.6, ...)
  kPerPairNonCumulative,  ///< non-standard: 0 at the first point of each pair, that position's
                          ///< weight at the second (0, 6.7, 0, 3.4, ...); consecutive differences
                          ///< across pairs would be negative "transit times"
  kIndistinguishable,     ///< each channel's only weight is at its last control-point pair: both
                          ///< readings agree
  kMixed,                 ///< some channels use one encoding and some the other
};

/// "standard_cumulative", "per_pair_non_cumulative", ...
std::string toString(DwellTimeEncoding encoding);

/// The DICOM-RT objects found in a folder (paths empty when absent).
struct DicomRtFiles {
  std::string plan;           ///< RTPLAN (RT Plan Storage, Modality RTPLAN)
  std::string structure_set;  ///< RTSTRUCT
  std::string dose;           ///< RTDOSE
};

/// Scans the regular files of `dir` (not recursive) and classifies them by SOP Class UID
/// (0008,0016), falling back to Modality (0008,0060). With several RTSTRUCT (RTDOSE) objects the
/// one referenced by the plan's ReferencedStructureSetSequence (ReferencedRTPlanSequence) wins.
/// Throws std::invalid_argument if `dir` is not a directory, holds no RTPLAN, or holds several
/// RTPLANs or ambiguous RTSTRUCT / RTDOSE objects.
DicomRtFiles findDicomRtFiles(const std::string& dir);

/// What the importer saw besides the case itself (for reports and sanity checks).
struct DicomRtImportReport {
  std::string plan_path;
  std::string structure_set_path;  ///< empty if imported without RTSTRUCT
  DwellTimeEncoding encoding = DwellTimeEncoding::kNoActiveDwells;  ///< whole plan
  std::vector<DwellTimeEncoding> channel_encodings;                 ///< one per catheter
  int fractions_planned = 1;        ///< NumberOfFractionsPlanned (300A,0078)
  double total_dwell_time_s = 0.0;  ///< sum of the imported dwell times (one fraction)
  std::optional<double>
      total_reference_air_kerma_uGy;             ///< TotalReferenceAirKerma (300A,0250), summed
  std::string source_type;                       ///< SourceType (300A,0214), e.g. LINE
  std::optional<double> active_source_length_m;  ///< ActiveSourceLength (300A,021A)
  std::string source_strength_reference_date;    ///< (300A,022C); S_K is NOT decay-corrected
  int orientation_flips = 0;  ///< ControlPointOrientation vectors reversed to point at the tip
  double max_axis_deviation_rad = 0.0;  ///< largest angle between ControlPointOrientation and the
                                        ///< catheter direction (after flipping)
  std::vector<std::string> warnings;    ///< non-fatal oddities, one sentence each
};

/// Options for import.
struct DicomRtImportOptions {
  /// Written to HdrCase::source (config/sources/ name): DICOM carries no TG-43 data set name.
  /// Empty keeps the HdrCase default.
  std::string source_name;
};

/// Imports the RTPLAN and (if present) RTSTRUCT found in `dir` (see findDicomRtFiles).
///  * structures: the CLOSED_PLANAR contours of every RTSTRUCT ROI that is not a BRACHY_CHANNEL
///    (one axial Contour per DICOM contour; repeated closing vertex dropped); role kTarget if the
///    name contains "prostate", "ptv" or "ctv" (case-insensitive) or RTROIInterpretedType is
///    PTV/CTV/GTV, else kOrganAtRisk; Structure::normalise() is called on each.
///  * catheters: one per RTPLAN channel, named by SourceApplicatorID (else "channel N"): the
///    polyline of the referenced BRACHY_CHANNEL ROI (ReferencedROINumber (3006,0084)) oriented so
///    that its first point is the distal tip, else the dwell positions in order of increasing
///    ControlPointRelativePosition (distance from the distal-most source position).
///  * dwells: one per control-point pair (zero-time positions kept), ordered from the tip;
///    axis = unit vector towards the catheter tip: ControlPointOrientation (300A,0412) if
///    present (reversed if it points away from the tip), else the catheter direction.
///  * dwell_times_s from the cumulative time weights (either DwellTimeEncoding, detected per
///    channel and checked against FinalCumulativeTimeWeight), one fraction.
///  * air_kerma_strength_U = ReferenceAirKermaRate (300A,022A) [uGy h^-1 at 1 m = U], as
///    written (no decay correction); prescription_Gy per fraction from BrachyApplicationSetupDose
///    (300A,00A4), else TargetPrescriptionDose (300A,0026) / fractions.
/// @param[out] report optional details (encoding found, totals, warnings)
/// Throws std::invalid_argument naming the file, tag and reason for any bad input.
HdrCase importDicomRt(const std::string& dir, DicomRtImportReport* report = nullptr,
                      const DicomRtImportOptions& options = {});

/// Same with explicit files; `structure_set_path` may be empty (no structures; catheters from
/// the control points).
HdrCase importDicomRt(const std::string& plan_path, const std::string& structure_set_path,
                      DicomRtImportReport* report = nullptr,
                      const DicomRtImportOptions& options = {});

/// A dose grid on an axis-aligned DICOM image grid (ImageOrientationPatient = 1\0\0\0\1\0).
/// Voxel (i, j, k) = (column, row, frame) sits at
///   origin_m + (i * spacing_m.x(), j * spacing_m.y(), z_offsets_m[k]).
struct DoseGrid {
  Point3 origin_m = Point3::Zero();  ///< centre of voxel (0,0,0): ImagePositionPatient [m]
  Eigen::Vector3d spacing_m =
      Eigen::Vector3d::Ones();           ///< column, row spacing; z: mean |frame step| [m]
  std::array<int, 3> sizes = {0, 0, 0};  ///< columns, rows, frames
  std::vector<double> z_offsets_m;  ///< frame z relative to origin_m.z() [m], strictly monotone
  std::vector<double> dose_Gy;      ///< index i + nx * (j + ny * k) [Gy]
  std::string summation_type;       ///< DoseSummationType (3004,000A), e.g. PLAN

  std::size_t voxelCount() const { return dose_Gy.size(); }
  std::size_t index(int i, int j, int k) const {
    return static_cast<std::size_t>(i) +
           static_cast<std::size_t>(sizes[0]) *
               (static_cast<std::size_t>(j) +
                static_cast<std::size_t>(sizes[1]) * static_cast<std::size_t>(k));
  }
  /// Centre of voxel (i, j, k) [m]. No bounds check.
  Point3 position(int i, int j, int k) const {
    return origin_m +
           Point3(i * spacing_m.x(), j * spacing_m.y(), z_offsets_m[static_cast<std::size_t>(k)]);
  }
  double at(int i, int j, int k) const { return dose_Gy[index(i, j, k)]; }
  double& at(int i, int j, int k) { return dose_Gy[index(i, j, k)]; }

  /// Trilinear interpolation [Gy] at p (frames may be unevenly spaced). False (and *dose_Gy
  /// untouched) if p lies outside the convex hull of the voxel centres.
  bool interpolate(const Point3& p, double* dose_Gy) const;
  /// Largest voxel dose [Gy] (0 for an empty grid).
  double maxDose() const;
  /// Checks sizes >= 1, spacing > 0 and finite, z offsets strictly monotone with the right count,
  /// dose_Gy.size() == product of sizes, doses finite and >= 0. Throws std::invalid_argument
  /// starting with `what`.
  void validate(const std::string& what = "DoseGrid") const;
};

/// Reads an RTDOSE file: ImagePositionPatient, ImageOrientationPatient (must be 1\0\0\0\1\0),
/// PixelSpacing (row\column spacing), Rows, Columns, NumberOfFrames, GridFrameOffsetVector
/// (relative, or absolute if its first value equals the origin z), DoseGridScaling, DoseUnits
/// (must be GY), BitsAllocated 16 or 32 uncompressed pixel data (unsigned; signed accepted if no
/// value is negative). Throws std::invalid_argument naming the file, tag and reason.
DoseGrid readRtDose(const std::string& path);

/// The identity an exported object carries (Patient, General Study, Frame of Reference modules)
/// and the objects it references. Empty UIDs are generated on writing.
struct DicomExportContext {
  std::string patient_name = "needle_guidance^export";
  std::string patient_id = "NG0001";
  std::string patient_birth_date;
  std::string patient_sex;
  std::string study_uid;
  std::string study_id = "1";
  std::string study_date = "20260101";  ///< YYYYMMDD; also the series / plan / structure set date
  std::string study_time = "000000";
  std::string frame_uid;
  std::string sop_instance_uid;   ///< of the object written
  std::string structure_set_uid;  ///< RTPLAN -> RTSTRUCT (ReferencedStructureSetSequence)
  std::string plan_uid;           ///< RTDOSE -> RTPLAN (ReferencedRTPlanSequence)
  int series_number = 1;
};

/// A context with fresh study and frame-of-reference UIDs.
DicomExportContext newExportContext();
/// A context with the patient, study and frame of reference of an existing DICOM object (e.g. the
/// clinical RTSTRUCT), fresh object UIDs. Throws std::invalid_argument naming file and tag.
DicomExportContext exportContextFrom(const std::string& path);

/// The writers below with an explicit context (the context-free ones use newExportContext()).
void writeRtDose(const DoseGrid& grid, const std::string& path, const DicomExportContext& context);
void writeRtStruct(const HdrCase& c, const std::string& path, const DicomExportContext& context);
void writeRtPlan(const HdrCase& c, const std::string& path, DwellTimeEncoding encoding,
                 const DicomExportContext& context);

/// Writes `grid` as an RTDOSE (uint32, DoseGridScaling = max / (2^32 - 1), PHYSICAL, GY, Explicit
/// VR Little Endian). Throws std::invalid_argument for an invalid grid, std::runtime_error if the
/// file cannot be written.
void writeRtDose(const DoseGrid& grid, const std::string& path);

/// Writes the case's structures (CLOSED_PLANAR ROIs 1..S, ORGAN or PTV by role) and catheters
/// (BRACHY_CHANNEL OPEN_NONPLANAR ROIs S+1..S+C, tip first) as an RTSTRUCT.
void writeRtStruct(const HdrCase& c, const std::string& path);

/// Writes the case's plan as an HDR RTPLAN: one channel per catheter referencing ROI S+1+index
/// (as written by writeRtStruct), two control points per dwell position with the given
/// time-weight encoding, ChannelTotalTime = FinalCumulativeTimeWeight = the channel's total time,
/// ReferenceAirKermaRate = S_K, BrachyApplicationSetupDose = TargetPrescriptionDose = Rx, one
/// fraction. dwell_times_s must be empty (all zero) or match dwells. Throws std::invalid_argument.
void writeRtPlan(const HdrCase& c, const std::string& path,
                 DwellTimeEncoding encoding = DwellTimeEncoding::kStandardCumulative);

/// A voxel index (column, row, frame).
struct VoxelIndex {
  int i = 0;
  int j = 0;
  int k = 0;
};

/// Every voxel with dose >= min_dose_Gy, in storage order.
std::vector<VoxelIndex> voxelsAtOrAbove(const DoseGrid& grid, double min_dose_Gy);

/// A reproducible sample of at most `max_samples` voxels (all of them if max_samples == 0 or
/// >= voxels.size()): partial Fisher-Yates shuffle driven by std::mt19937(seed), whose output is
/// fixed by the C++ standard (so the sample is the same on every platform).
std::vector<VoxelIndex> sampleVoxels(const std::vector<VoxelIndex>& voxels, std::size_t max_samples,
                                     std::uint32_t seed);

/// Global gamma criteria (Low et al., Med. Phys. 25 (1998) 656).
struct GammaCriteria {
  double dose_fraction = 0.03;  ///< dose-difference criterion as a fraction of normalisation_Gy
  double dta_m = 3e-3;          ///< distance-to-agreement criterion [m]
  double normalisation_Gy = 0;  ///< global normalisation dose, usually the prescription [Gy], > 0
  double search_step_fraction = 0.1;  ///< reference search step as a fraction of dta_m (DTA/10)
};

struct GammaResult {
  double pass_rate = 0.0;  ///< fraction (0-1) of points with gamma <= 1
  int points = 0;          ///< points evaluated
  int points_outside = 0;  ///< points outside the reference grid (counted as failing)
  double mean_gamma =
      0.0;  ///< over the points inside the grid (gamma capped at the search radius, see gammaIndex)
  double max_gamma = 0.0;
  /// median over the points inside the grid with reference dose > 0 of
  /// (evaluated - reference) / reference, the reference interpolated at the point itself.
  double median_relative_difference = 0.0;
};

/// Global gamma index of evaluated doses at points_m against the reference grid:
///   gamma(p) = min over q of sqrt(|q - p|^2 / DTA^2 + (D_ref(q) - D_eval(p))^2 / (dD * Dnorm)^2)
/// with q on a cubic lattice of step search_step_fraction * DTA inside the sphere |q - p| <= DTA
/// and D_ref trilinearly interpolated (sub-voxel). Pass/fail (gamma <= 1) is exact up to the
/// lattice; for failing points the value reported is the minimum over that sphere (> 1, an
/// upper bound of the true gamma). Lattice points outside the grid are skipped.
/// Throws std::invalid_argument for sizes that differ, non-finite doses or bad criteria.
GammaResult gammaIndex(const DoseGrid& reference, const std::vector<Point3>& points_m,
                       const std::vector<double>& evaluated_Gy, const GammaCriteria& criteria);

/// Our TG-43 dose [Gy] at every voxel centre of `geometry` (its dose values are ignored): the
/// case's dwells with time > 0, its dwell times and S_K, through doseRateMatrix with
/// min_distance 0 (the TG-43 model's own near-source handling applies), times `scale` (e.g. the
/// number of fractions for a PLAN dose). Throws std::invalid_argument for a bad case or grid.
DoseGrid computeDoseOnGrid(const HdrCase& c, const Tg43Source& source, const DoseGrid& geometry,
                           SourceModel model = SourceModel::kLine, double scale = 1.0);

/// Settings of validateAgainstRtDose; the defaults are the thresholds justified in dicom_rt.cpp.
struct RtDoseValidationOptions {
  double low_dose_cutoff = 0.10;     ///< compare voxels with RTDOSE >= this fraction of Rx
  std::size_t gamma_samples = 3000;  ///< fixed-seed sample for the gamma index (0 = all voxels)
  std::uint32_t seed = 1;
  double min_gamma_3pct3mm = 0.99;  ///< pass rate required in both directions
  double max_abs_median = 0.01;     ///< |median relative difference|
  double max_p95_abs = 0.02;        ///< 95th percentile of |relative difference|
};

/// Result of comparing our dose with an RTDOSE.
struct RtDoseValidation {
  bool pass = false;
  std::vector<std::string> reasons;  ///< why it failed (empty when it passes), then hints
  double normalisation_Gy = 0.0;     ///< Rx x fraction factor: the global gamma normalisation
  double fraction_factor = 1.0;      ///< our one-fraction dose is scaled by this (PLAN dose)
  std::size_t voxels = 0;            ///< RTDOSE voxels >= low_dose_cutoff x Rx
  std::size_t gamma_points = 0;
  GammaResult gamma33_ours_vs_rtdose;  ///< our dose at the sampled voxels against the RTDOSE grid
  GammaResult gamma33_rtdose_vs_ours;  ///< RTDOSE voxel values against our dose grid
  GammaResult gamma22_ours_vs_rtdose;
  GammaResult gamma22_rtdose_vs_ours;
  /// (ours - RTDOSE) / RTDOSE over all compared voxels.
  double median_relative_difference = 0.0;
  double p95_abs_relative_difference = 0.0;
  double p99_abs_relative_difference = 0.0;
  int worst_frame = -1;  ///< frame with the largest |median| (>= 20 voxels), -1 if none
  double worst_frame_median = 0.0;
  std::size_t worst_frame_voxels = 0;
  /// Registration diagnostic: the whole-voxel displacement d (one axis, up to 2 voxels) for which
  /// our dose at (written position + d) best matches the RTDOSE values; zero if none beats d = 0.
  Point3 best_shift_m = Point3::Zero();
  double best_shift_median_abs = 0.0;  ///< median |relative difference| with that displacement
  double unshifted_median_abs = 0.0;

  double gamma3pct3mm() const;  ///< worse of the two directions
  double gamma2pct2mm() const;
};

/// Compares our TG-43 dose for the imported plan with a vendor RTDOSE: relative differences at
/// every RTDOSE voxel >= low_dose_cutoff x Rx, global gamma 3 %/3 mm and 2 %/2 mm (Rx-normalised)
/// in both directions at a fixed-seed sample of them, a per-frame and a shift diagnostic, and
/// the verdict. `fractions` scales our dose when the RTDOSE DoseSummationType is PLAN (or empty).
/// Throws std::invalid_argument if no voxel reaches the cut-off or the inputs are invalid.
RtDoseValidation validateAgainstRtDose(const HdrCase& c, const Tg43Source& source,
                                       const DoseGrid& rtdose, int fractions,
                                       const RtDoseValidationOptions& options = {});

}  // namespace needle_guidance::dose
