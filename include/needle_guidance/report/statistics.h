// Summary statistics for benchmarks and planners: mean, sample standard deviation, quantiles.
#pragma once

#include <vector>

#include "needle_guidance/math.h"

namespace needle_guidance::report {

/// Arithmetic mean; 0 for an empty sample.
double mean(const std::vector<double>& v);
/// Sample standard deviation (n - 1); 0 for fewer than two values.
double sampleSd(const std::vector<double>& v);
/// The q-quantile with linear interpolation (needle_guidance/math.h).
using needle_guidance::quantile;
inline double median(std::vector<double> v) {
  return quantile(std::move(v), 0.5);
}

}  // namespace needle_guidance::report
