// ROS wrapper of HDR dwell-time planning (node dwell_scheduler, dissertation ch. 6): plans a case
// with the LP or simulated annealing, turns the plan into an afterloader delivery schedule,
// publishes plan, DVH and rviz markers (latched), and evaluates what was delivered against it.
#pragma once

#include <ros/ros.h>
#include <visualization_msgs/MarkerArray.h>

#include <map>
#include <memory>
#include <string>
#include <vector>

#include "needle_guidance/DoseVolumeHistogram.h"
#include "needle_guidance/DwellPlan.h"
#include "needle_guidance/EvaluateDelivery.h"
#include "needle_guidance/PlanDwells.h"
#include "needle_guidance/procedures/hdr_pipeline.h"

namespace needle_guidance {

/// Serves `~plan` (PlanDwells) and `~evaluate` (EvaluateDelivery); publishes latched `~plan`
/// (DwellPlan), `~dvh` (DoseVolumeHistogram) and `~markers` (MarkerArray, frame ~frame_id).
/// A refused request changes nothing: the plans kept and the topics stay as they were.
class DwellSchedulerRos {
public:
  /// Reads and checks every parameter once and advertises; with ~plan_on_start plans the
  /// default synthetic case. Throws std::runtime_error naming a bad parameter or the failed
  /// start-up plan.
  DwellSchedulerRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);

  /// Parameters, read once (docs/nodes/dwell_scheduler.md).
  struct Settings {
    std::string frame_id = "patient";
    procedures::HdrPlanSettings pipeline;  ///< method (when a request leaves it empty), schedule
                                           ///< calibration, source speed, dose grid, DVH bins
    int default_synthetic_seed = 1;
  };

private:
  /// Everything a successful ~plan publishes, made before anything is stored or published.
  struct PlanOutcome {
    procedures::HdrPlan stored;
    DwellPlan plan;
    DoseVolumeHistogram dvh;
    visualization_msgs::MarkerArray markers;
    std::string summary;
  };

  bool onPlan(PlanDwells::Request& req, PlanDwells::Response& res);
  bool onEvaluate(EvaluateDelivery::Request& req, EvaluateDelivery::Response& res);

  /// Plans the request; throws std::invalid_argument (bad input) or std::runtime_error (solver
  /// or schedule failure) with a message naming what and where. Changes no member but the
  /// source cache.
  PlanOutcome makePlan(const PlanDwells::Request& req);
  /// Evaluates a delivery into `res` (success left to the caller); throws std::invalid_argument
  /// naming the bad entry.
  void evaluate(const EvaluateDelivery::Request& req, EvaluateDelivery::Response& res) const;
  /// Stores the plan and publishes it (the only place state changes); returns the plan message
  /// as published.
  DwellPlan commit(PlanOutcome outcome);
  /// A new plan id "<case>_<method>_<UTC time>_<n>" in [A-Za-z0-9_.-], not yet used.
  std::string newPlanId(const std::string& case_name, const std::string& method) const;

  Settings settings_;
  std::map<std::string, procedures::HdrPlan> plans_;
  procedures::SourceCache sources_;
  long plans_made_ = 0;
  ros::Publisher plan_pub_;
  ros::Publisher dvh_pub_;
  ros::Publisher markers_pub_;
  ros::ServiceServer plan_srv_;
  ros::ServiceServer evaluate_srv_;
};

}  // namespace needle_guidance
