// Dwell-time optimisation on the dose-volume criteria themselves (dissertation ch. 6; the
// mixed-integer form of Siauw et al., Med Phys 2011 (IPIP) and Gorissen, den Hertog and Hoffmann,
// PMB 2013): maximise the target's V100 subject to the organs' dose-volume criteria, with one
// binary per dose point and criterion saying whether the point may break the criterion's dose
// level. COIN-OR CBC solves it. Every criterion has an elastic budget, so a case whose criteria
// cannot all hold gets the least-violating plan and the criteria that give way are named.
#pragma once

#include <Eigen/Core>
#include <limits>
#include <map>
#include <string>
#include <vector>

#include "needle_guidance/dose/dose_indices.h"
#include "needle_guidance/dose/hdr_case.h"

namespace needle_guidance::dose {

/// One dose-volume criterion: `index` of `structure` at most (or at least) `limit`, e.g.
/// {"urethra", "D10", 18.4} (Gy), {"rectum", "V75", 5} (%), {"prostate", "V100", 90, false}.
struct DvhCriterion {
  std::string structure;  ///< canonical (lower-case) structure name
  std::string index;      ///< V<p>, D<p> or D<v>cc (doseVolumeIndex)
  double limit = 0.0;     ///< Gy for D indices, % of the structure's volume for V indices
  bool at_most = true;    ///< false: the index must be at least the limit
};

/// The default criteria at prescription rx (GEC-ESTRO / ABS prostate HDR monotherapy):
/// prostate V100 >= 90 %, V150 <= 35 %, V200 <= 11 %; urethra D10 <= 115 %, D0.1cc <= 118 %,
/// V125 <= 1 %; rectum and bladder D2cc <= 75 %, D0.1cc <= 80 %, V75 <= 5 %.
std::vector<DvhCriterion> defaultDvhCriteria(double prescription_Gy);

/// Parses "urethra D10 <= 115%" / "rectum V75 <= 5" / "prostate V100 >= 90": D limits in % of
/// the prescription (with %) or Gy (with Gy), V limits in % of the structure's volume. Throws
/// std::invalid_argument naming the text.
DvhCriterion parseDvhCriterion(const std::string& text, double prescription_Gy);

/// "urethra D10 <= 18.40 Gy".
std::string describe(const DvhCriterion& k);

struct DvhPlanOptions {
  /// "descent": descent on the criteria over the evaluation lattice (descendOnCriteria in
  /// src/dose/dvh_model.h), optimised and judged on the same points; "mip": the IPIP-style
  /// MIP on a coarse lattice (freeing LP heuristic, then CBC when cbc_seconds > 0).
  std::string method = "descent";
  /// Descent: each condition's dose level is moved by this fraction towards its safe side, so
  /// that a plan the surrogate accepts meets the exact criterion.
  double descent_level_margin = 2e-3;
  double descent_goal_step_pp = 2.0;  ///< descent: first coverage goal above the best plan [pp]
  int descent_patience = 40;  ///< descent: iterations without a better plan before the goal drops
  double descent_min_step_pp = 0.05;  ///< descent: stops when the goal step falls below this
  double plan_spacing_m = 2.5e-3;     ///< dose points of the MIP: structure lattice, this spacing
  /// ... or coarser, so that no structure has more than this many dose points.
  int max_points_per_structure = 600;
  /// An at-most criterion's point whose dose under equal dwell times (target mean = Rx) is
  /// below this fraction of the criterion's level is held below the level without a binary.
  double binary_dose_ratio = 0.5;
  double eval_spacing_m = 0.5e-3;  ///< lattice on which the criteria are checked and indices read
  double max_seconds = 5.0;        ///< processor-time limit of one plan [s]
  /// CBC's processor time per round after the heuristic or descent [s] (its incumbent); 0: no
  /// CBC, no bound.
  double cbc_seconds = 0.0;
  double relative_gap = 1e-3;  ///< CBC stops within this gap of its bound
  int rounds = 3;              ///< re-solves with limits tightened by the fine-lattice excess
  int heuristic_rounds = 8;    ///< LP solves of the freeing heuristic (CBC's incumbent)
  /// Penalty per percentage point of an organ's volume over a budget, against 1 per point of
  /// target V100: 100 makes the criteria come first and coverage second.
  double violation_penalty = 100.0;
  /// Criteria whose structure is absent or cannot support them are skipped with a note.
};

struct DvhPlanResult {
  std::string status = "ok";  ///< "ok", or why no plan was found
  std::vector<double> times_s;
  double seconds = 0.0;       ///< wall time
  double cpu_seconds = 0.0;   ///< processor time of this process
  double v100_pct = 0.0;      ///< target V100 on the evaluation lattice
  double mip_v100_pct = 0.0;  ///< target V100 on the planner's own dose points (see objective)
  /// The planner's objective on its own dose points (the evaluation lattice for the descent, the
  /// coarse lattice for the MIP; lower is better): minus the target V100, plus violation_penalty
  /// per percentage point over a criterion's stated budget.
  double objective = 0.0;
  /// The same objective and V100 for the dwell times the case carries (HdrCase::dwell_times_s,
  /// e.g. the clinical plan mapped onto the candidate dwells); NaN when it carries none. A
  /// value below `objective` shows a plan the planner missed on its own model.
  double case_times_objective = std::numeric_limits<double>::quiet_NaN();
  double case_times_v100_pct = std::numeric_limits<double>::quiet_NaN();
  /// With cbc_seconds > 0: the MIP objective of the plan minus CBC's proven bound (V100 points
  /// when no criterion gives way); without, unknown (mip_bound_known false).
  double mip_gap_pct = 0.0;
  bool mip_bound_known = false;
  bool mip_optimal = false;    ///< CBC proved optimality within relative_gap
  int binaries = 0, rows = 0;  ///< size of the last MIP
  int rounds = 0;
  int descent_iterations = 0;  ///< descent: iterations
  int points = 0;              ///< dose points of the evaluation lattice
  /// Processor time of building the evaluation lattice and its dose-rate matrix [s] (the rest
  /// of cpu_seconds is the LP start, the descent or MIP, and judging the plan).
  double setup_cpu_seconds = 0.0;
  /// Descent: the objective of its best start (the case's times, the LP's or equal times,
  /// scaled) and of its answer (before CBC); NaN for the MIP.
  double start_objective = std::numeric_limits<double>::quiet_NaN();
  double descent_objective = std::numeric_limits<double>::quiet_NaN();
  std::map<std::string, DoseVolumeIndex> indices;  ///< on the evaluation lattice
  std::vector<std::string> violated;               ///< criteria that give way (fine lattice)
  std::vector<std::string> notes;
  bool ok() const { return status == "ok"; }
};

/// Plans `c`'s dwell times on `criteria`. Throws std::invalid_argument for a case without dwell
/// positions, a criterion on an unknown index form, or options out of range.
DvhPlanResult optimizeDvh(const HdrCase& c, const Tg43Source& source,
                          const std::vector<DvhCriterion>& criteria,
                          const DvhPlanOptions& options = {});

/// The index set of `criteria` (the structure's indices the criteria name), for evaluation.
std::map<std::string, std::vector<std::string>> criteriaSpecs(
    const std::vector<DvhCriterion>& criteria);

/// Criteria from `indices` at their values: the at-most criteria become "no worse than this
/// plan" (used to ask for a plan that dominates a reference plan). `keys` are index keys
/// ("urethra_D10"); `at_least` keys must not decrease.
std::vector<DvhCriterion> criteriaAt(const std::map<std::string, DoseVolumeIndex>& indices,
                                     const std::vector<std::string>& at_most_keys,
                                     const std::vector<std::string>& at_least_keys);

}  // namespace needle_guidance::dose
