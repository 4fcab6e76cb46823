#include "needle_guidance/ros/steering_policy_ros.h"

#include <visualization_msgs/Marker.h>
#include <visualization_msgs/MarkerArray.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "needle_guidance/SteeringControl.h"
#include "needle_guidance/format.h"
#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/params.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/model_selection.h"
#include "needle_guidance/steering/value_iteration.h"

namespace needle_guidance {
namespace {

namespace st = steering;

constexpr char kName[] = "steering_policy";
constexpr char kSceneFrame[] = "scene";
constexpr double kMaxEpsilon = 0.1;   ///< loosest accepted value-iteration threshold
constexpr double kThrottle_s = 5.0;   ///< period of per-message warnings and errors [s]
constexpr double kMapDepth_m = 0.02;  ///< ~ps_map sits this far below z = 0: rviz's top-down ortho
                                      ///< depth buffer loses mm separations
constexpr double kMapThickness_m = 5e-4;  ///< cube height of ~ps_map [m]
constexpr double kKeyOffset_m = 4e-3;     ///< ~ps_map_key's distance right of the workspace [m]
constexpr double kKeyLine_m = 5e-3;       ///< ~ps_map_key's line spacing [m]
constexpr double kKeyText_m = 2.5e-3;     ///< ~ps_map_key's text height [m]
constexpr double kArrowLength_m = 0.01;   ///< ~best_start_marker [m]
constexpr double kArrowShaft_m = 1e-3;
constexpr double kArrowHead_m = 2e-3;

double secondsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// ---- conversions (message <-> core), kept together -----------------------

/// The wire name of a look-up status (SteeringControl.status).
std::string toWire(st::ControlLookup::Status status) {
  switch (status) {
    case st::ControlLookup::Status::kOk:
      return "ok";
    case st::ControlLookup::Status::kOutsideGrid:
      return "outside_grid";
    case st::ControlLookup::Status::kInTarget:
      return "in_target";
    case st::ControlLookup::Status::kInObstacle:
      return "in_obstacle";
  }
  return "outside_grid";
}

geometry_msgs::Pose2D toMessage(const st::TipPose& pose) {
  geometry_msgs::Pose2D msg;
  msg.x = pose.p_SceneTip.x();
  msg.y = pose.p_SceneTip.y();
  msg.theta = pose.theta_rad;
  return msg;
}

/// The answer to `tip` (whose bevel is `bevel`) by the table of `model`: header copied (an empty
/// frame becomes scene); the step length and the noise that model assumes.
SteeringControl toMessage(const NeedleTip& tip, const st::ControlLookup& lookup,
                          const st::SteeringModel& model) {
  SteeringControl msg;
  msg.header = tip.header;
  if (msg.header.frame_id.empty()) {
    msg.header.frame_id = kSceneFrame;
  }
  msg.status = toWire(lookup.status);
  msg.control = st::toString(lookup.control);
  msg.probability_of_success = lookup.probability_of_success;
  msg.step_length_m = model.arcLength_m();
  msg.sigma_insert_rad = model.params().sigma_insert_rad;
  msg.sigma_flip_rad = model.params().sigma_flip_rad;
  msg.tip = tip.pose;
  msg.bevel = tip.bevel;
  msg.tip_source = tip.source;
  msg.tip_confident = tip.confident;
  return msg;
}

using ros_conversions::colour;

/// P_s in [0, 1] -> dark blue (0) ... yellow (1), linear in RGB.
std_msgs::ColorRGBA probabilityColour(double p) {
  const double t = std::clamp(p, 0.0, 1.0);
  return colour(t, t, 0.5 * (1.0 - t));
}

/// A marker of frame scene, id 0 (stamp 0: static, rviz uses the latest transform).
visualization_msgs::Marker marker(const std::string& ns, int type) {
  return ros_conversions::baseMarker(kSceneFrame, ns, 0, type);
}

/// One cube per grid position coloured by the largest P_s over its orientations and bevels
/// (what the best orientation achieves there); obstacle cells grey.
visualization_msgs::Marker probabilityMap(const st::PolicyTable& table) {
  using visualization_msgs::Marker;
  const st::GridSpec& grid = table.grid();
  Marker m = marker("ps_map", Marker::CUBE_LIST);
  m.color = colour(1.0, 1.0, 1.0);  // per-cube colours below; opaque
  m.pose.position.z = -kMapDepth_m;
  m.scale.x = grid.spacing_m;
  m.scale.y = grid.spacing_m;
  m.scale.z = kMapThickness_m;
  m.points.reserve(static_cast<std::size_t>(grid.numPositions()));
  m.colors.reserve(static_cast<std::size_t>(grid.numPositions()));
  const std::size_t per_position = 2 * static_cast<std::size_t>(grid.nc);
  const auto& values = table.values();
  for (int ix = 0; ix < grid.nx; ++ix) {
    for (int iy = 0; iy < grid.ny; ++iy) {
      const std::int64_t position = grid.position(ix, iy);
      const auto first = values.begin() + static_cast<std::ptrdiff_t>(
                                              static_cast<std::size_t>(position) * per_position);
      geometry_msgs::Point p;
      p.x = grid.point(ix, iy).x();
      p.y = grid.point(ix, iy).y();
      m.points.push_back(p);
      m.colors.push_back(table.cell(position) == st::Cell::kObstacle
                             ? colour(0.5, 0.5, 0.5)
                             : probabilityColour(*std::max_element(
                                   first, first + static_cast<std::ptrdiff_t>(per_position))));
    }
  }
  return m;
}

/// The colour key of ~ps_map, just right of the workspace: a title, then a swatch and a short
/// label per P_s step, and the obstacle grey.
visualization_msgs::MarkerArray probabilityKey(const st::SteeringProblem& problem) {
  using visualization_msgs::Marker;
  visualization_msgs::MarkerArray key;
  const double x = problem.workspace_max.x() + kKeyOffset_m;
  const double top = problem.workspace_max.y() - kKeyLine_m;
  const auto text = [&](int id, double y, const std::string& s) {
    Marker label = marker("ps_map_key", Marker::TEXT_VIEW_FACING);
    label.id = id;
    // Text is centred on its position: start it half its width right of the swatch.
    label.pose.position.x = x + 0.5 * kKeyLine_m + 0.3 * kKeyText_m * double(s.size());
    label.pose.position.y = y;
    label.scale.z = kKeyText_m;
    label.color = colour(0.1, 0.1, 0.1);
    label.text = s;
    key.markers.push_back(label);
  };
  text(0, problem.workspace_max.y(), "P_s");
  for (int k = 0; k <= 5; ++k) {
    const bool obstacle = k == 5;
    Marker swatch = marker("ps_map_key", Marker::CUBE);
    swatch.id = 2 * k + 1;
    swatch.pose.position.x = x;
    swatch.pose.position.y = top - kKeyLine_m * k;
    swatch.scale.x = swatch.scale.y = 0.6 * kKeyLine_m;
    swatch.scale.z = kMapThickness_m;
    swatch.color = obstacle ? colour(0.5, 0.5, 0.5) : probabilityColour(1.0 - 0.25 * k);
    key.markers.push_back(swatch);
    text(2 * k + 2, swatch.pose.position.y, obstacle ? "obst." : formatNumber(1.0 - 0.25 * k, 2));
  }
  return key;
}

/// An arrow at the start pose in use (green), or a DELETE when there is none.
visualization_msgs::Marker bestStartMarker(const st::VerifiedStart& best) {
  using visualization_msgs::Marker;
  Marker m = marker("best_start", Marker::ARROW);
  if (!best) {
    m.action = Marker::DELETE;
    return m;
  }
  const st::TipPose& pose = best.start.pose;
  m.pose.position.x = pose.p_SceneTip.x();
  m.pose.position.y = pose.p_SceneTip.y();
  m.pose.orientation.z = std::sin(0.5 * pose.theta_rad);
  m.pose.orientation.w = std::cos(0.5 * pose.theta_rad);
  m.scale.x = kArrowLength_m;
  m.scale.y = kArrowShaft_m;
  m.scale.z = kArrowHead_m;
  m.color = colour(0.1, 0.9, 0.1);
  return m;
}

}  // namespace

std::string modelDescription(const st::SteeringModel& model) {
  std::ostringstream s;
  s << st::toString(model.transitionModel()) << ", grid "
    << formatNumber(model.grid().spacing_m * 1e3, 6)
    << " mm, s = " << model.params().orientation_subdivision << ", " << model.numStates()
    << " states";
  return s.str();
}

SteeringPolicyRos::SteeringPolicyRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh) {
  ROS_INFO("steering_policy parameters:");
  settings_.scene = ros_params::text(private_nh, "scene", settings_.scene, true);
  settings_.target = ros_params::text(private_nh, "target", settings_.target);
  settings_.epsilon =
      ros_params::number(private_nh, "epsilon", settings_.epsilon, 0.0, kMaxEpsilon, "");
  if (!(settings_.epsilon > 0.0)) {
    throw std::runtime_error("parameter '" + private_nh.resolveName("epsilon") + "' must be > 0");
  }
  settings_.threads = static_cast<int>(
      ros_params::integer(private_nh, "threads", settings_.threads, 1, 2, "threads"));
  settings_.table_dir =
      ros_params::rosHomePath(ros_params::text(private_nh, "table_dir", "steering_tables"));
  settings_.solve_on_start =
      ros_params::flag(private_nh, "solve_on_start", settings_.solve_on_start);
  settings_.adapt_noise = ros_params::flag(private_nh, "adapt_noise", settings_.adapt_noise);

  const scene::Scene scene = scene::loadSceneSpec(settings_.scene);
  scene_name_ = scene.name;
  start_options_ = st::startOptionsFromScene(scene);
  problem_ = st::problemFromScene(scene, settings_.target);
  // The scene's model as given (with ps_tolerance: the coarsest one tried), until a solve picks.
  model_ = std::make_unique<const st::SteeringModel>(problem_, settings_.threads);
  for (const std::string& warning : model_->diagnostics()) {
    ROS_WARN_STREAM_NAMED(kName, "steering_policy: " << warning);
  }
  const st::GridSpec& grid = model_->grid();
  ROS_INFO_STREAM_NAMED(
      kName, "steering_policy: scene '"
                 << scene_name_ << "', target '" << model_->problem().target.name << "', model "
                 << modelDescription(*model_) << ", grid " << grid.nx << " x " << grid.ny << " x "
                 << grid.nc << " x 2 = " << model_->numStates() << " states, step "
                 << 1e3 * model_->arcLength_m() << " mm, ps_tolerance "
                 << (problem_.ps_tolerance > 0.0 ? formatNumber(problem_.ps_tolerance)
                                                 : std::string("0 (grid as given)"))
                 << ", tables in '" << settings_.table_dir << "'");

  control_pub_ = private_nh.advertise<SteeringControl>("control", 10);
  ps_map_pub_ = private_nh.advertise<visualization_msgs::Marker>("ps_map", 1, true);
  ps_key_pub_ = private_nh.advertise<visualization_msgs::MarkerArray>("ps_map_key", 1, true);
  best_start_pub_ = private_nh.advertise<visualization_msgs::Marker>("best_start_marker", 1, true);

  if (settings_.solve_on_start) {
    const SolveOutcome outcome = solveOrLoad(settings_.epsilon, false);
    if (!outcome.success) {
      ROS_ERROR_STREAM_NAMED(kName, "steering_policy: start-up solve failed ("
                                        << outcome.message << "); waiting for ~solve");
    }
  }

  tip_sub_ = nh.subscribe("tip", 10, &SteeringPolicyRos::onTip, this);
  solve_srv_ = private_nh.advertiseService("solve", &SteeringPolicyRos::onSolve, this);
  best_start_srv_ =
      private_nh.advertiseService("best_start", &SteeringPolicyRos::onBestStart, this);
  ROS_INFO_STREAM_NAMED(kName, "steering_policy: ready, tips from '" << tip_sub_.getTopic() << "'");
}

