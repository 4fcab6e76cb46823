// Event location for the needle–tissue interaction (dissertation 2.3.4–2.3.6), in scalar
// quantities along the needle, so any mesh dimension can use it. Between two events the linear
// quasi-static tissue answers affinely in the needle's depth: every reaction, tip force and node
// position is f0 + s (f1 - f0) over a step's fraction s, so the depth where a threshold is crossed
// (a cut, a stick–slip transition, a shaft node released on retraction) is found exactly from
// the step's two ends. The interaction is then the same however the motion is cut into steps.
#pragma once

#include <limits>

namespace needle_guidance::tissue::events {

/// No event within the step.
constexpr double kNever = std::numeric_limits<double>::infinity();

/// Fraction s in [0, 1] of a step where f0 + s (f1 - f0) first reaches `threshold` from below;
/// 0 when f0 >= threshold already; kNever when it stays below.
double upCrossing(double f0, double f1, double threshold);

/// Fraction s in [0, 1] where |r0 + s (r1 - r0)| first exceeds `limit` (a stuck shaft node
/// slips, 2.3.5); 0 when |r0| > limit already; kNever when it stays within.
double magnitudeCrossing(double r0, double r1, double limit);

/// A slipping shaft node sticks again (2.3.5) when, over a step of dt_s in which the needle
/// advances needle_advance_m and the node node_advance_m along the needle, its speed relative
/// to the needle is below stick_velocity_m_s.
bool sticks(double needle_advance_m, double node_advance_m, double dt_s, double stick_velocity_m_s);

}  // namespace needle_guidance::tissue::events
