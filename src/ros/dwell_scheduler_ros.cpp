#include "needle_guidance/ros/dwell_scheduler_ros.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <ctime>
#include <filesystem>
#include <iterator>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "needle_guidance/dose/case_folder.h"
#include "needle_guidance/dose/dicom_case.h"
#include "needle_guidance/dose/dose_indices.h"
#include "needle_guidance/dose/dwell_optimization.h"
#include "needle_guidance/dose/isodose.h"
#include "needle_guidance/dose/prostate_case.h"
#include "needle_guidance/format.h"
#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/delivery_conversions.h"
#include "needle_guidance/ros/params.h"

namespace needle_guidance {
namespace {

constexpr double kSecondsPerDay = 86400.0;
constexpr double kIsodoseSpacing_m = 1e-3;  ///< dose grid of the isodose slice
constexpr double kIsodoseMargin_m = 10e-3;  ///< slice box = mid-gland target contours + this
constexpr double kIsodoseLevels[] = {0.5, 1.0, 1.5, 2.0};  ///< fractions of the prescription
constexpr double kContourWidth_m = 0.5e-3;
constexpr double kCatheterWidth_m = 0.8e-3;
constexpr double kDwellDiameter_m = 1.5e-3;

/// "2024-01-05T10:00" -> seconds; a bad date throws naming the parameter.
double dateParameter(const ros::NodeHandle& nh, const std::string& name, const std::string& text) {
  try {
    return delivery::parseUtcSeconds(text);
  } catch (const std::exception& e) {
    throw std::runtime_error("parameter '" + nh.resolveName(name) + "': " + e.what());
  }
}

std::string utcStamp(double seconds) {
  const std::time_t t = static_cast<std::time_t>(seconds);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char text[32];
  std::strftime(text, sizeof text, "%Y%m%dT%H%M%S", &tm);
  return text;
}

std::string sanitised(const std::string& text) {
  std::string out = text;
  for (char& ch : out) {
    if (std::string(delivery::kPlanIdCharacters).find(ch) == std::string::npos)
      ch = '_';
  }
  while (!out.empty() && out.front() == '.')
    out.erase(out.begin());
  return out.empty() ? "case" : out;
}


/// Throws std::runtime_error naming `what` if `value` is NaN or infinite (nothing non-finite is
/// ever published).
void requireFinite(double value, const std::string& what) {
  if (!std::isfinite(value))
    throw std::runtime_error(what + " is not finite (" + formatNumber(value) + ")");
}

using ros_conversions::colour;

std_msgs::ColorRGBA structureColour(const std::string& name) {
  std::string n = name;
  std::transform(n.begin(), n.end(), n.begin(),
                 [](unsigned char ch) { return static_cast<char>(std::tolower(ch)); });
  constexpr double kAlpha = 0.8;
  if (n == "prostate")
    return colour(1.0, 0.0, 0.0, kAlpha);
  if (n == "urethra")
    return colour(1.0, 1.0, 0.0, kAlpha);
  if (n == "rectum")
    return colour(0.55, 0.27, 0.07, kAlpha);
  if (n == "bladder")
    return colour(0.3, 0.5, 1.0, kAlpha);
  return colour(0.8, 0.8, 0.8, kAlpha);
}

geometry_msgs::Point point(double x, double y, double z) {
  geometry_msgs::Point p;
  p.x = x;
  p.y = y;
  p.z = z;
  return p;
}

visualization_msgs::Marker marker(const std::string& frame_id, const std::string& ns, int id,
                                  int type) {
  visualization_msgs::Marker m;
  m.header.frame_id = frame_id;  // stamp 0: static geometry, rviz uses the latest transform
  m.ns = ns;
  m.id = id;
  m.type = type;
  m.action = visualization_msgs::Marker::ADD;
  m.pose.orientation.w = 1.0;
  return m;
}

/// The target structure (role kTarget, else named "prostate"); nullptr if none.
const dose::Structure* targetStructure(const dose::HdrCase& c) {
  for (const auto& s : c.structures) {
    if (s.role == dose::StructureRole::kTarget && !s.contours.empty())
      return &s;
  }
  const int k = c.structureIndex("prostate");
  return k >= 0 && !c.structures[static_cast<std::size_t>(k)].contours.empty()
             ? &c.structures[static_cast<std::size_t>(k)]
             : nullptr;
}

/// Structure contours, catheters, scheduled dwells coloured by time and the isodose lines of the
/// mid-gland slice (dissertation figure 6.6).
visualization_msgs::MarkerArray planMarkers(const dose::HdrCase& c, const dose::Tg43Source& source,
                                            const std::vector<double>& times_s,
                                            const delivery::Schedule& schedule,
                                            const std::string& frame_id) {
  using visualization_msgs::Marker;
  visualization_msgs::MarkerArray array;
  Marker clear;
  clear.header.frame_id = frame_id;
  clear.action = Marker::DELETEALL;  // the previous plan's markers go first
  array.markers.push_back(clear);

  for (std::size_t k = 0; k < c.structures.size(); ++k) {
    const dose::Structure& s = c.structures[k];
    Marker m = marker(frame_id, "contours", static_cast<int>(k), Marker::LINE_LIST);
    m.scale.x = kContourWidth_m;
    m.color = structureColour(s.name);
    for (const auto& contour : s.contours) {
      for (std::size_t v = 0; v < contour.xy_m.size(); ++v) {
        const auto& a = contour.xy_m[v];
        const auto& b = contour.xy_m[(v + 1) % contour.xy_m.size()];
        m.points.push_back(point(a.x(), a.y(), contour.z_m));
        m.points.push_back(point(b.x(), b.y(), contour.z_m));
      }
    }
    if (!m.points.empty())
      array.markers.push_back(m);
  }

  for (std::size_t k = 0; k < c.catheters.size(); ++k) {
    Marker m = marker(frame_id, "catheters", static_cast<int>(k), Marker::LINE_STRIP);
    m.scale.x = kCatheterWidth_m;
    m.color = colour(0.6, 0.6, 0.6);
    for (const auto& p : c.catheters[k].points_m)
      m.points.push_back(ros_conversions::toPointMessage(p));
    if (m.points.size() >= 2)
      array.markers.push_back(m);
  }

  Marker dwells = marker(frame_id, "dwells", 0, Marker::SPHERE_LIST);
  dwells.scale.x = dwells.scale.y = dwells.scale.z = kDwellDiameter_m;
  dwells.color = colour(1.0, 1.0, 1.0);
  double longest_s = 0.0;
  for (const auto& ch : schedule.channels) {
    for (double t : ch.time_s)
      longest_s = std::max(longest_s, t);
  }
  for (const auto& ch : schedule.channels) {
    for (std::size_t k = 0; k < ch.time_s.size() && k < ch.position_m.size(); ++k) {
      const double f = longest_s > 0.0 ? ch.time_s[k] / longest_s : 0.0;  // blue short, red long
      dwells.points.push_back(ros_conversions::toPointMessage(ch.position_m[k]));
      dwells.colors.push_back(colour(f, 0.0, 1.0 - f));
    }
  }
  if (!dwells.points.empty())
    array.markers.push_back(dwells);

  const dose::Structure* target = targetStructure(c);
  if (target) {
    const double z = dose::midSliceZ(*target);
    double x_lo = std::numeric_limits<double>::infinity(), y_lo = x_lo;
    double x_hi = -x_lo, y_hi = -x_lo;
    for (const auto& contour : target->contours) {
      if (contour.z_m != z)
        continue;
      for (const auto& p : contour.xy_m) {
        x_lo = std::min(x_lo, p.x());
        y_lo = std::min(y_lo, p.y());
        x_hi = std::max(x_hi, p.x());
        y_hi = std::max(y_hi, p.y());
      }
    }
    const dose::DoseSlice slice =
        dose::doseSlice(c, source, times_s, z, x_lo - kIsodoseMargin_m, y_lo - kIsodoseMargin_m,
                        x_hi + kIsodoseMargin_m, y_hi + kIsodoseMargin_m, kIsodoseSpacing_m);
    const std_msgs::ColorRGBA level_colours[] = {colour(0.0, 0.8, 0.0), colour(0.0, 1.0, 1.0),
                                                 colour(1.0, 1.0, 0.0), colour(1.0, 0.0, 1.0)};
    for (std::size_t level = 0; level < std::size(kIsodoseLevels); ++level) {
      Marker m = marker(frame_id, "isodose", static_cast<int>(level), Marker::LINE_LIST);
      m.scale.x = kContourWidth_m;
      m.color = level_colours[level];
      for (const auto& line :
           dose::isodoseLines(slice.dose_Gy, slice.x0_m, slice.y0_m, slice.spacing_m,
                              kIsodoseLevels[level] * c.prescription_Gy)) {
        for (std::size_t v = 0; v < line.size(); ++v) {
          const auto& a = line[v];
          const auto& b = line[(v + 1) % line.size()];
          m.points.push_back(point(a.x(), a.y(), z));
          m.points.push_back(point(b.x(), b.y(), z));
        }
      }
      if (!m.points.empty())
        array.markers.push_back(m);
    }
  }
  return array;
}

/// index_names in map order (sorted by name) with their values.
void splitIndices(const std::map<std::string, double>& indices, std::vector<std::string>& names,
                  std::vector<double>& values) {
  names.clear();
  values.clear();
  for (const auto& [name, value] : indices) {
    requireFinite(value, "index " + name);
    names.push_back(name);
    values.push_back(value);
  }
}

}  // namespace

DwellSchedulerRos::DwellSchedulerRos(ros::NodeHandle& /*nh*/, ros::NodeHandle& private_nh) {
  ROS_INFO("dwell_scheduler parameters:");
  settings_.frame_id = ros_params::text(private_nh, "frame_id", settings_.frame_id, true);
  settings_.method = ros_params::text(private_nh, "method", settings_.method);
  if (settings_.method != "lp" && settings_.method != "sa") {
    throw std::runtime_error("parameter '" + private_nh.resolveName("method") + "' = '" +
                             settings_.method + "' is not lp or sa");
  }
  const double calibration_U =
      ros_params::number(private_nh, "calibration_air_kerma_strength_U", 0.0, 0.0, 1e6, "U");
  const std::string calibration_date = ros_params::text(private_nh, "calibration_date", "");
  const std::string treatment_date = ros_params::text(private_nh, "treatment_date", "");
  const double treatment_s = treatment_date.empty()
                                 ? ros::WallTime::now().toSec()
                                 : dateParameter(private_nh, "treatment_date", treatment_date);
  if ((calibration_U > 0.0) != !calibration_date.empty()) {
    throw std::runtime_error("parameters '" +
                             private_nh.resolveName("calibration_air_kerma_strength_U") +
                             "' and '" + private_nh.resolveName("calibration_date") +
                             "' go together: give both (decay-corrected times) or neither");
  }
  settings_.schedule.calibration_air_kerma_strength_U = calibration_U;
  if (calibration_U > 0.0) {
    const double calibration_s = dateParameter(private_nh, "calibration_date", calibration_date);
    const double days = (treatment_s - calibration_s) / kSecondsPerDay;
    if (!(days >= 0.0)) {
      throw std::runtime_error(
          "parameter '" + private_nh.resolveName("treatment_date") + "' (" +
          (treatment_date.empty() ? "now, " + utcStamp(treatment_s) : treatment_date) +
          ") is before '" + private_nh.resolveName("calibration_date") + "' (" + calibration_date +
          ")");
    }
    settings_.schedule.days_since_calibration = days;
    ROS_INFO_STREAM("  source: " << calibration_U << " U at calibration, " << days << " days ago: "
                                 << calibration_U * delivery::ir192DecayFactor(days)
                                 << " U at treatment");
  } else {
    ROS_INFO("  no calibration given: each case's S_K is the source's current strength (no decay)");
  }
  settings_.schedule.transfer_length_m = ros_params::number(
      private_nh, "transfer_length_m", settings_.schedule.transfer_length_m, 0.0, 2.0, "m");
  settings_.source_speed_m_s = ros_params::number(private_nh, "source_speed_m_s",
                                                  settings_.source_speed_m_s, 1e-3, 10.0, "m/s");
  settings_.dvh_bins =
      static_cast<int>(ros_params::integer(private_nh, "dvh_bins", settings_.dvh_bins, 1, 100000, "bins"));
  settings_.dose_grid_m =
      ros_params::number(private_nh, "dose_grid_m", settings_.dose_grid_m, 5e-4, 1e-2, "m");
  settings_.sa_iterations =
      ros_params::integer(private_nh, "sa_iterations", settings_.sa_iterations, 1, 100000000, "moves");
  settings_.sa_seed =
      static_cast<unsigned>(ros_params::integer(private_nh, "sa_seed", settings_.sa_seed, 0, 4294967295L, "-"));
  settings_.default_synthetic_seed = static_cast<int>(ros_params::integer(
      private_nh, "default_synthetic_seed", settings_.default_synthetic_seed, 1, 1000000, "-"));
  const bool plan_on_start = ros_params::flag(private_nh, "plan_on_start", false);

  plan_pub_ = private_nh.advertise<DwellPlan>("plan", 1, true);
  dvh_pub_ = private_nh.advertise<DoseVolumeHistogram>("dvh", 1, true);
  markers_pub_ = private_nh.advertise<visualization_msgs::MarkerArray>("markers", 1, true);
  if (plan_on_start) {
    try {
      commit(makePlan("", settings_.default_synthetic_seed, "", ""));
    } catch (const std::exception& e) {
      throw std::runtime_error("plan_on_start: " + std::string(e.what()));
    }
  }
  plan_srv_ = private_nh.advertiseService("plan", &DwellSchedulerRos::onPlan, this);
  evaluate_srv_ = private_nh.advertiseService("evaluate", &DwellSchedulerRos::onEvaluate, this);
  ROS_INFO("dwell_scheduler: ready");
}

std::shared_ptr<const dose::Tg43Source> DwellSchedulerRos::source(const std::string& name) {
  auto it = sources_.find(name);
  if (it == sources_.end()) {
    it = sources_.emplace(name, std::make_shared<const dose::Tg43Source>(dose::loadSource(name)))
             .first;
  }
  return it->second;
}

std::string DwellSchedulerRos::newPlanId(const std::string& case_name,
                                         const std::string& method) const {
  // Case, method, UTC time and a counter: unique within this node and across restarts. The
  // counter moves on in commit(), so a refused plan leaves it as it was.
  const std::string stem = sanitised(case_name).substr(0, 60) + "_" + method + "_" +
                           utcStamp(ros::WallTime::now().toSec()) + "_";
  long n = plans_made_;
  std::string id;
  do {
    id = stem + std::to_string(++n);
  } while (plans_.count(id) > 0);
  return id;
}

DwellSchedulerRos::PlanOutcome DwellSchedulerRos::makePlan(const std::string& case_dir,
                                                           int synthetic_seed,
                                                           const std::string& requested_method,
                                                           const std::string& requested_id,
                                                           const std::string& dicom_dir) {
  const ros::WallTime start = ros::WallTime::now();
  const std::string method = requested_method.empty() ? settings_.method : requested_method;
  if (method != "lp" && method != "sa") {
    throw std::invalid_argument("method '" + requested_method + "' is not lp or sa");
  }
  if (!requested_id.empty() && !delivery::isValidPlanId(requested_id)) {
    throw std::invalid_argument(
        "plan_id '" + requested_id +
        "' must be 1-100 characters of [A-Za-z0-9_.-], not starting with '.'");
  }
  if (plans_.count(requested_id) > 0) {
    // The afterloader keys its journal by plan id: an id never names two different plans.
    throw std::invalid_argument("plan_id '" + requested_id + "' is already a plan of this node");
  }

  PlanOutcome out;
  StoredPlan& stored = out.stored;
  dose::HdrCase& c = stored.hdr_case;
  if (!dicom_dir.empty()) {
    try {
      c = dose::loadDicomCase(dicom_dir).planning;  // candidate dwells, ch. 6 points, Table 6.1
    } catch (const std::exception& e) {
      throw std::invalid_argument("dicom_dir '" + dicom_dir + "': " + e.what());
    }
  } else if (!case_dir.empty()) {
    if (!std::filesystem::is_directory(case_dir)) {
      throw std::invalid_argument("case_dir '" + case_dir + "' is not a directory");
    }
    try {
      c = dose::readCaseFolder(case_dir);
    } catch (const std::exception& e) {
      throw std::invalid_argument("case_dir '" + case_dir + "': " + e.what());
    }
  } else {
    const int seed = synthetic_seed == 0 ? settings_.default_synthetic_seed : synthetic_seed;
    if (seed < 1) {
      throw std::invalid_argument(
          "synthetic_seed " + std::to_string(synthetic_seed) +
          " must be >= 1 (0: ~default_synthetic_seed) when case_dir is empty");
    }
    dose::SyntheticCaseOptions options;
    options.seed = static_cast<unsigned>(seed);
    c = dose::syntheticProstateCase(options);
  }
  const std::string where = "case '" + c.name + "'";
  if (c.dwells.empty())
    throw std::invalid_argument(where + " has no dwell positions");
  if (c.points.empty())
    throw std::invalid_argument(where + " has no dose points");
  try {
    stored.source = source(c.source);
  } catch (const std::exception& e) {
    throw std::invalid_argument(where + ": source '" + c.source + "': " + e.what());
  }

  // Optimise (dissertation 6.2.3: LP of eq. 6.6, or annealing as the clinical baseline).
  const Eigen::MatrixXd d = dose::doseRateMatrix(c, *stored.source);
  for (const auto& note : dose::penaltyModel(c).notes)
    ROS_INFO_STREAM_NAMED("dwell_scheduler", where << ": " << note);
  dose::DwellResult result;
  if (method == "lp") {
    result = dose::optimizeLp(c, d);
  } else {
    dose::AnnealingOptions options;
    options.iterations = settings_.sa_iterations;
    options.seed = settings_.sa_seed;
    result = dose::optimizeAnnealing(c, d, options);
  }
  if (!result.ok()) {
    throw std::runtime_error(where + ": " + method + " optimisation failed: " + result.status);
  }
  if (result.times_s.size() != c.dwells.size()) {
    throw std::runtime_error(where + ": the optimiser returned " +
                             std::to_string(result.times_s.size()) + " dwell times for " +
                             std::to_string(c.dwells.size()) + " dwell positions");
  }
  requireFinite(result.objective, where + ": objective");
  requireFinite(result.lower_bound, where + ": lower bound");
  stored.planned_times_s = result.times_s;
  for (std::size_t j = 0; j < stored.planned_times_s.size(); ++j) {
    double& t = stored.planned_times_s[j];
    if (!std::isfinite(t) || t < 0.0) {
      throw std::runtime_error(where + ": the optimiser gave dwell " + std::to_string(j) +
                               " the time " + formatNumber(t) + " s");
    }
    if (t <= settings_.schedule.min_dwell_s)
      t = 0.0;  // makeSchedule drops it: plan what is delivered
  }

  const std::string plan_id = requested_id.empty() ? newPlanId(c.name, method) : requested_id;
  try {
    stored.schedule =
        delivery::makeSchedule(c, stored.planned_times_s, plan_id, settings_.schedule);
  } catch (const std::exception& e) {
    throw std::runtime_error(where + ": schedule: " + e.what());
  }
  if (stored.schedule.channels.empty())
    throw std::runtime_error(where + ": the plan has no dwell time at all");
  double transit_s = 0.0;
  for (const auto& ch : stored.schedule.channels)
    transit_s += delivery::tripTransitSeconds(ch, settings_.source_speed_m_s);

  // Indices and DVHs on the structure grid (dissertation 6.3.2).
  const auto doses =
      dose::structureDoses(c, *stored.source, stored.planned_times_s, settings_.dose_grid_m);
  stored.planned_indices = dose::dosimetricIndices(doses, c.prescription_Gy);
  double max_dose_Gy = 0.0;
  for (const auto& s : doses) {
    for (double v : s.dose_Gy) {
      requireFinite(v, where + ": dose in " + s.name);
      max_dose_Gy = std::max(max_dose_Gy, v);
    }
  }
  // Up to 2 Rx (hot spots around the sources would squash the curves), less if nothing gets it.
  const double dvh_max_Gy =
      max_dose_Gy > 0.0 ? std::min(2.0 * c.prescription_Gy, max_dose_Gy) : 2.0 * c.prescription_Gy;
  out.dvh.plan_id = plan_id;
  for (int b = 0; b <= settings_.dvh_bins; ++b)
    out.dvh.dose_Gy.push_back(dvh_max_Gy * b / settings_.dvh_bins);
  for (const auto& s : doses) {
    DvhCurve curve;
    curve.structure = s.name;
    curve.volume_percent = dose::cumulativeDvh(s, dvh_max_Gy, settings_.dvh_bins);
    out.dvh.curves.push_back(curve);
  }

  DwellPlan& plan = out.plan;
  plan.plan_id = plan_id;
  plan.case_name = c.name;
  plan.method = method;
  plan.objective = result.objective;
  plan.lower_bound = method == "lp" ? result.lower_bound : 0.0;  // E >= 0 is all SA certifies
  plan.optimisation_s = result.seconds;
  plan.prescription_Gy = c.prescription_Gy;
  splitIndices(stored.planned_indices, plan.index_names, plan.index_values);
  plan.total_dwell_s = stored.schedule.totalDwellTime();
  plan.transit_s = transit_s;
  plan.schedule = ros_conversions::toMessage(stored.schedule, settings_.frame_id);
  for (double v : {plan.optimisation_s, plan.total_dwell_s, plan.transit_s,
                   stored.schedule.current_air_kerma_strength_U}) {
    requireFinite(v, where + ": plan summary value");
  }

  out.markers =
      planMarkers(c, *stored.source, stored.planned_times_s, stored.schedule, settings_.frame_id);

  std::ostringstream summary;
  summary << "plan " << plan_id << ": " << where << " with " << method << ", objective "
          << result.objective;
  if (stored.planned_indices.count("prostate_V100")) {
    summary << ", prostate V100 " << stored.planned_indices.at("prostate_V100") << " %";
  }
  summary << ", " << stored.schedule.dwellCount() << " dwells in "
          << stored.schedule.channels.size() << " channels, " << plan.total_dwell_s << " s dwell + "
          << transit_s << " s transit; planned in " << (ros::WallTime::now() - start).toSec()
          << " s";
  out.summary = summary.str();
  return out;
}

DwellPlan DwellSchedulerRos::commit(PlanOutcome outcome) {
  const ros::Time now = ros::Time::now();
  outcome.plan.header.stamp = now;
  outcome.plan.header.frame_id = settings_.frame_id;
  outcome.dvh.header.stamp = now;
  outcome.dvh.header.frame_id = settings_.frame_id;
  const std::string id = outcome.plan.plan_id;
  plans_.emplace(id, std::move(outcome.stored));
  ++plans_made_;
  plan_pub_.publish(outcome.plan);
  dvh_pub_.publish(outcome.dvh);
  markers_pub_.publish(outcome.markers);
  ROS_INFO_STREAM_NAMED("dwell_scheduler", outcome.summary);
  return outcome.plan;
}

bool DwellSchedulerRos::onPlan(PlanDwells::Request& req, PlanDwells::Response& res) {
  try {
    PlanOutcome outcome = makePlan(req.case_dir, req.synthetic_seed, req.method, req.plan_id, req.dicom_dir);
    res.message = outcome.summary;
    res.plan = commit(std::move(outcome));
    res.success = true;
  } catch (const std::exception& e) {
    res = PlanDwells::Response();
    res.success = false;
    res.message = e.what();
    ROS_WARN_STREAM_NAMED("dwell_scheduler", "plan refused: " << e.what());
  }
  return true;
}

void DwellSchedulerRos::evaluate(const EvaluateDelivery::Request& req,
                                 EvaluateDelivery::Response& res) const {
  const auto found = plans_.find(req.plan_id);
  if (found == plans_.end()) {
    std::string known;
    for (const auto& [id, plan] : plans_)
      known += (known.empty() ? "" : ", ") + id;
    throw std::invalid_argument("unknown plan_id '" + req.plan_id +
                                "' (plans of this node: " + (known.empty() ? "none" : known) + ")");
  }
  const StoredPlan& stored = found->second;
  const dose::HdrCase& c = stored.hdr_case;
  const delivery::Schedule& schedule = stored.schedule;
  if (req.dwell_index.size() != req.channel.size() ||
      req.delivered_s.size() != req.channel.size()) {
    throw std::invalid_argument(
        "channel, dwell_index and delivered_s have " + std::to_string(req.channel.size()) + ", " +
        std::to_string(req.dwell_index.size()) + " and " + std::to_string(req.delivered_s.size()) +
        " entries (must be equal)");
  }
  if (req.trips.size() != req.trips_channel.size()) {
    throw std::invalid_argument("trips_channel and trips have " +
                                std::to_string(req.trips_channel.size()) + " and " +
                                std::to_string(req.trips.size()) + " entries (must be equal)");
  }
  // Delivered times back at the plan's S_K: the source was weaker by current / plan.
  const double to_plan = schedule.current_air_kerma_strength_U / schedule.plan_air_kerma_strength_U;
  auto catheterOf = [&](const delivery::ChannelSchedule& ch) {
    for (std::size_t k = 0; k < c.catheters.size(); ++k) {
      if (c.catheters[k].name == ch.catheter)
        return static_cast<int>(k);
    }
    throw std::runtime_error("plan '" + req.plan_id + "': channel " + std::to_string(ch.channel) +
                             "'s catheter '" + ch.catheter + "' is not in its case");
  };
  std::vector<double> delivered(c.dwells.size(), 0.0);
  for (std::size_t k = 0; k < req.channel.size(); ++k) {
    const std::string entry = "entry " + std::to_string(k) + " (channel " +
                              std::to_string(req.channel[k]) + ", dwell_index " +
                              std::to_string(req.dwell_index[k]) + ")";
    const double t = req.delivered_s[k];
    if (!std::isfinite(t) || t < 0.0) {
      throw std::invalid_argument(entry + ": delivered time " + formatNumber(t) +
                                  " s must be finite and >= 0");
    }
    const int ch_index = schedule.channelIndex(req.channel[k]);
    if (ch_index < 0)
      throw std::invalid_argument(entry + ": channel not in plan '" + req.plan_id + "'");
    const delivery::ChannelSchedule& ch = schedule.channels[static_cast<std::size_t>(ch_index)];
    if (std::find(ch.dwell_index.begin(), ch.dwell_index.end(), req.dwell_index[k]) ==
        ch.dwell_index.end()) {
      throw std::invalid_argument(entry + ": no such scheduled dwell in that channel");
    }
    const int catheter = catheterOf(ch);
    std::size_t j = 0;
    while (j < c.dwells.size() &&
           !(c.dwells[j].catheter == catheter && c.dwells[j].index == req.dwell_index[k]))
      ++j;
    if (j == c.dwells.size())
      throw std::runtime_error(entry + ": dwell position missing from the case");
    delivered[j] += t * to_plan;  // an interrupted dwell reported twice adds up
  }
  // Transit: every trip's path in the patient as short equivalent dwells (schedule.h).
  std::vector<dose::ExtraDwell> transit;
  for (std::size_t k = 0; k < req.trips_channel.size(); ++k) {
    const std::string entry = "trips entry " + std::to_string(k) + " (channel " +
                              std::to_string(req.trips_channel[k]) + ")";
    if (req.trips[k] < 0)
      throw std::invalid_argument(entry + ": " + std::to_string(req.trips[k]) + " trips");
    const int ch_index = schedule.channelIndex(req.trips_channel[k]);
    if (ch_index < 0)
      throw std::invalid_argument(entry + ": channel not in plan '" + req.plan_id + "'");
    if (req.trips[k] == 0)
      continue;
    const delivery::ChannelSchedule& ch = schedule.channels[static_cast<std::size_t>(ch_index)];
    const int catheter = catheterOf(ch);
    for (const auto& sample : delivery::tripTransitSamples(ch, settings_.source_speed_m_s)) {
      dose::ExtraDwell e;
      e.dwell.catheter = catheter;
      e.dwell.index = -1;  // between dwell positions
      e.dwell.position_m = sample.position_m;
      e.dwell.axis = sample.axis;
      e.time_s = sample.time_s * req.trips[k] * to_plan;
      transit.push_back(e);
    }
  }

  const auto delivered_doses =
      dose::structureDoses(c, *stored.source, delivered, settings_.dose_grid_m);
  auto with_transit = delivered_doses;
  if (!transit.empty()) {
    const auto transit_doses =
        dose::structureDoses(c, *stored.source, std::vector<double>(c.dwells.size(), 0.0), transit,
                             settings_.dose_grid_m);
    for (std::size_t s = 0; s < with_transit.size(); ++s) {
      for (std::size_t i = 0; i < with_transit[s].dose_Gy.size(); ++i)
        with_transit[s].dose_Gy[i] += transit_doses[s].dose_Gy[i];
    }
  }
  const auto delivered_indices = dose::dosimetricIndices(delivered_doses, c.prescription_Gy);
  const auto transit_indices = dose::dosimetricIndices(with_transit, c.prescription_Gy);

  double transit_max = 0.0, transit_target_sum = 0.0;
  int target_points = 0;
  for (const auto& p : c.points) {
    double dose_Gy = 0.0;
    for (const auto& e : transit)
      dose_Gy += e.time_s * dose::dwellDoseRate(c, *stored.source, e.dwell, p.position_m);
    transit_max = std::max(transit_max, dose_Gy);
    if (p.structure >= 0 && static_cast<std::size_t>(p.structure) < c.structures.size() &&
        c.structures[static_cast<std::size_t>(p.structure)].role == dose::StructureRole::kTarget) {
      transit_target_sum += dose_Gy;
      ++target_points;
    }
  }
  const double transit_mean = target_points > 0 ? transit_target_sum / target_points : 0.0;
  requireFinite(transit_max, "transit dose max");
  requireFinite(transit_mean, "transit dose mean");

  res.index_names.clear();
  res.planned_values.clear();
  res.delivered_values.clear();
  res.with_transit_values.clear();
  for (const auto& [name, planned] : stored.planned_indices) {
    const auto d = delivered_indices.find(name);
    const auto w = transit_indices.find(name);
    if (d == delivered_indices.end() || w == transit_indices.end()) {
      throw std::runtime_error("index " + name + " missing from the delivered dose");
    }
    requireFinite(d->second, "delivered " + name);
    requireFinite(w->second, "delivered + transit " + name);
    res.index_names.push_back(name);
    res.planned_values.push_back(planned);
    res.delivered_values.push_back(d->second);
    res.with_transit_values.push_back(w->second);
  }
  res.transit_dose_max_Gy = transit_max;
  res.transit_dose_mean_Gy = transit_mean;
  double delivered_total_s = 0.0;
  for (double t : req.delivered_s)
    delivered_total_s += t;
  std::ostringstream message;
  message << "plan " << req.plan_id << ": " << req.channel.size() << " delivered dwells, "
          << delivered_total_s << " s (of " << schedule.totalDwellTime() << " s scheduled), "
          << transit.size() << " transit samples, transit dose max " << transit_max << " Gy";
  res.message = message.str();
}

bool DwellSchedulerRos::onEvaluate(EvaluateDelivery::Request& req,
                                   EvaluateDelivery::Response& res) {
  const ros::WallTime start = ros::WallTime::now();
  try {
    evaluate(req, res);
    res.success = true;
    ROS_INFO_STREAM_NAMED("dwell_scheduler", "evaluated " << res.message << " in "
                                                          << (ros::WallTime::now() - start).toSec()
                                                          << " s");
  } catch (const std::exception& e) {
    res = EvaluateDelivery::Response();
    res.success = false;
    res.message = e.what();
    ROS_WARN_STREAM_NAMED("dwell_scheduler", "evaluate refused: " << e.what());
  }
  return true;
}

}  // namespace needle_guidance