SteeringPolicyRos::SolveOutcome SteeringPolicyRos::solveOrLoad(double epsilon, bool force) {
  const auto t0 = std::chrono::steady_clock::now();
  SolveOutcome out;
  try {
    // A table in memory solved at least as tightly needs no work.
    if (!force && table_ && table_->epsilon() <= epsilon) {
      out.success = true;
      out.source = "cached";
      out.sweeps = table_->sweeps();
      out.seconds = secondsSince(t0);
      out.message = "table in memory (" + table_source_ + ", epsilon " +
                    formatNumber(table_->epsilon()) + ")";
      ROS_INFO_STREAM_NAMED(kName, "steering_policy: cached table, " << model_->numStates()
                                                                     << " states, " << out.sweeps
                                                                     << " sweeps");
      return out;
    }
    st::SelectionOptions options;
    options.solver.epsilon = epsilon;
    options.solver.threads = settings_.threads;
    options.threads = settings_.threads;
    options.start = start_options_;
    Result<st::PolicySource> policy =
        st::solveOrLoad(problem_, scene_name_, settings_.table_dir, options, force);
    if (!policy) {
      throw std::runtime_error(policy.status().toString());
    }
    st::PolicySource& p = policy.value();
    if (!p.note.empty() && p.note.rfind("not saved", 0) == 0) {
      ROS_WARN_STREAM_NAMED(kName, "steering_policy: table " << p.note);
    }
    for (const st::ModelRung& rung : p.ladder) {
      ROS_INFO_STREAM_NAMED(
          kName,
          "steering_policy: model "
              << st::toString(rung.transition_model) << ", grid " << rung.grid_spacing_m * 1e3
              << " mm, s = " << rung.orientation_subdivision << ", " << rung.states
              << " states, solved in " << rung.solve_s << " s, estimated mean P_s error "
              << (std::isnan(rung.estimated_error) ? std::string("not estimated (first model of "
                                                                 "these transitions)")
                                                   : formatNumber(rung.estimated_error, 2))
              << "; " << rung.check.toString()
              << (rung.coarsened ? " (coarser grid of the accepted transitions)" : "")
              << (rung.chosen ? " (chosen)" : ""));
    }
    description_ = p.description();  // before the model moves out
    estimated_error_ = p.estimated_error;
    out.source = p.source;
    const std::string note = p.note;
    const auto source = std::make_shared<const st::PolicySource>(std::move(p));
    adopt(source);
    if (settings_.adapt_noise) {
      st::AdaptationOptions adaptation;
      adaptation.solver = options.solver;
      adaptation.threads = settings_.threads;
      adaptation.table_dir = settings_.table_dir;  // the procedure's report loads re-solved tables
      adaptation.scene_name = scene_name_;
      adaptive_ = std::make_unique<st::AdaptivePolicy>(problem_, source, adaptation);
      steps_.emplace(model_->arcLength_m());
    }
    table_source_ = out.source;
    out.success = true;
    out.sweeps = table_->sweeps();
    out.seconds = secondsSince(t0);
    out.message = out.source + " (epsilon " + formatNumber(table_->epsilon()) + ")" +
                  (note.empty() ? "" : ", " + note);
    ROS_INFO_STREAM_NAMED(kName, "steering_policy: table " << out.source << ": " << description_
                                                           << ", " << out.sweeps << " sweeps");
  } catch (const std::exception& e) {
    out = SolveOutcome{};
    out.message = e.what();
    out.seconds = secondsSince(t0);
    ROS_ERROR_STREAM_NAMED(kName,
                           "steering_policy: solve failed, previous table kept: " << e.what());
    return out;
  }
  try {
    publishMaps(true);
  } catch (const std::exception& e) {
    ROS_ERROR_STREAM_NAMED(kName, "steering_policy: markers not published: " << e.what());
  }
  return out;
}

