// Our dose-volume plans against a reference plan (the clinical RTPLAN, or the IPSA-style
// annealing plan of a synthetic case) on the same dose engine and index method: a plan that is
// at least as good on every defined index at once (dominance), the indices that prevent it, and
// the trade-off front of target V100 against urethra D10 with the other criteria held.
#pragma once

#include <map>
#include <string>
#include <vector>

#include "needle_guidance/dose/dvh_optimization.h"

namespace needle_guidance::dose {

/// True if a larger value of index `key` ("prostate_V100") is better: the target's D<p> and
/// its V<p> up to V100; every other index is better smaller (hot spots, organ doses).
bool higherIsBetter(const std::string& key, const std::string& target);

/// The indices, defined in both sets, on which `ours` is worse than `reference`, as
/// "urethra_D10 17.31 > 17.20" (tolerance: 1e-6 in the index's unit).
std::vector<std::string> worseIndices(const std::map<std::string, DoseVolumeIndex>& ours,
                                      const std::map<std::string, DoseVolumeIndex>& reference,
                                      const std::string& target);

struct Dominance {
  DvhPlanResult plan;  ///< planned with every reference index as a criterion
  std::map<std::string, DoseVolumeIndex> indices;  ///< ours, comparison set
  bool dominated = false;          ///< ours at least as good on every index defined in both
  std::vector<std::string> worse;  ///< where not: the indices that prevent it
};

/// Plans c to dominate the reference indices (comparison set, see comparisonIndexSet):
/// each defined reference index becomes a criterion at its value, the target's V100 at least
/// the reference's and then maximised.
Dominance dominate(const HdrCase& c, const Tg43Source& source,
                   const std::map<std::string, DoseVolumeIndex>& reference,
                   const std::string& target, const DvhPlanOptions& options = {});

/// One point of the front: target V100 maximised with urethra D10 <= limit and the other
/// criteria held.
struct DvhFrontPoint {
  double urethra_d10_limit_Gy = 0.0;
  double v100_pct = 0.0, urethra_d10_Gy = 0.0;  ///< on the evaluation lattice
  double seconds = 0.0;
  bool criteria_met = false;  ///< no criterion gives way
};

/// The front over `limits_Gy` (urethra D10 limits), the criteria otherwise as given.
std::vector<DvhFrontPoint> dvhFront(const HdrCase& c, const Tg43Source& source,
                                    const std::vector<DvhCriterion>& criteria,
                                    const std::vector<double>& limits_Gy,
                                    const DvhPlanOptions& options = {});

}  // namespace needle_guidance::dose
