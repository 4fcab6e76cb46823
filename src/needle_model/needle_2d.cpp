// The planar bevel-tip needle of dissertation 5.3 (needle_2d.h).
#include "needle_guidance/needle_model/needle_2d.h"

#include <cmath>

namespace needle_guidance::needle_model {

std::string toString(Bevel bevel) {
  return bevel == Bevel::kLeft ? "left" : "right";
}

std::optional<Bevel> bevelFromString(const std::string& text) {
  if (text == toString(Bevel::kLeft)) {
    return Bevel::kLeft;
  }
  if (text == toString(Bevel::kRight)) {
    return Bevel::kRight;
  }
  return std::nullopt;
}

std::string toString(Control control) {
  return control == Control::kInsert ? "insert" : "flip";
}

TipPose advanceTip(const TipPose& pose, Control control, double beta_rad, double arc_length_m,
                   double radius_m) {
  TipPose out;
  out.bevel = control == Control::kFlip ? flipped(pose.bevel) : pose.bevel;
  const double theta0 = pose.theta_rad + beta_rad;
  const double turn = arc_length_m / radius_m;
  // Left: centre on the left of the tangent, counter-clockwise; right: mirror image (5.3).
  const double side = out.bevel == Bevel::kLeft ? 1.0 : -1.0;
  const Point2 center =
      pose.p_SceneTip + side * radius_m * Point2(-std::sin(theta0), std::cos(theta0));
  out.theta_rad = theta0 + side * turn;
  out.p_SceneTip =
      center + side * radius_m * Point2(std::sin(out.theta_rad), -std::cos(out.theta_rad));
  return out;
}

}  // namespace needle_guidance::needle_model
