// An HDR planning case built from a DICOM-RT folder (RTSTRUCT + RTPLAN, RTDOSE optional): the
// structures by name through a mapping, the catheters of the RTPLAN channels, candidate dwell
// positions every plan step along each catheter inside the target plus a margin (ch. 6.2), dose
// points as in 6.2.1 and Table 6.1's criteria scaled to the plan's prescription. The clinical
// plan's own dwell positions and times come along for the comparison (ch. 6.3.2 indices).
// DCMTK does the DICOM I/O (dicom_rt.cpp).
#pragma once

#include <map>
#include <string>
#include <vector>

#include "needle_guidance/dose/dicom_rt.h"
#include "needle_guidance/dose/dose_indices.h"
#include "needle_guidance/dose/dvh_optimization.h"
#include "needle_guidance/dose/dwell_optimization.h"
#include "needle_guidance/dose/hdr_case.h"
#include "needle_guidance/dose/prostate_case.h"

namespace needle_guidance::dose {

/// What a case file (YAML, config/hdr/dicom_case.yaml) sets; every key is optional.
///   structures: {prostate: [Prostate, CTV, PTV], urethra: [Urethra], rectum: [Rectum], bladder:
///   [Bladder]} margin_mm: 2.5            # candidate dwells within this of the target along the
///   catheter surface_spacing_mm: 4     # surface dose points every this along each contour
///   volume_points: 1500       # volume dose points, shared by structure volume
///   min_points_per_structure: 50
///   seed: 1
///   source: gammamed_plus_hdr # config/sources/ name (DICOM carries no TG-43 data set name)
///   criteria: [{structure: prostate, kind: surface, min_Gy: 16, max_Gy: 24, weight_under: 100,
///   weight_over: 100}, ...]
///   dvh_criteria: ["urethra D10 <= 115%", "rectum D2cc <= 12 Gy", "prostate V100 >= 90", ...]
/// The first name of `structures` is the target (its canonical name is the key: "prostate").
/// Without `criteria`, Table 6.1 scaled to the plan's prescription.
struct DicomCaseSettings {
  /// canonical name -> RTSTRUCT ROI names (case-insensitive); the first entry is the target.
  std::vector<std::pair<std::string, std::vector<std::string>>> structures = {
      {"prostate", {"prostate", "ctv", "ptv"}},
      {"urethra", {"urethra"}},
      {"rectum", {"rectum"}},
      {"bladder", {"bladder"}}};
  double margin_m = 2.5e-3;
  DosePointOptions points;
  std::string source = "gammamed_plus_hdr";
  std::vector<Criterion> criteria;  ///< empty: table61Criteria(prescription)
  /// Dose-volume criteria of the dose-volume planner, as written ("urethra D10 <= 115%", D
  /// limits in % of the prescription or Gy); empty: defaultDvhCriteria (dvh_optimization.h).
  std::vector<std::string> dvh_criteria;
};

/// The settings' dose-volume criteria at prescription rx. Throws std::invalid_argument.
std::vector<DvhCriterion> dvhCriteria(const DicomCaseSettings& settings, double prescription_Gy);

/// Reads a case file (see DicomCaseSettings). Throws std::invalid_argument naming the file and key.
DicomCaseSettings readDicomCaseSettings(const std::string& path);

struct DicomCase {
  HdrCase planning;  ///< candidate dwells, no times: what the optimiser plans
  HdrCase
      clinical;  ///< the same structures, points and criteria with the RTPLAN's dwells and times
  DicomRtFiles files;
  DicomRtImportReport import_report;
  double step_m = 0.0;      ///< plan step: median spacing of consecutive clinical dwells
  int clinical_active = 0;  ///< clinical dwells with t > 0
  int clinical_active_on_candidates = 0;  ///< ... within 0.5 mm of a candidate position
  double clinical_max_offset_m =
      0.0;  ///< largest distance of an active clinical dwell to a candidate
  std::vector<std::string> ignored_rois;  ///< RTSTRUCT ROIs that no mapping entry names
  std::vector<std::string> notes;         ///< non-fatal findings, one sentence each
};

/// Builds the case from `dir`. Throws std::invalid_argument (naming file, tag or structure) for
/// bad input: among others when no ROI maps to the target (the message lists the ROI names found).
DicomCase loadDicomCase(const std::string& dir, const DicomCaseSettings& settings = {});

/// Candidate dwell positions: every step_m along each catheter, on the lattice through the
/// catheter's first clinical dwell (so clinical positions are candidates), inside the target or
/// within margin_m of it along the catheter.
std::vector<DwellPosition> candidateDwells(const HdrCase& c,
                                           const std::vector<DwellPosition>& clinical,
                                           double step_m, double margin_m);

/// The planning case carrying the clinical plan's dwell times on the candidate dwells (an
/// active clinical dwell within 1 mm of a candidate on its catheter adds its time there): the
/// clinical plan as a point of the planner's model, and a start for it.
HdrCase planningWithClinicalTimes(const DicomCase& dc);

/// The comparison indices (6.3.2 plus the clinical comparison set), keyed "prostate_V100",
/// "prostate_V150", "prostate_V200", "prostate_D90", "urethra_D10", "urethra_D0.1cc",
/// "urethra_V125", "rectum_D2cc", "rectum_D0.1cc", "rectum_V75", "bladder_D2cc", "bladder_D0.1cc",
/// "bladder_V75" (V in % of volume, D in Gy; absent structures and undefined indices left out).
std::map<std::string, double> comparisonIndices(const std::vector<StructureDose>& doses,
                                                double prescription_Gy);
/// The same indices with the undefined ones and their reasons (e.g. D2cc of a 0.94 cm^3 rectum).
std::map<std::string, DoseVolumeIndex> comparisonIndexSet(const std::vector<StructureDose>& doses,
                                                          double prescription_Gy);
/// The specs of the comparison set per structure ({"urethra", {"D10", "D0.1cc", "V125"}}, ...).
std::map<std::string, std::vector<std::string>> comparisonIndexSpecs();

/// Writes `plan` (planning case with dwell times) as RS.dcm (structures + BRACHY_CHANNEL ROIs),
/// RP.dcm (Brachy RTPLAN, standard cumulative time weights, referencing RS.dcm) and, if
/// `dose_geometry` is non-null, RD.dcm (our TG-43 dose on that grid, referencing RP.dcm) into
/// `dir`, all in one study and frame of reference copied from the clinical RTSTRUCT if given.
void exportDicomRtPlan(const HdrCase& plan, const Tg43Source& source, const DoseGrid* dose_geometry,
                       const std::string& dir, const std::string& clinical_structure_set = "");

}  // namespace needle_guidance::dose