void SteeringPolicyRos::publishMaps(bool verify_start) {
  ps_map_pub_.publish(probabilityMap(*table_));
  ps_key_pub_.publish(probabilityKey(problem_));
  if (!verify_start) {  // a table swapped in mid-run: the run keeps its start (~best_start
    return;             // verifies the new table when asked)
  }
  const st::VerifiedStart& best = verifiedStart();
  best_start_pub_.publish(bestStartMarker(best));
  ROS_INFO_STREAM_NAMED(kName, "steering_policy: start " << best.toString() << " (verified in "
                                                         << best.seconds << " s)");
}

const st::VerifiedStart& SteeringPolicyRos::verifiedStart() {
  if (!verified_ || verified_for_ != table_.get()) {
    const st::ContinuousWorkspace world(model_->problem());
    st::StartVerificationOptions options;
    options.tolerance = st::verificationTolerance(problem_);
    options.threads = settings_.threads;
    verified_ = st::verifyBestStart(world, *table_, start_options_, options);
    verified_for_ = table_.get();
  }
  return *verified_;
}

void SteeringPolicyRos::adopt(const std::shared_ptr<const st::PolicySource>& source) {
  model_ = std::shared_ptr<const st::SteeringModel>(source, source->model.get());
  table_ = std::shared_ptr<const st::PolicyTable>(source, source->table.get());
}

