// P_s and the control at a continuous tip pose by one Bellman step (dissertation eq. 5.2) from the
// pose itself over the solved look-up table (5.4.2-5.4.3), instead of the value of the grid state
// the pose rounds to (PolicyTable::lookup).
//
// Why: beside an obstacle corner the rounded grid point can sit on the other side of the corner's
// expanded boundary, where P_s differs by up to 0.1 within 0.2 mm; the arcs traced from the pose
// itself see the corner where the needle does. The table and its hash are unchanged. Plain C++;
// no ROS.
#pragma once

#include <string>

#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance::steering {

/// Which control the step from a continuous pose applies.
enum class PoseControl {
  /// The table's control of the rounded state (PolicyTable::lookup): the policy the table
  /// serves, so the prediction is the P_s of that policy.
  kTable,
  /// The control that maximises the one-step value from the pose (look-ahead policy).
  kLookAhead,
};

/// The prediction at one pose.
struct PosePrediction {
  /// kOk, kOutsideGrid (not finite, outside the workspace or the grid), kInTarget (P_s = 1),
  /// kInObstacle (P_s = 0), judged on the continuous workspace (expanded obstacles, target disc).
  ControlLookup::Status status = ControlLookup::Status::kOutsideGrid;
  Control control = Control::kInsert;   ///< the control applied (kInsert unless kOk)
  double probability_of_success = 0.0;  ///< P_s after `control`, in [0, 1]
  /// P_s of each control from the pose (index 0 insert, 1 flip); 0 unless kOk.
  double control_ps[2] = {0.0, 0.0};

  explicit operator bool() const { return status == ControlLookup::Status::kOk; }
  /// E.g. "ok: flip, P_s = 0.734 (insert 0.701, flip 0.734)" or "in obstacle".
  std::string toString() const;
};

/// One exact Bellman step from a continuous pose over a solved table:
///
///   P_s(pose, u) = sum_d p_u(d) [arc from the pose with orientation (k0 + d) alpha / s stays free]
///                  V(end of that arc)
///
/// k0 the orientation index nearest theta; the deflection bins are those of the model
/// (SteeringModel::deflectionProbabilities, binSigma) shifted by theta - k0 alpha / s, so bin d
/// holds the deflections beta that start the arc closest to orientation k0 + d. The arcs and
/// the collision test are the continuous needle's (ContinuousWorkspace::traceArc, arc length
/// 2 pi r / N_c). V is taken as the model's transitions take it: kRounded, the table at the
/// rounded start position moved by the arc's rounded displacement; kInterpolated, the exact end
/// point in the target disc succeeds, else the bilinear split over the free corners of its cell.
/// At a grid state's own pose this is the solver's update, so it reproduces the table to within
/// its epsilon. Costs (2 controls x deflection bins) arc traces, a few microseconds. Thread-safe.
class ExactPosePrediction {
public:
  /// Keeps references to `model` and `table`, which must outlive this. Throws
  /// std::invalid_argument if the table was solved for another model (hash or grid).
  ExactPosePrediction(const SteeringModel& model, const PolicyTable& table,
                      PoseControl control = PoseControl::kTable);

  /// P_s at `pose` and the control applied there; never throws, never NaN.
  PosePrediction predict(const TipPose& pose) const noexcept;
  /// P_s at `pose` after control `u` (0 unless the pose is free, 1 in the target).
  double controlPs(const TipPose& pose, Control u) const noexcept;
  /// The policy whose P_s predict() gives: the table's control (kTable), or predict()'s
  /// control at every pose (kLookAhead). This object must outlive the returned function.
  SteeringPolicy policy() const;

  const ContinuousWorkspace& world() const { return world_; }

private:
  /// The pose's status (PosePrediction::status), shared by predict() and controlPs().
  ControlLookup::Status status(const TipPose& pose) const noexcept;
  /// The Bellman step from a free pose (status kOk) after control u.
  double stepPs(const TipPose& pose, Control u) const noexcept;

  const SteeringModel& model_;
  const PolicyTable& table_;
  PoseControl mode_;
  ContinuousWorkspace world_;
};

}  // namespace needle_guidance::steering
