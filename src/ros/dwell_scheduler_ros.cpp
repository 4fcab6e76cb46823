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

#include "needle_guidance/dose/isodose.h"
#include "needle_guidance/format.h"
#include "needle_guidance/procedures/hdr_pipeline.h"
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
constexpr double kLegendText_m = 3e-3;     ///< colour key text height
constexpr double kLegendLine_m = 4.5e-3;   ///< colour key line spacing
constexpr double kLegendOffset_m = 12e-3;  ///< colour key's distance to the right of the slice

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
  return ros_conversions::toMessage(geometry::Point2(x, y), z);
}

using ros_conversions::baseMarker;

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
    Marker m = baseMarker(frame_id, "contours", static_cast<int>(k), Marker::LINE_LIST);
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
    Marker m = baseMarker(frame_id, "catheters", static_cast<int>(k), Marker::LINE_STRIP);
    m.scale.x = kCatheterWidth_m;
    m.color = colour(0.6, 0.6, 0.6);
    for (const auto& p : c.catheters[k].points_m)
      m.points.push_back(ros_conversions::toPointMessage(p));
    if (m.points.size() >= 2)
      array.markers.push_back(m);
  }

  Marker dwells = baseMarker(frame_id, "dwells", 0, Marker::SPHERE_LIST);
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
      Marker m = baseMarker(frame_id, "isodose", static_cast<int>(level), Marker::LINE_LIST);
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
    // Colour key beside the slice: what the isodose and dwell colours mean.
    const char* level_names[] = {"50 % Rx", "100 % Rx", "150 % Rx", "200 % Rx"};
    std::vector<std::pair<std::string, std_msgs::ColorRGBA>> key;
    for (std::size_t level = 0; level < std::size(kIsodoseLevels); ++level)
      key.emplace_back(std::string("isodose ") + level_names[level], level_colours[level]);
    key.emplace_back("dwell: short time (blue)", colour(0.4, 0.6, 1.0));
    key.emplace_back("dwell: longest, " + formatNumber(longest_s) + " s (red)",
                     colour(1.0, 0.2, 0.2));
    for (std::size_t k = 0; k < key.size(); ++k) {
      Marker text = baseMarker(frame_id, "legend", static_cast<int>(k), Marker::TEXT_VIEW_FACING);
      // Stacked along the patient's z (the up axis of the default view), right of the slice.
      text.pose.position = point(x_hi + kIsodoseMargin_m + kLegendOffset_m, 0.5 * (y_lo + y_hi),
                                 z + kLegendLine_m * (0.5 * double(key.size()) - double(k)));
      text.scale.z = kLegendText_m;
      text.color = key[k].second;
      text.text = key[k].first;
      array.markers.push_back(text);
    }
  }
  return array;
}

}  // namespace