void SteeringPolicyRos::learnFrom(const NeedleTip& tip, const st::TipPose& pose, bool vouched) {
  if (!adaptive_ || !steps_) {
    return;
  }
  if (const std::optional<st::ObservedStep> step =
          steps_->add(tip.inserted_length_m, pose, vouched)) {
    const bool was_solving = adaptive_->solving();
    adaptive_->observe(step->before, step->after, step->control);
    if (!was_solving && adaptive_->solving()) {
      const st::Resolve& r = adaptive_->resolves().back();
      ROS_INFO_STREAM_NAMED(kName, "steering_policy: learned noise left the assumed interval after "
                                       << r.requested_at_step << " steps; re-solving for sigma_i = "
                                       << r.sigma_insert_rad * 180.0 / M_PI
                                       << " deg, sigma_r = " << r.sigma_flip_rad * 180.0 / M_PI
                                       << " deg (the current table answers meanwhile)");
    }
  }
}

void SteeringPolicyRos::adoptFinishedResolve() {
  bool finished = false;
  try {
    finished = adaptive_ && adaptive_->poll();
  } catch (const std::exception& e) {  // the current table stays in use
    ROS_ERROR_STREAM_NAMED(kName, "steering_policy: " << e.what() << "; keeping " << description_);
    return;
  }
  if (finished) {
    adopt(adaptive_->current());
    const st::Resolve& r = adaptive_->resolves().back();
    description_ = adaptive_->current()->description();
    ROS_INFO_STREAM_NAMED(kName, "steering_policy: re-solved table swapped in ("
                                     << (r.cached ? "cached" : formatNumber(r.seconds, 3) + " s")
                                     << "): " << description_);
    publishMaps(false);
  }
}

