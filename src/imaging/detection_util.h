// Small functions shared by the tip detector, the Hough baseline and the tip tracker (private to
// src/imaging).
#pragma once

#include <cmath>
#include <sstream>
#include <string>

#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/math.h"

namespace needle_guidance::imaging::detail {

/// Angle wrapped into [-pi, pi) [rad].
inline double wrapAngle(double a) {
  a = std::fmod(a + kPi, 2.0 * kPi);
  if (a < 0.0) {
    a += 2.0 * kPi;
  }
  return a - kPi;
}

/// v with `precision` decimals, for messages.
inline std::string fmt(double v, int precision = 3) {
  std::ostringstream s;
  s.setf(std::ios::fixed);
  s.precision(precision);
  s << v;
  return s.str();
}

/// A failed detection saying why.
inline Detection fail(const std::string& why) {
  Detection d;
  d.found = false;
  d.message = why;
  return d;
}

}  // namespace needle_guidance::imaging::detail
