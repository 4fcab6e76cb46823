// Constants and order statistics shared by every module: one definition of pi, and the sample
// quantiles the planners, detectors, validations and benchmarks report (src/common/math.cpp).
#pragma once

#include <vector>

namespace needle_guidance {

inline constexpr double kPi = 3.14159265358979323846;

/// The q-quantile (q in [0, 1]) with linear interpolation between order statistics (the mean of
/// the two middle values for q = 0.5); 0 for an empty sample. Throws std::invalid_argument for q
/// outside [0, 1].
double quantile(std::vector<double> v, double q);

/// The sample's element of rank floor(q (n - 1)) (q clamped to [0, 1]): a quantile that is one
/// of the values, without interpolation, in O(n); 0 for an empty sample.
double orderStatistic(std::vector<double> v, double q);

/// The element of rank n / 2 (the upper of the two middle values for an even n), in O(n); 0 for
/// an empty sample.
double upperMedian(std::vector<double> v);

}  // namespace needle_guidance