void SteeringPolicyRos::onTip(const NeedleTipConstPtr& msg) {
  if (!table_) {
    ROS_WARN_STREAM_THROTTLE_NAMED(
        kThrottle_s, kName, "steering_policy: no policy table yet (call ~solve); tip ignored");
    return;
  }
  if (!msg->header.frame_id.empty() && msg->header.frame_id != kSceneFrame) {
    ROS_ERROR_STREAM_THROTTLE_NAMED(kThrottle_s, kName,
                                    "steering_policy: tip in frame '"
                                        << msg->header.frame_id << "', expected '" << kSceneFrame
                                        << "'; tip ignored");
    return;
  }
  const std::optional<st::Bevel> bevel = st::bevelFromString(msg->bevel);
  if (!bevel) {
    ROS_ERROR_STREAM_THROTTLE_NAMED(
        kThrottle_s, kName,
        "steering_policy: tip bevel '" << msg->bevel << "' is not left or right; tip ignored");
    return;
  }
  if (!std::isfinite(msg->pose.x) || !std::isfinite(msg->pose.y) ||
      !std::isfinite(msg->pose.theta)) {
    // Refused, but answered, so that a waiting procedure learns it at once: no control.
    ROS_ERROR_STREAM_THROTTLE_NAMED(kThrottle_s, kName,
                                    "steering_policy: tip pose is not finite; no control given");
    SteeringControl refusal = toMessage(*msg, st::ControlLookup{}, *model_);
    refusal.status = "invalid_tip";
    refusal.control = "";
    control_pub_.publish(refusal);
    return;
  }
  try {
    st::TipPose pose;
    pose.p_SceneTip = geometry::Point2(msg->pose.x, msg->pose.y);
    pose.theta_rad = msg->pose.theta;
    pose.bevel = *bevel;
    adoptFinishedResolve();
    const st::ControlLookup answer = table_->lookup(pose);
    // Only tips the robot or an image vouches for teach the noise.
    learnFrom(*msg, pose, msg->source == "ground_truth" || msg->confident);
    control_pub_.publish(toMessage(*msg, answer, *model_));
  } catch (const std::exception& e) {
    ROS_ERROR_STREAM_THROTTLE_NAMED(kThrottle_s, kName,
                                    "steering_policy: tip not answered: " << e.what());
  }
}

