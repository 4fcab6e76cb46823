// The 3-D procedure's world and report (steering_3d_trials.h).
#include "needle_guidance/procedures/steering_3d_trials.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/report/plot.h"
#include "needle_guidance/report/statistics.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/steering/monte_carlo.h"

namespace needle_guidance::procedures {

using needle_model::Control3;
using needle_model::TipPose3;
using steering_3d::TrialResult3;

SteeringTrial3::SteeringTrial3(const needle_model::Scene3d& scene,
                               const needle_model::CollisionWorld3& world,
                               const needle_model::NoiseParams3& noise, std::uint64_t seed,
                               int max_steps)
    : scene_(scene),
      world_(world),
      needle_(scene.needle, noise, seed),
      max_steps_(max_steps),
      seed_(seed) {
  result_.target_error_m = std::numeric_limits<double>::infinity();
}

void SteeringTrial3::start(const TipPose3& entry, double predicted_p_success,
                           double initial_plan_s) {
  tip_ = entry;
  estimate_ = entry;  // the guide's pose is known
  result_.predicted_p_success = predicted_p_success;
  result_.initial_plan_s = initial_plan_s;
  result_.path.assign(1, entry.p_SceneTip);
}

void SteeringTrial3::refuseStart(steering_3d::PlanCode code, const std::string& message) {
  result_.no_plan = code;
  result_.message = message;
  done_ = true;
}

void SteeringTrial3::setPlan(const std::vector<Control3>& controls) {
  plan_.assign(controls.begin(), controls.end());
}

bool SteeringTrial3::step() {
  if (done_) {
    return false;
  }
  if (plan_.empty()) {
    result_.message = "no plan to follow";
    end();
    return false;
  }
  const double step = scene_.step_length_m;
  std::deque<Control3> rest = plan_;  // the plan after this step (a few controls)
  const Control3 c = steering_3d::nextStep(rest, step);
  if (inserted_m_ + c.length_m > travel_m_ * (1.0 + 1e-9)) {
    std::ostringstream why;
    why << "refused: the next step would insert the needle to " << inserted_m_ + c.length_m
        << " m beyond the insertion joint's travel of " << travel_m_ << " m";
    result_.message = why.str();
    end();
    result_.success = false;  // the plan was not completed
    return false;
  }
  steering_3d::TrialOptions3 options;
  options.record_path = true;
  const bool free = world_step_
                        ? world_step_(c, tip_, result_)
                        : steering_3d::executeStep3(needle_, world_, c, tip_, result_, options);
  inserted_m_ += c.length_m;
  if (observe_) {
    observe(c);
  }
  plan_ = std::move(rest);
  if (!free || plan_.empty() || result_.steps >= max_steps_) {
    end();
  }
  return !done_;
}

needle_model::Matrix3 SteeringTrial3::observedCovariance_m2(double sigma_m) const {
  return observe_ && observation_.tip
             ? observation_.covariance_m2
             : needle_model::Matrix3(sigma_m * sigma_m * needle_model::Matrix3::Identity());
}

bool SteeringTrial3::followAnswer(const std::string& status, const std::string& message,
                                  double plan_seconds, const std::vector<Control3>& controls) {
  if (status == "bad_input") {
    abort("the planner refused the tip: " + message);
    return false;
  }
  recordReplan(plan_seconds);
  if (status == "ok") {
    setPlan(controls);
  }
  return true;
}

void SteeringTrial3::setViews(const imaging::BiplaneViews3* views) {
  if (views == nullptr) {
    observe_ = nullptr;
    return;
  }
  observe_ = [views](const std::vector<needle_model::Vector3>& path, const TipPose3& predicted,
                     std::uint64_t index) { return views->observe(path, predicted, index); };
}

void SteeringTrial3::observe(const Control3& c) {
  const TipPose3 predicted = steering_3d::predictTip3(estimate_, c, scene_.needle);
  observation_ = observe_(result_.path, predicted, seed_ * 1000 + result_.steps);
  estimate_ = steering_3d::acceptBiplane(observation_.tip, predicted, tip_, result_);
}

std::optional<TipSource3> tipSource3FromString(const std::string& name) {
  if (name == "truth") {
    return TipSource3::kTruth;
  }
  if (name == "biplane") {
    return TipSource3::kBiplane;
  }
  return std::nullopt;
}

TipSource3 tipSource3OrThrow(const std::string& name, const std::string& where) {
  const std::optional<TipSource3> source = tipSource3FromString(name);
  if (!source) {
    throw std::runtime_error("parameter '" + where + "' = '" + name + "' is not truth or biplane");
  }
  return *source;
}

std::optional<bool> recordRobotStep3(bool succeeded, const std::string& contact,
                                     const std::string& obstacle, const std::string& message,
                                     const std::vector<needle_model::Vector3>& path,
                                     TrialResult3& result) {
  using needle_model::Contact3;
  const bool touched = contact == "obstacle" || contact == "outside_tissue";
  if (!succeeded && !touched) {
    return std::nullopt;
  }
  ++result.steps;
  result.path.insert(result.path.end(), path.begin() + std::min<std::size_t>(1, path.size()),
                     path.end());
  if (touched) {
    result.contact = contact == "obstacle" ? Contact3::kObstacle : Contact3::kOutsideTissue;
    result.obstacle = obstacle;
    result.message = message;
  }
  return !touched;
}

bool SteeringRun3::completed(int trials) const {
  return static_cast<int>(results.size()) == trials &&
         std::find(faulted.begin(), faulted.end(), true) == faulted.end();
}

void SteeringTrial3::abort(const std::string& message) {
  if (done_) {
    return;
  }
  result_.message = message;
  end();
  result_.success = false;  // a fault is not an outcome
}

void SteeringTrial3::end() {
  steering_3d::finishTrial3(scene_, tip_, result_);
  done_ = true;
}

SteeringRun3 runSteeringTrials3(const needle_model::Scene3d& scene,
                                const needle_model::CollisionWorld3& world,
                                SteeringDevices3& devices, int trials, std::uint64_t seed,
                                int max_steps, double travel_m) {
  SteeringRun3 run;
  for (int k = 0; k < trials; ++k) {
    devices.progress("trial " + std::to_string(k + 1) + "/" + std::to_string(trials));
    const std::uint64_t trial_seed = seed * 100000ULL + static_cast<std::uint64_t>(k);
    SteeringTrial3 trial(scene, world, scene.noise, trial_seed, max_steps);
    trial.setTravel(travel_m);
    bool ok = false;
    try {
      ok = devices.runTrial(trial, trial_seed);
    } catch (const std::exception& e) {  // a malformed plan, a robot fault
      trial.abort(devices.fault().value_or(e.what()));
    }
    run.results.push_back(trial.result());
    run.faulted.push_back(!ok);
    devices.progress("trial " + std::to_string(k) + ": " + describe(trial.result()));
    if (!ok || devices.fault()) {
      break;
    }
  }
  run.safe_stop = devices.leaveSafe();
  return run;
}

steering_3d::PlanCode planCodeFromName(const std::string& name) {
  using steering_3d::PlanCode;
  for (PlanCode c :
       {PlanCode::kStartOutsideTissue, PlanCode::kStartInObstacle, PlanCode::kTargetOutsideTissue,
        PlanCode::kTargetInObstacle, PlanCode::kNoPathWithinBudget}) {
    if (steering_3d::toString(c) == name) {
      return c;
    }
  }
  return PlanCode::kNoPathWithinBudget;
}

std::string describe(const TrialResult3& r) {
  std::ostringstream out;
  out << (r.success ? "success" : "failure") << ", " << r.target_error_m * 1e3 << " mm, " << r.steps
      << " steps" << (r.message.empty() ? "" : ", " + r.message);
  return out.str();
}

std::string describe(const SteeringSummary3& s) {
  std::ostringstream out;
  out << s.successes << "/" << s.trials << " successes (" << s.success_ci_low << ".."
      << s.success_ci_high << "), median error " << s.target_error_mm_median
      << " mm, median replan " << s.replan_ms_median << " ms";
  if (s.views_fused + s.views_dropped + s.views_gated > 0) {
    out << ", biplane views fused " << s.views_fused << ", dropped " << s.views_dropped
        << ", gated " << s.views_gated << ", estimate error max " << s.estimate_error_mm_max
        << " mm";
  }
  return out.str();
}

bool runSucceeded(const SteeringSummary3& s) {
  return s.faults == 0 && s.trials > 0 && s.success_ci_high >= s.predicted_p_success_mean;
}

SteeringSummary3 summarize(const std::vector<TrialResult3>& results,
                           const std::vector<bool>& faulted) {
  SteeringSummary3 s;
  s.trials = static_cast<int>(results.size());
  std::vector<double> errors_mm, replan_ms, initial_s, predicted;
  for (std::size_t k = 0; k < results.size(); ++k) {
    const TrialResult3& r = results[k];
    s.successes += r.success ? 1 : 0;
    s.faults += k < faulted.size() && faulted[k] ? 1 : 0;
    if (std::isfinite(r.target_error_m)) {
      errors_mm.push_back(r.target_error_m * 1e3);
      initial_s.push_back(r.initial_plan_s);
      predicted.push_back(r.predicted_p_success);
    }
    for (double t : r.replan_s) {
      replan_ms.push_back(t * 1e3);
    }
    s.views_fused += r.views_fused;
    s.views_dropped += r.views_dropped;
    s.views_gated += r.views_gated;
    s.estimate_error_mm_max = std::max(s.estimate_error_mm_max, r.estimate_error_m_max * 1e3);
  }
  s.success_rate = s.trials > 0 ? static_cast<double>(s.successes) / s.trials : 0.0;
  const steering::Interval ci = steering::wilsonInterval(s.successes, s.trials);
  s.success_ci_low = ci.low;
  s.success_ci_high = ci.high;
  s.target_error_mm_median = report::median(errors_mm);
  s.target_error_mm_max = report::quantile(errors_mm, 1.0);
  s.replan_ms_median = report::median(replan_ms);
  s.replan_ms_p95 = report::quantile(replan_ms, 0.95);
  s.replan_ms_max = report::quantile(replan_ms, 1.0);
  s.initial_plan_s_median = report::median(initial_s);
  s.predicted_p_success_mean = report::mean(predicted);
  return s;
}

namespace {

std::string summaryJson(const needle_model::Scene3d& scene, const SteeringSummary3& s,
                        const std::vector<double>& round_trip_ms, std::uint64_t seed,
                        const NodeDeath3& death, const std::string& safe_stop) {
  const auto num = [](double v) { return report::jsonNumber(v); };
  std::string quoted = safe_stop;  // a robot's message inside a JSON string
  std::replace(quoted.begin(), quoted.end(), '"', '\'');
  std::ostringstream json;
  json << "{\n  \"procedure\": \"steerable_procedure_3d\",\n  \"scene\": \"" << scene.name
       << "\",\n  \"seed\": " << seed << ",\n  \"trials\": " << s.trials
       << ",\n  \"successes\": " << s.successes << ",\n  \"success_rate\": " << num(s.success_rate)
       << ",\n  \"success_ci_low\": " << num(s.success_ci_low)
       << ",\n  \"success_ci_high\": " << num(s.success_ci_high)
       << ",\n  \"target_radius_mm\": " << num(scene.target.radius_m * 1e3)
       << ",\n  \"target_error_mm_median\": " << num(s.target_error_mm_median)
       << ",\n  \"target_error_mm_max\": " << num(s.target_error_mm_max)
       << ",\n  \"replan_ms_median\": " << num(s.replan_ms_median)
       << ",\n  \"replan_ms_p95\": " << num(s.replan_ms_p95)
       << ",\n  \"replan_ms_max\": " << num(s.replan_ms_max)
       << ",\n  \"round_trip_ms_median\": " << num(report::median(round_trip_ms))
       << ",\n  \"initial_plan_s_median\": " << num(s.initial_plan_s_median)
       << ",\n  \"predicted_p_success_mean\": " << num(s.predicted_p_success_mean)
       << ",\n  \"faults\": " << s.faults << ",\n  \"safe_stop\": \"" << quoted << "\"";
  if (s.views_fused + s.views_dropped + s.views_gated > 0) {
    json << ",\n  \"tip_source\": \"biplane\",\n  \"views_fused\": " << s.views_fused
         << ",\n  \"views_dropped\": " << s.views_dropped
         << ",\n  \"views_gated\": " << s.views_gated
         << ",\n  \"estimate_error_mm_max\": " << num(s.estimate_error_mm_max);
  }
  if (!death.dead_node.empty()) {
    json << ",\n  \"dead_node\": \"" << death.dead_node << "\",\n  \"cause\": \"" << death.cause
         << "\",\n  \"detected_unix_s\": " << report::jsonNumber(death.detected_unix_s, 15);
  }
  const bool ok = runSucceeded(s) && death.dead_node.empty();
  json << ",\n  \"success\": " << (ok ? "true" : "false") << ",\n  \"status\": \""
       << (!death.dead_node.empty() ? "node_died"
           : s.faults == 0          ? "completed"
                                    : "fault")
       << "\"\n}\n";
  return json.str();
}

void writePlots(const std::string& dir, const needle_model::Scene3d& scene,
                const std::vector<TrialResult3>& results) {
  report::LinePlot errors("Final tip error per trial (" + scene.name + ")", "trial",
                          "tip to target centre [mm]");
  std::vector<double> xs, ys, xf, yf, replan_x, replan_y;
  for (std::size_t k = 0; k < results.size(); ++k) {
    const double e = results[k].target_error_m * 1e3;
    (results[k].success ? xs : xf).push_back(static_cast<double>(k));
    (results[k].success ? ys : yf).push_back(e);
    for (double t : results[k].replan_s) {
      replan_x.push_back(static_cast<double>(replan_x.size()));
      replan_y.push_back(t * 1e3);
    }
  }
  errors.addPoints("success", xs, ys, cv::Scalar(60, 160, 60), 6);
  errors.addPoints("failure", xf, yf, cv::Scalar(40, 40, 220), 6);
  errors.addHorizontal("target radius", scene.target.radius_m * 1e3, cv::Scalar(120, 120, 120));
  errors.save(dir + "/target_error.png");
  report::LinePlot replans("Replan time of steering_planner_3d (" + scene.name + ")",
                           "replan (all trials, in order)", "planner time [ms]");
  replans.addPoints("replan", replan_x, replan_y, report::seriesColour(0), 2);
  replans.save(dir + "/replan_ms.png");
}

}  // namespace

void writeSteeringReport3(const std::string& report_dir, const needle_model::Scene3d& scene,
                          const SteeringRun3& run, const std::vector<double>& round_trip_ms,
                          std::uint64_t seed, const NodeDeath3& death) {
  const std::vector<TrialResult3>& results = run.results;
  const std::vector<bool>& faulted = run.faulted;
  const SteeringSummary3 s = summarize(results, faulted);
  report::writeTextFile(report_dir + "/summary.json",
                        summaryJson(scene, s, round_trip_ms, seed, death, run.safe_stop));
  report::Table trials({"trial", "success", "contact", "obstacle", "target_error_mm", "steps",
                        "initial_plan_s", "replans", "replan_ms_median", "predicted_p_success",
                        "fault", "message"});
  report::Table paths({"trial", "x_mm", "y_mm", "z_mm"});
  for (std::size_t k = 0; k < results.size(); ++k) {
    const TrialResult3& r = results[k];
    std::vector<double> replan_ms;
    for (double t : r.replan_s) {
      replan_ms.push_back(t * 1e3);
    }
    trials.addRow({static_cast<double>(k), r.success ? 1.0 : 0.0, needle_model::toString(r.contact),
                   r.obstacle, r.target_error_m * 1e3, static_cast<double>(r.steps),
                   r.initial_plan_s, static_cast<double>(r.replan_s.size()),
                   report::median(replan_ms), r.predicted_p_success,
                   k < faulted.size() && faulted[k] ? 1.0 : 0.0, r.message});
    for (const needle_model::Vector3& p : r.path) {
      paths.addRow({static_cast<double>(k), p.x() * 1e3, p.y() * 1e3, p.z() * 1e3});
    }
  }
  trials.writeCsv(report_dir + "/trials.csv");
  paths.writeCsv(report_dir + "/paths.csv");
  writePlots(report_dir, scene, results);
}

}  // namespace needle_guidance::procedures