namespace needle_guidance::dose {

/// One plan evaluated on the fine grid: indices (comparisonIndices) and per-structure doses.
struct PlanEvaluation {
  std::map<std::string, double> indices;
  std::vector<StructureDose> doses;
  double objective = 0.0;  ///< IPSA penalty E (eq. 6.3) on the case's dose points
};

/// One LP plan of the urethra-weight sweep.
struct FrontPoint {
  double urethra_weight_scale = 1.0;  ///< multiplies the urethra criteria's over-dose weights
  double urethra_max_factor = 1.0;    ///< multiplies the urethra criteria's D_max (>= D_min kept)
  double v100_pct = 0.0, urethra_d10_Gy = 0.0, rectum_d2cc_Gy = 0.0, lp_s = 0.0;
  bool dominates_clinical = false;  ///< V100 >=, urethra D10 <=, rectum D2cc <= the clinical plan's
};

/// The clinical plan and our LP on the same catheters, dose engine and dose points.
struct ClinicalComparison {
  double matrix_s = 0.0;  ///< time to build the dose-rate matrix
  DwellResult lp;         ///< with the case's own criteria (scale 1)
  PlanEvaluation clinical, ours;
  std::vector<FrontPoint> front;
  bool clinical_dominated = false;  ///< some front point dominates the clinical plan
};

PlanEvaluation evaluatePlan(const HdrCase& c, const Tg43Source& source,
                            const std::vector<double>& times_s, double grid_m);

/// Plans the LP, evaluates both plans on a grid_m dose grid and sweeps the urethra weight over
/// `urethra_scales` for each urethra D_max factor in `urethra_max_factors` (1: Table 6.1's D_max;
/// below 1 the penalty starts below it). Empty scales: no front.
ClinicalComparison compareWithClinical(const DicomCase& dc, const Tg43Source& source,
                                       const std::vector<double>& urethra_scales,
                                       double grid_m = 1e-3,
                                       const std::vector<double>& urethra_max_factors = {1.0});

}  // namespace needle_guidance::dose
