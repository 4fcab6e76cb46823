// Summary statistics for benchmarks and planners: mean, sample standard deviation, quantiles.
#pragma once

#include <vector>

namespace needle_guidance::report {

/// Arithmetic mean; 0 for an empty sample.
double mean(const std::vector<double>& v);
/// Sample standard deviation (n - 1); 0 for fewer than two values.
double sampleSd(const std::vector<double>& v);
/// The q-quantile (q in [0, 1]) with linear interpolation between order statistics; 0 for an
/// empty sample. Throws std::invalid_argument for q outside [0, 1].
double quantile(std::vector<double> v, double q);
inline double median(std::vector<double> v) {
  return quantile(std::move(v), 0.5);
}

}  // namespace needle_guidance::report
