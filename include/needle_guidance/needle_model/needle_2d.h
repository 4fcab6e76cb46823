// The planar bevel-tip needle of dissertation 5.3: the tip state {p, theta, b}, the two controls
// (insert, flip) and the exact constant-curvature arc a control traces. Plain C++ and Eigen; no
// ROS. The steering MDP (steering/steering_model.h) discretises this model; the simulated needle
// of the insertion robot and the imaging tip tracker follow it continuously.
//
// Frames and conventions: everything lives in the x-y plane of frame `scene`, insertion mostly
// along +x (the dissertation's z is our x, its y our y). The tip orientation theta is the angle
// of the tip tangent from +x, counter-clockwise [rad]. Bevel left (b = 0) traces the control
// circle counter-clockwise (theta grows), bevel right (b = 1) clockwise (5.4.2).
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "needle_guidance/geometry/polygon.h"

namespace needle_guidance::needle_model {

using geometry::Point2;

/// Bevel direction b of 5.3: left traces arcs counter-clockwise, right clockwise.
enum class Bevel : std::uint8_t { kLeft = 0, kRight = 1 };
/// The two controls u of 5.3: insert a distance delta (u = 0), or rotate the needle base by
/// 180 degrees (bevel flip) and then insert a distance delta (u = 1).
enum class Control : std::uint8_t { kInsert = 0, kFlip = 1 };

/// "left" | "right".
std::string toString(Bevel bevel);
/// The inverse of toString(Bevel): "left" | "right" -> bevel; nullopt for anything else.
std::optional<Bevel> bevelFromString(const std::string& text);
/// "insert" | "flip".
std::string toString(Control control);

/// The other bevel direction.
inline Bevel flipped(Bevel bevel) {
  return bevel == Bevel::kLeft ? Bevel::kRight : Bevel::kLeft;
}

/// Continuous needle tip state w = {p, theta, b} (5.3).
struct TipPose {
  Point2 p_SceneTip = Point2::Zero();  ///< tip position in frame scene [m]
  double theta_rad = 0.0;              ///< tip tangent angle from +x, counter-clockwise [rad]
  Bevel bevel = Bevel::kLeft;
};

/// The continuous model of 5.3: apply `control` (a flip changes the bevel in place), deflect the
/// orientation by beta, then trace an arc of length arc_length_m and radius radius_m in the (new)
/// bevel direction. The MDP's transitions are this with beta restricted to multiples of
/// alpha = 2 pi / N_c, the start point on the grid and the end point rounded to the grid (see
/// steering::SteeringModel). A Monte Carlo simulator of the "true" needle calls this with
/// continuous beta ~ N(0, sigma_i or sigma_r).
/// @param[in] pose tip before the step; @param[in] beta_rad deflection [rad]
/// @param[in] arc_length_m delta [m], >= 0; @param[in] radius_m r [m], > 0
TipPose advanceTip(const TipPose& pose, Control control, double beta_rad, double arc_length_m,
                   double radius_m);

}  // namespace needle_guidance::needle_model