bool SteeringPolicyRos::onSolve(SolvePolicy::Request& req, SolvePolicy::Response& res) {
  const double epsilon = req.epsilon == 0.0 ? settings_.epsilon : req.epsilon;
  if (!(epsilon > 0.0 && epsilon <= kMaxEpsilon)) {
    std::ostringstream why;
    why << "epsilon " << req.epsilon << " is outside (0, " << kMaxEpsilon << "] (0 = ~epsilon)";
    res.success = false;
    res.message = why.str();
    ROS_WARN_STREAM_NAMED(kName, "steering_policy: solve refused: " << res.message);
  } else {
    const SolveOutcome outcome = solveOrLoad(epsilon, req.force);
    res.success = outcome.success;
    res.message = outcome.message;
    res.source = outcome.source;
    res.seconds = outcome.seconds;
  }
  res.states = table_ ? table_->grid().numStates() : 0;
  res.sweeps = table_ ? table_->sweeps() : 0;
  res.model = description_.empty() ? modelDescription(*model_) : description_;
  res.grid_spacing_m = model_->grid().spacing_m;
  res.estimated_ps_error = estimated_error_;
  return true;
}

bool SteeringPolicyRos::onBestStart(BestStart::Request& /*req*/, BestStart::Response& res) {
  if (!table_) {
    res.found = false;
    res.message = "no policy table yet: call ~solve";
    return true;
  }
  const st::VerifiedStart& best = verifiedStart();
  res.found = best.found;
  res.message = best.toString();
  res.pose = toMessage(best.start.pose);
  res.bevel = st::toString(best.start.pose.bevel);
  res.probability_of_success = best.start.probability_of_success;
  res.verified_ps = static_cast<float>(best.verification.rate());
  res.verified_ci_low = static_cast<float>(best.verification.interval().low);
  res.verified_ci_high = static_cast<float>(best.verification.interval().high);
  res.verification_trials = static_cast<std::int32_t>(best.verification.trials);
  res.confirmed = best.confirmed;
  res.ps_tolerance = static_cast<float>(best.tolerance);
  res.table_best_ps = table_->bestStart(start_options_).best.probability_of_success;
  res.reported_ps = static_cast<float>(best.reported());
  return true;
}

}  // namespace needle_guidance
