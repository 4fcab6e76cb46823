#include "needle_guidance/dose/dvh_comparison.h"

#include <cstdio>

#include "needle_guidance/dose/dicom_case.h"

namespace needle_guidance::dose {

bool higherIsBetter(const std::string& key, const std::string& target) {
  const std::size_t cut = key.rfind('_');
  if (cut == std::string::npos || key.substr(0, cut) != target)
    return false;
  const std::string spec = key.substr(cut + 1);
  if (spec.empty())
    return false;
  if (spec[0] == 'D')
    return spec.find("cc") == std::string::npos;
  return std::stod(spec.substr(1)) <= 100.0;
}

std::vector<std::string> worseIndices(const std::map<std::string, DoseVolumeIndex>& ours,
                                      const std::map<std::string, DoseVolumeIndex>& reference,
                                      const std::string& target) {
  std::vector<std::string> out;
  for (const auto& [key, ref] : reference) {
    const auto it = ours.find(key);
    if (!ref.defined || it == ours.end() || !it->second.defined)
      continue;
    const bool higher = higherIsBetter(key, target);
    const double ours_value = it->second.value;
    if (higher ? ours_value < ref.value - 1e-6 : ours_value > ref.value + 1e-6) {
      char text[160];
      std::snprintf(text, sizeof text, "%s %.2f %s %.2f", key.c_str(), ours_value,
                    higher ? "<" : ">", ref.value);
      out.push_back(text);
    }
  }
  return out;
}

Dominance dominate(const HdrCase& c, const Tg43Source& source,
                   const std::map<std::string, DoseVolumeIndex>& reference,
                   const std::string& target, const DvhPlanOptions& options) {
  std::vector<std::string> at_most, at_least;
  for (const auto& [key, index] : reference) {
    if (index.defined)
      (higherIsBetter(key, target) ? at_least : at_most).push_back(key);
  }
  Dominance d;
  d.plan = optimizeDvh(c, source, criteriaAt(reference, at_most, at_least), options);
  if (!d.plan.ok())
    return d;
  d.indices = comparisonIndexSet(structureDoses(c, source, d.plan.times_s, options.eval_spacing_m),
                                 c.prescription_Gy);
  d.worse = worseIndices(d.indices, reference, target);
  d.dominated = d.worse.empty();
  return d;
}

std::vector<DvhFrontPoint> dvhFront(const HdrCase& c, const Tg43Source& source,
                                    const std::vector<DvhCriterion>& criteria,
                                    const std::vector<double>& limits_Gy,
                                    const DvhPlanOptions& options) {
  std::vector<DvhFrontPoint> out;
  for (const double limit : limits_Gy) {
    std::vector<DvhCriterion> k;
    for (const DvhCriterion& x : criteria) {
      if (!(x.structure == "urethra" && x.index == "D10"))
        k.push_back(x);
    }
    k.push_back({"urethra", "D10", limit, true});
    const DvhPlanResult r = optimizeDvh(c, source, k, options);
    DvhFrontPoint p;
    p.urethra_d10_limit_Gy = limit;
    p.seconds = r.seconds;
    if (r.ok()) {
      p.v100_pct = r.v100_pct;
      const auto it = r.indices.find("urethra_D10");
      p.urethra_d10_Gy = it != r.indices.end() && it->second.defined ? it->second.value : 0.0;
      p.criteria_met = r.violated.empty();
    }
    out.push_back(p);
  }
  return out;
}

}  // namespace needle_guidance::dose
