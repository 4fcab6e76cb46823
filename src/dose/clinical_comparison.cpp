// The clinical comparison of dicom_case.h: the clinical RTPLAN's dwell times against our LP
// (dissertation 6.3.2) on the same dose engine, dose points and evaluation grid.
#include <algorithm>
#include <chrono>
#include <stdexcept>

#include "needle_guidance/dose/dicom_case.h"
#include "needle_guidance/dose/dwell_optimization.h"

namespace needle_guidance::dose {
namespace {

double seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

double indexOr(const std::map<std::string, double>& m, const std::string& key, double fallback) {
  const auto it = m.find(key);
  return it == m.end() ? fallback : it->second;
}

}  // namespace

PlanEvaluation evaluatePlan(const HdrCase& c, const Tg43Source& source,
                            const std::vector<double>& times_s, double grid_m) {
  PlanEvaluation e;
  e.doses = structureDoses(c, source, times_s, grid_m);
  e.indices = comparisonIndices(e.doses, c.prescription_Gy);
  Eigen::VectorXd dose(static_cast<Eigen::Index>(c.points.size()));
  for (std::size_t i = 0; i < c.points.size(); ++i) {
    dose(static_cast<Eigen::Index>(i)) = doseAt(c, source, times_s, c.points[i].position_m);
  }
  e.objective = penaltyModel(c)(dose);
  return e;
}

ClinicalComparison compareWithClinical(const DicomCase& dc, const Tg43Source& source,
                                       const std::vector<double>& urethra_scales, double grid_m,
                                       const std::vector<double>& urethra_max_factors) {
  ClinicalComparison out;
  auto t0 = std::chrono::steady_clock::now();
  const Eigen::MatrixXd d = doseRateMatrix(dc.planning, source);
  out.matrix_s = seconds(t0);
  out.lp = optimizeLp(dc.planning, d);
  if (!out.lp.ok()) {
    throw std::runtime_error("compareWithClinical: LP failed: " + out.lp.status);
  }
  out.clinical = evaluatePlan(dc.clinical, source, dc.clinical.dwell_times_s, grid_m);
  out.ours = evaluatePlan(dc.planning, source, out.lp.times_s, grid_m);
  const double big = 1e300;
  const double c_v100 = indexOr(out.clinical.indices, "prostate_V100", 0.0);
  const double c_u = indexOr(out.clinical.indices, "urethra_D10", big);
  const double c_r = indexOr(out.clinical.indices, "rectum_D2cc", big);
  for (const double max_factor : urethra_max_factors)
    for (const double scale : urethra_scales) {
      HdrCase c = dc.planning;
      for (Criterion& k : c.criteria) {
        if (k.structure == "urethra") {
          k.weight_over *= scale;
          k.max_Gy = std::max(k.min_Gy, k.max_Gy * max_factor);
        }
      }
      const DwellResult lp = optimizeLp(c, d);
      if (!lp.ok()) {
        throw std::runtime_error("compareWithClinical: LP failed at urethra scale " +
                                 std::to_string(scale));
      }
      const auto idx =
          comparisonIndices(structureDoses(c, source, lp.times_s, grid_m), c.prescription_Gy);
      FrontPoint p;
      p.urethra_weight_scale = scale;
      p.urethra_max_factor = max_factor;
      p.v100_pct = indexOr(idx, "prostate_V100", 0.0);
      p.urethra_d10_Gy = indexOr(idx, "urethra_D10", 0.0);
      p.rectum_d2cc_Gy = indexOr(idx, "rectum_D2cc", 0.0);
      p.lp_s = lp.seconds;
      p.dominates_clinical =
          p.v100_pct >= c_v100 && p.urethra_d10_Gy <= c_u && p.rectum_d2cc_Gy <= c_r;
      out.clinical_dominated = out.clinical_dominated || p.dominates_clinical;
      out.front.push_back(p);
    }
  return out;
}

}  // namespace needle_guidance::dose