DwellSchedulerRos::DwellSchedulerRos(ros::NodeHandle& /*nh*/, ros::NodeHandle& private_nh) {
  ROS_INFO("dwell_scheduler parameters:");
  settings_.frame_id = ros_params::text(private_nh, "frame_id", settings_.frame_id, true);
  procedures::HdrPlanSettings& pipeline = settings_.pipeline;
  try {
    pipeline.method =
        procedures::parseDwellMethod(ros_params::text(private_nh, "method", "lp"),
                                     "parameter '" + private_nh.resolveName("method") + "'");
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(e.what());
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
  pipeline.schedule.calibration_air_kerma_strength_U = calibration_U;
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
    pipeline.schedule.days_since_calibration = days;
    ROS_INFO_STREAM("  source: " << calibration_U << " U at calibration, " << days << " days ago: "
                                 << calibration_U * delivery::ir192DecayFactor(days)
                                 << " U at treatment");
  } else {
    ROS_INFO("  no calibration given: each case's S_K is the source's current strength (no decay)");
  }
  pipeline.schedule.transfer_length_m = ros_params::number(
      private_nh, "transfer_length_m", pipeline.schedule.transfer_length_m, 0.0, 2.0, "m");
  pipeline.source_speed_m_s = ros_params::number(private_nh, "source_speed_m_s",
                                                 pipeline.source_speed_m_s, 1e-3, 10.0, "m/s");
  pipeline.dvh_bins = static_cast<int>(
      ros_params::integer(private_nh, "dvh_bins", pipeline.dvh_bins, 1, 100000, "bins"));
  pipeline.dose_grid_m =
      ros_params::number(private_nh, "dose_grid_m", pipeline.dose_grid_m, 5e-4, 1e-2, "m");
  pipeline.annealing.iterations = ros_params::integer(
      private_nh, "sa_iterations", pipeline.annealing.iterations, 1, 100000000, "moves");
  pipeline.annealing.seed = static_cast<unsigned>(
      ros_params::integer(private_nh, "sa_seed", pipeline.annealing.seed, 0, 4294967295L, "-"));
  settings_.default_synthetic_seed = static_cast<int>(ros_params::integer(
      private_nh, "default_synthetic_seed", settings_.default_synthetic_seed, 1, 1000000, "-"));
  const bool plan_on_start = ros_params::flag(private_nh, "plan_on_start", false);

  plan_pub_ = private_nh.advertise<DwellPlan>("plan", 1, true);
  dvh_pub_ = private_nh.advertise<DoseVolumeHistogram>("dvh", 1, true);
  markers_pub_ = private_nh.advertise<visualization_msgs::MarkerArray>("markers", 1, true);
  if (plan_on_start) {
    try {
      commit(makePlan(PlanDwells::Request()));
    } catch (const std::exception& e) {
      throw std::runtime_error("plan_on_start: " + std::string(e.what()));
    }
  }
  plan_srv_ = private_nh.advertiseService("plan", &DwellSchedulerRos::onPlan, this);
  evaluate_srv_ = private_nh.advertiseService("evaluate", &DwellSchedulerRos::onEvaluate, this);
  ROS_INFO("dwell_scheduler: ready");
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

DwellSchedulerRos::PlanOutcome DwellSchedulerRos::makePlan(const PlanDwells::Request& req) {
  const procedures::DwellMethod method =
      req.method.empty() ? settings_.pipeline.method : procedures::parseDwellMethod(req.method);
  if (!req.plan_id.empty() && !delivery::isValidPlanId(req.plan_id)) {
    throw std::invalid_argument(
        "plan_id '" + req.plan_id +
        "' must be 1-100 characters of [A-Za-z0-9_.-], not starting with '.'");
  }
  if (plans_.count(req.plan_id) > 0) {
    // The afterloader keys its journal by plan id: an id never names two different plans.
    throw std::invalid_argument("plan_id '" + req.plan_id + "' is already a plan of this node");
  }
  procedures::HdrCaseInput input;
  input.dicom_dir = req.dicom_dir;
  input.case_dir = req.dicom_dir.empty() ? req.case_dir : "";
  if (input.dicom_dir.empty() && input.case_dir.empty()) {
    input.synthetic_seed =
        req.synthetic_seed == 0 ? settings_.default_synthetic_seed : req.synthetic_seed;
    if (input.synthetic_seed < 1) {
      throw std::invalid_argument(
          "synthetic_seed " + std::to_string(req.synthetic_seed) +
          " must be >= 1 (0: ~default_synthetic_seed) when case_dir is empty");
    }
  }
  dose::HdrCase c = procedures::loadHdrCase(input);
  procedures::HdrPlanSettings settings = settings_.pipeline;
  settings.method = method;
  const std::string plan_id =
      req.plan_id.empty() ? newPlanId(c.name, procedures::toString(method)) : req.plan_id;

  PlanOutcome out;
  out.stored = procedures::planHdr(std::move(c), plan_id, settings, sources_);
  const procedures::HdrPlan& stored = out.stored;
  for (const auto& note : stored.notes)
    ROS_INFO_STREAM_NAMED("dwell_scheduler", "case '" << stored.hdr_case.name << "': " << note);

  out.dvh.plan_id = plan_id;
  out.dvh.dose_Gy = stored.dvh_dose_Gy;
  for (const auto& [name, volume] : stored.dvh) {
    DvhCurve curve;
    curve.structure = name;
    curve.volume_percent = volume;
    out.dvh.curves.push_back(curve);
  }
  DwellPlan& plan = out.plan;
  plan.plan_id = plan_id;
  plan.case_name = stored.hdr_case.name;
  plan.method = procedures::toString(method);
  plan.objective = stored.optimisation.objective;
  // E >= 0 is all annealing certifies.
  plan.lower_bound = method == procedures::DwellMethod::kLp ? stored.optimisation.lower_bound : 0.0;
  plan.optimisation_s = stored.optimisation.seconds;
  plan.prescription_Gy = stored.hdr_case.prescription_Gy;
  for (const auto& [name, value] : stored.planned_indices) {
    plan.index_names.push_back(name);
    plan.index_values.push_back(value);
  }
  plan.total_dwell_s = stored.schedule.totalDwellTime();
  plan.transit_s = stored.transit_s;
  plan.schedule = ros_conversions::toMessage(stored.schedule, settings_.frame_id);
  out.markers = planMarkers(stored.hdr_case, *stored.source, stored.planned_times_s,
                            stored.schedule, settings_.frame_id);
  out.summary = stored.summary;
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
    PlanOutcome outcome = makePlan(req);
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
  procedures::DeliveryRecord record;
  for (std::size_t k = 0; k < req.channel.size(); ++k)
    record.dwells.push_back({req.channel[k], req.dwell_index[k], req.delivered_s[k]});
  for (std::size_t k = 0; k < req.trips.size(); ++k)
    record.trips.push_back({req.trips_channel[k], req.trips[k]});
  const procedures::DeliveryEvaluation ev =
      procedures::evaluateDelivery(found->second, record, settings_.pipeline);
  res.index_names.clear();
  res.planned_values.clear();
  res.delivered_values.clear();
  res.with_transit_values.clear();
  for (const auto& index : ev.indices) {
    res.index_names.push_back(index.name);
    res.planned_values.push_back(index.planned);
    res.delivered_values.push_back(index.delivered);
    res.with_transit_values.push_back(index.with_transit);
  }
  res.transit_dose_max_Gy = ev.transit_dose_max_Gy;
  res.transit_dose_mean_Gy = ev.transit_dose_mean_Gy;
  res.message = ev.message;
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
