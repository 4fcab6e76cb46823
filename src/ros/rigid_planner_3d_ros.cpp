#include "needle_guidance/ros/rigid_planner_3d_ros.h"

#include <cmath>
#include <sstream>

#include "needle_guidance/cpu_time.h"
#include "needle_guidance/tissue_3d/tet_mesh_3d.h"

namespace needle_guidance {

RigidPlanner3Ros::RigidPlanner3Ros(ros::NodeHandle& private_nh, const std::string& scene_file,
                                   double tolerance_m)
    : scene_(tissue_3d::loadTissueScene3d(scene_file)) {
  const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
  model_ = std::make_unique<tissue_3d::TissueModel3>(tissue_3d::meshTissue3d(scene_, {}),
                                                     scene_.materialTable(), scene_.corotational);
  if (tolerance_m > 0.0) {
    options_.tolerance_m = tolerance_m;
  }
  planner_ = std::make_unique<tissue_3d::OffsetPlanner3>(scene_, *model_, options_);
  plan_srv_ = private_nh.advertiseService("plan", &RigidPlanner3Ros::onPlan, this);
  ROS_INFO_STREAM("rigid_planner: ready on 3-D scene '"
                  << scene_.name << "', " << model_->mesh().elements.size()
                  << " tetrahedra, built in " << clock.seconds() << " s CPU");
}

bool RigidPlanner3Ros::onPlan(PlanRigid::Request& req, PlanRigid::Response& res) {
  const tissue_3d::Vector3 target(req.target.x, req.target.y, req.target.z);
  res.tolerance_m = options_.tolerance_m;
  res.verified_error_m = NAN;
  res.predicted_implant.x = res.predicted_implant.y = res.predicted_implant.z = NAN;
  if (!target.allFinite()) {
    res.success = false;
    res.code = "target not finite";
    res.message = "the target is not a finite point";
    return true;
  }
  if (!req.mode.empty() && req.mode != "full") {
    res.success = false;
    res.code = "mode not supported";
    res.message = "mode '" + req.mode + "' is not supported in 3-D (only full)";
    return true;
  }
  std::ostringstream name;
  name << "(" << 1e3 * target.x() << ", " << 1e3 * target.y() << ", " << 1e3 * target.z() << ") mm";
  const tissue_3d::PlanResult3 plan = planner_->plan({name.str(), target});
  res.success = plan.placed;
  res.code = plan.placed                                ? "ok"
             : plan.unreachable                         ? "unreachable"
             : plan.refusal.rfind("simulation", 0) == 0 ? "simulation failed"
                                                        : "out of tolerance";
  res.message = plan.placed ? "ok" : plan.refusal;
  res.release.x = plan.tip_x_m;
  res.release.y = plan.lateral_m.x();
  res.release.z = plan.lateral_m.y();
  res.predicted_error_m = plan.predicted_error_m >= 0.0 ? plan.predicted_error_m : NAN;
  res.unplanned_error_m = plan.unplanned_error_m;  // < 0: undefined
  res.simulations = plan.simulations;
  res.planning_time_s = plan.plan_cpu_s;
  res.unimodal = true;
  res.verified = plan.verified_error_m >= 0.0;
  if (res.verified) {
    res.verified_implant.x = plan.verified_seed_m.x();
    res.verified_implant.y = plan.verified_seed_m.y();
    res.verified_implant.z = plan.verified_seed_m.z();
    res.verified_error_m = plan.verified_error_m;
  }
  res.within_tolerance = plan.placed;
  res.verifications = res.verified ? 1 : 0;
  res.budget_expired = false;
  if (plan.placed) {
    ROS_INFO_STREAM_NAMED("rigid_planner",
                          "plan for " << name.str() << ": tip x " << 1e3 * plan.tip_x_m
                                      << " mm at lateral (" << 1e3 * plan.lateral_m.x() << ", "
                                      << 1e3 * plan.lateral_m.y() << ") mm, verified error "
                                      << 1e3 * plan.verified_error_m << " mm, " << plan.simulations
                                      << " simulations, " << plan.plan_cpu_s << " s CPU");
  } else {
    ROS_WARN_STREAM_NAMED("rigid_planner",
                          "plan for " << name.str() << " refused: " << res.message);
  }
  return true;
}

}  // namespace needle_guidance
