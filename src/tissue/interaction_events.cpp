#include "needle_guidance/tissue/interaction_events.h"

#include <algorithm>
#include <cmath>

namespace needle_guidance::tissue::events {

double upCrossing(double f0, double f1, double threshold) {
  if (f0 >= threshold) {
    return 0.0;
  }
  if (!(f1 >= threshold)) {
    return kNever;
  }
  return (threshold - f0) / (f1 - f0);  // f1 > f0 here, so the fraction lies in (0, 1]
}

double magnitudeCrossing(double r0, double r1, double limit) {
  if (std::abs(r0) > limit) {
    return 0.0;
  }
  double s = kNever;
  if (r1 > limit) {
    s = (limit - r0) / (r1 - r0);
  }
  if (r1 < -limit) {
    s = std::min(s, (-limit - r0) / (r1 - r0));
  }
  return s;
}

bool sticks(double needle_advance_m, double node_advance_m, double dt_s,
            double stick_velocity_m_s) {
  return std::abs(needle_advance_m - node_advance_m) < stick_velocity_m_s * dt_s;
}

}  // namespace needle_guidance::tissue::events
