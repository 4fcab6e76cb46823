#include "needle_guidance/procedures/rigid_implant.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::procedures {

const char* toString(TargetOutcome outcome) {
  switch (outcome) {
    case TargetOutcome::kPlaced:
      return "placed";
    case TargetOutcome::kMissed:
      return "missed";
    case TargetOutcome::kRefused:
      return "refused";
    case TargetOutcome::kError:
      return "error";
  }
  return "?";
}

namespace {

std::vector<ImplantTarget> planarTargets(const scene::Scene& scene) {
  std::vector<ImplantTarget> out;
  for (const auto& t : scene.targets) {
    out.push_back({t.name, Point3(t.position.x(), t.position.y(), 0.0)});
  }
  return out;
}

}  // namespace

RigidImplantProcedure::RigidImplantProcedure(const scene::Scene& scene,
                                             RigidImplantSettings settings)
    : RigidImplantProcedure(scene.name, planarTargets(scene), scene.workspace_min.x(), settings) {}

RigidImplantProcedure::RigidImplantProcedure(std::string scene_name,
                                             std::vector<ImplantTarget> targets, double entry_x_m,
                                             RigidImplantSettings settings)
    : scene_name_(std::move(scene_name)),
      targets_(std::move(targets)),
      entry_x_m_(entry_x_m),
      settings_(settings) {
  auto positive = [](double v) { return std::isfinite(v) && v > 0.0; };
  if (!positive(settings_.insertion_velocity_m_s) || !positive(settings_.retract_velocity_m_s) ||
      !positive(settings_.height_velocity_m_s) || !positive(settings_.placement_tolerance_m) ||
      !(settings_.retract_depth_m <= entry_x_m_) || !(settings_.depth_tolerance_m >= 0.0) ||
      !(settings_.velocity_tolerance >= 0.0) || settings_.max_targets < 0) {
    throw std::invalid_argument(
        "RigidImplantProcedure: velocities and placement tolerance must be > 0, tolerances >= 0, "
        "max_targets >= 0 and the retract depth outside the tissue (<= the entry face x)");
  }
}

bool RigidImplantProcedure::runTarget(RigidImplantDevices& devices, TargetRecord& r,
                                      double& depth_now) const {
  if (devices.hasPlanner()) {
    r.plan = devices.plan(r.target);
    if (!r.plan.ok) {
      r.outcome = r.plan.refused ? TargetOutcome::kRefused : TargetOutcome::kError;
      r.reason = r.plan.message;
      r.status = "plan failed";
      return !devices.fault();
    }
    r.aim = r.plan.release;
  }
  if (devices.fault()) {
    r.status = "interrupted";
    return false;
  }
  r.height = devices.moveHeight(r.aim.y(), settings_.height_velocity_m_s);
  if (r.height.ok && settings_.lateral_stage) {
    r.lateral = devices.moveLateral(r.aim.z(), settings_.height_velocity_m_s);
  }
  if (r.height.ok && (r.lateral.ok || !settings_.lateral_stage)) {
    r.insert = devices.moveDepth(r.aim.x(), settings_.insertion_velocity_m_s, depth_now, false);
  }
  if (const auto tip = devices.tip()) {
    r.tip_error_m = (*tip - r.aim).norm();
  }
  std::string why_not;
  if (devices.hasTissue() && r.insert.ok && !devices.fault()) {
    const std::optional<int> id = devices.implantSeed(why_not);
    r.seed_id = id ? *id : -1;
  }
  if (devices.fault()) {
    r.status = "interrupted";
    return false;
  }
  r.retract =
      devices.moveDepth(settings_.retract_depth_m, settings_.retract_velocity_m_s, r.aim.x(), true);
  depth_now = r.retract.ok ? settings_.retract_depth_m : r.aim.x();
  if (r.seed_id >= 0 && r.retract.ok) {
    r.seed = devices.seedAtRest(r.seed_id).value_or(Point3(NAN, NAN, NAN));
  }
  r.status = !r.height.ok                               ? "height " + r.height.state
             : settings_.lateral_stage && !r.lateral.ok ? "lateral " + r.lateral.state
             : !r.insert.ok                             ? "insert " + r.insert.state
             : !r.retract.ok                            ? "retract " + r.retract.state
             : (devices.hasTissue() && r.seed_id < 0)   ? "no seed: " + why_not
                                                        : "ok";
  if (devices.hasTissue() && settings_.reset_between_needles && r.retract.ok) {
    devices.resetTissue();  // the next needle meets undisturbed tissue (4.4)
  }
  return !devices.fault();
}

void RigidImplantProcedure::classify(TargetRecord& r, bool with_tissue) const {
  if (r.status == "plan failed") {
    return;  // refused or error, with the planner's reason
  }
  const double depth_error = std::abs(r.insert.reached_m - r.aim.x());
  const double velocity_error =
      std::abs(r.insert.mean_velocity_m_s - settings_.insertion_velocity_m_s) /
      settings_.insertion_velocity_m_s;
  if (r.status == "ok" && depth_error > settings_.depth_tolerance_m) {
    std::ostringstream why;
    why << "insertion depth " << 1e3 * depth_error << " mm off the release point (tolerance "
        << 1e3 * settings_.depth_tolerance_m << " mm)";
    r.status = why.str();
  } else if (r.status == "ok" && velocity_error > settings_.velocity_tolerance) {
    std::ostringstream why;
    why << "insertion velocity " << 100.0 * velocity_error << " % off the commanded "
        << 1e3 * settings_.insertion_velocity_m_s << " mm/s (tolerance "
        << 100.0 * settings_.velocity_tolerance << " %)";
    r.status = why.str();
  }
  if (r.status == "ok" && with_tissue && !r.seed.allFinite()) {
    r.status = "seed not measured";
  }
  if (r.status != "ok") {
    r.outcome = TargetOutcome::kError;
    r.reason = r.status;
  } else if (with_tissue) {
    const double error = r.seedError_m();
    r.outcome =
        error <= settings_.placement_tolerance_m ? TargetOutcome::kPlaced : TargetOutcome::kMissed;
    r.reason = r.outcome == TargetOutcome::kMissed ? "seed error above the tolerance" : "";
  } else {
    r.outcome = TargetOutcome::kPlaced;  // robot only: the move is the placement
  }
}

RigidImplantReport RigidImplantProcedure::run(RigidImplantDevices& devices) const {
  RigidImplantReport report;
  report.scene = scene_name_;
  report.planned = devices.hasPlanner();
  report.with_tissue = devices.hasTissue();
  report.settings = settings_;
  const std::size_t count =
      settings_.max_targets > 0
          ? std::min<std::size_t>(targets_.size(), static_cast<std::size_t>(settings_.max_targets))
          : targets_.size();
  report.targets_in_scene = static_cast<int>(count);
  const double start_s = devices.now_s();
  double depth_now = settings_.retract_depth_m;
  for (std::size_t i = 0; i < count; ++i) {
    if ((report.fault = devices.fault())) {
      break;
    }
    TargetRecord r;
    r.name = targets_[i].name;
    r.target = r.aim = targets_[i].position;
    const bool carry_on = runTarget(devices, r, depth_now);
    report.fault = devices.fault();
    if (report.fault && r.status != "ok" && r.status != "plan failed") {
      r.status += " (" + report.fault->node + " died)";
    }
    classify(r, report.with_tissue);
    std::ostringstream line;
    line << "target " << i + 1 << "/" << count << " " << r.name << ": " << toString(r.outcome);
    if (std::isfinite(r.seedError_m()))
      line << ", seed error " << 1e3 * r.seedError_m() << " mm";
    if (!r.reason.empty())
      line << " (" << r.reason << ")";
    devices.progress(line.str());
    report.records.push_back(r);
    if (!carry_on || report.fault) {
      break;
    }
  }
  if (report.fault) {
    report.safe_stop = devices.safeStop(settings_.retract_depth_m, settings_.retract_velocity_m_s);
  }
  report.wall_time_s = devices.now_s() - start_s;
  return report;
}

}  // namespace needle_guidance::procedures
