#include "needle_guidance/procedures/hdr_pipeline.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "needle_guidance/dose/case_folder.h"
#include "needle_guidance/dose/dicom_case.h"
#include "needle_guidance/dose/dose_indices.h"
#include "needle_guidance/dose/dvh_optimization.h"
#include "needle_guidance/dose/prostate_case.h"
#include "needle_guidance/format.h"

namespace needle_guidance {
namespace procedures {
namespace {

/// Throws std::runtime_error naming `what` if `value` is NaN or infinite.
void requireFinite(double value, const std::string& what) {
  if (!std::isfinite(value))
    throw std::runtime_error(what + " is not finite (" + formatNumber(value) + ")");
}

/// The dose-volume plan (default criteria at the case's prescription) as a DwellResult; its
/// objective is the IPSA penalty of the plan on the case's points, for comparison with LP / SA.
dose::DwellResult dvhOptimisation(const dose::HdrCase& c, const dose::Tg43Source& source,
                                  std::vector<std::string>& notes) {
  const dose::DvhPlanResult r =
      dose::optimizeDvh(c, source, dose::defaultDvhCriteria(c.prescription_Gy));
  notes.insert(notes.end(), r.notes.begin(), r.notes.end());
  for (const auto& v : r.violated)
    notes.push_back("dose-volume criterion gives way: " + v);
  dose::DwellResult out;
  out.method = "dvh";
  out.status = r.status;
  out.times_s = r.times_s;
  out.seconds = r.seconds;
  out.iterations = r.rounds;
  if (r.ok()) {
    Eigen::VectorXd dose(static_cast<Eigen::Index>(c.points.size()));
    for (std::size_t i = 0; i < c.points.size(); ++i)
      dose(static_cast<Eigen::Index>(i)) =
          dose::doseAt(c, source, r.times_s, c.points[i].position_m);
    out.objective = dose::penaltyModel(c)(dose);
  }
  return out;
}

/// Optimises the dwell times (6.2.3) and makes them exactly what the schedule delivers.
void optimise(HdrPlan& plan, const HdrPlanSettings& settings, const std::string& where) {
  const dose::HdrCase& c = plan.hdr_case;
  const Eigen::MatrixXd d = dose::doseRateMatrix(c, *plan.source);
  plan.notes = dose::penaltyModel(c).notes;
  if (settings.method == DwellMethod::kDvh) {
    plan.optimisation = dvhOptimisation(c, *plan.source, plan.notes);
  } else {
    plan.optimisation = settings.method == DwellMethod::kLp
                            ? dose::optimizeLp(c, d)
                            : dose::optimizeAnnealing(c, d, settings.annealing);
  }
  const dose::DwellResult& result = plan.optimisation;
  const std::string method = toString(settings.method);
  if (!result.ok())
    throw std::runtime_error(where + ": " + method + " optimisation failed: " + result.status);
  if (result.times_s.size() != c.dwells.size()) {
    throw std::runtime_error(where + ": the optimiser returned " +
                             std::to_string(result.times_s.size()) + " dwell times for " +
                             std::to_string(c.dwells.size()) + " dwell positions");
  }
  requireFinite(result.objective, where + ": objective");
  requireFinite(result.lower_bound, where + ": lower bound");
  plan.planned_times_s = result.times_s;
  for (std::size_t j = 0; j < plan.planned_times_s.size(); ++j) {
    double& t = plan.planned_times_s[j];
    if (!std::isfinite(t) || t < 0.0) {
      throw std::runtime_error(where + ": the optimiser gave dwell " + std::to_string(j) +
                               " the time " + formatNumber(t) + " s");
    }
    if (t <= settings.schedule.min_dwell_s)
      t = 0.0;  // makeSchedule drops it: plan what is delivered
  }
}

/// Indices and DVHs on the structure grid (dissertation 6.3.2).
void doseIndices(HdrPlan& plan, const HdrPlanSettings& settings, const std::string& where) {
  const dose::HdrCase& c = plan.hdr_case;
  const auto doses =
      dose::structureDoses(c, *plan.source, plan.planned_times_s, settings.dose_grid_m);
  plan.planned_indices = dose::dosimetricIndices(doses, c.prescription_Gy);
  for (const auto& [name, value] : plan.planned_indices)
    requireFinite(value, where + ": index " + name);
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
  plan.dvh_dose_Gy.clear();
  for (int b = 0; b <= settings.dvh_bins; ++b)
    plan.dvh_dose_Gy.push_back(dvh_max_Gy * b / settings.dvh_bins);
  plan.dvh.clear();
  for (const auto& s : doses)
    plan.dvh.emplace_back(s.name, dose::cumulativeDvh(s, dvh_max_Gy, settings.dvh_bins));
}

/// Index of the case's catheter that feeds `ch`; throws naming the plan otherwise.
int catheterOf(const HdrPlan& plan, const delivery::ChannelSchedule& ch) {
  const auto& catheters = plan.hdr_case.catheters;
  for (std::size_t k = 0; k < catheters.size(); ++k) {
    if (catheters[k].name == ch.catheter)
      return static_cast<int>(k);
  }
  throw std::runtime_error("plan '" + plan.schedule.plan_id + "': channel " +
                           std::to_string(ch.channel) + "'s catheter '" + ch.catheter +
                           "' is not in its case");
}

/// Delivered time per case dwell, back at the plan's S_K (the source was weaker by current /
/// plan); throws naming the first entry that is not in the plan.
std::vector<double> deliveredTimes(const HdrPlan& plan, const DeliveryRecord& record) {
  const dose::HdrCase& c = plan.hdr_case;
  const delivery::Schedule& schedule = plan.schedule;
  const double to_plan = schedule.current_air_kerma_strength_U / schedule.plan_air_kerma_strength_U;
  std::vector<double> delivered(c.dwells.size(), 0.0);
  for (std::size_t k = 0; k < record.dwells.size(); ++k) {
    const DeliveryRecord::Dwell& e = record.dwells[k];
    const std::string entry = "entry " + std::to_string(k) + " (channel " +
                              std::to_string(e.channel) + ", dwell_index " +
                              std::to_string(e.dwell_index) + ")";
    if (!std::isfinite(e.delivered_s) || e.delivered_s < 0.0) {
      throw std::invalid_argument(entry + ": delivered time " + formatNumber(e.delivered_s) +
                                  " s must be finite and >= 0");
    }
    const int ch_index = schedule.channelIndex(e.channel);
    if (ch_index < 0)
      throw std::invalid_argument(entry + ": channel not in plan '" + schedule.plan_id + "'");
    const delivery::ChannelSchedule& ch = schedule.channels[static_cast<std::size_t>(ch_index)];
    if (std::find(ch.dwell_index.begin(), ch.dwell_index.end(), e.dwell_index) ==
        ch.dwell_index.end()) {
      throw std::invalid_argument(entry + ": no such scheduled dwell in that channel");
    }
    const int catheter = catheterOf(plan, ch);
    std::size_t j = 0;
    while (j < c.dwells.size() &&
           !(c.dwells[j].catheter == catheter && c.dwells[j].index == e.dwell_index))
      ++j;
    if (j == c.dwells.size())
      throw std::runtime_error(entry + ": dwell position missing from the case");
    delivered[j] += e.delivered_s * to_plan;  // an interrupted dwell reported twice adds up
  }
  return delivered;
}

/// Every trip's path in the patient as short equivalent dwells (schedule.h), at the plan's S_K.
std::vector<dose::ExtraDwell> transitDwells(const HdrPlan& plan, const DeliveryRecord& record,
                                            double source_speed_m_s) {
  const delivery::Schedule& schedule = plan.schedule;
  const double to_plan = schedule.current_air_kerma_strength_U / schedule.plan_air_kerma_strength_U;
  std::vector<dose::ExtraDwell> transit;
  for (std::size_t k = 0; k < record.trips.size(); ++k) {
    const DeliveryRecord::Trips& t = record.trips[k];
    const std::string entry =
        "trips entry " + std::to_string(k) + " (channel " + std::to_string(t.channel) + ")";
    if (t.trips < 0)
      throw std::invalid_argument(entry + ": " + std::to_string(t.trips) + " trips");
    const int ch_index = schedule.channelIndex(t.channel);
    if (ch_index < 0)
      throw std::invalid_argument(entry + ": channel not in plan '" + schedule.plan_id + "'");
    if (t.trips == 0)
      continue;
    const delivery::ChannelSchedule& ch = schedule.channels[static_cast<std::size_t>(ch_index)];
    const int catheter = catheterOf(plan, ch);
    for (const auto& sample : delivery::tripTransitSamples(ch, source_speed_m_s)) {
      dose::ExtraDwell e;
      e.dwell.catheter = catheter;
      e.dwell.index = -1;  // between dwell positions
      e.dwell.position_m = sample.position_m;
      e.dwell.axis = sample.axis;
      e.time_s = sample.time_s * t.trips * to_plan;
      transit.push_back(e);
    }
  }
  return transit;
}

}  // namespace

const char* toString(DwellMethod method) {
  return method == DwellMethod::kLp ? "lp" : method == DwellMethod::kDvh ? "dvh" : "sa";
}

DwellMethod parseDwellMethod(const std::string& text, const std::string& what) {
  if (text == "lp")
    return DwellMethod::kLp;
  if (text == "sa")
    return DwellMethod::kAnnealing;
  if (text == "dvh")
    return DwellMethod::kDvh;
  throw std::invalid_argument(what + " '" + text + "' is not lp, sa or dvh");
}

dose::HdrCase loadHdrCase(const HdrCaseInput& input) {
  const int given =
      int(!input.dicom_dir.empty()) + int(!input.case_dir.empty()) + int(input.synthetic_seed != 0);
  if (given != 1) {
    throw std::invalid_argument("give exactly one of dicom_dir, case_dir or synthetic_seed (" +
                                std::to_string(given) + " given)");
  }
  if (!input.dicom_dir.empty()) {
    try {
      return dose::loadDicomCase(input.dicom_dir).planning;  // candidate dwells, ch. 6 points
    } catch (const std::exception& e) {
      throw std::invalid_argument("dicom_dir '" + input.dicom_dir + "': " + e.what());
    }
  }
  if (!input.case_dir.empty()) {
    if (!std::filesystem::is_directory(input.case_dir))
      throw std::invalid_argument("case_dir '" + input.case_dir + "' is not a directory");
    try {
      return dose::readCaseFolder(input.case_dir);
    } catch (const std::exception& e) {
      throw std::invalid_argument("case_dir '" + input.case_dir + "': " + e.what());
    }
  }
  if (input.synthetic_seed < 1) {
    throw std::invalid_argument("synthetic_seed " + std::to_string(input.synthetic_seed) +
                                " must be >= 1");
  }
  dose::SyntheticCaseOptions options;
  options.seed = static_cast<unsigned>(input.synthetic_seed);
  return dose::syntheticProstateCase(options);
}

std::shared_ptr<const dose::Tg43Source> SourceCache::get(const std::string& name) {
  auto it = sources_.find(name);
  if (it == sources_.end()) {
    try {
      it = sources_.emplace(name, std::make_shared<const dose::Tg43Source>(dose::loadSource(name)))
               .first;
    } catch (const std::exception& e) {
      throw std::invalid_argument("source '" + name + "': " + e.what());
    }
  }
  return it->second;
}

HdrPlan planHdr(dose::HdrCase c, const std::string& plan_id, const HdrPlanSettings& settings,
                SourceCache& sources) {
  const auto start = std::chrono::steady_clock::now();
  const std::string where = "case '" + c.name + "'";
  if (c.dwells.empty())
    throw std::invalid_argument(where + " has no dwell positions");
  if (c.points.empty())
    throw std::invalid_argument(where + " has no dose points");
  if (settings.dvh_bins < 1)
    throw std::invalid_argument("planHdr: dvh_bins " + std::to_string(settings.dvh_bins) + " < 1");
  HdrPlan plan;
  plan.method = settings.method;
  plan.source = sources.get(c.source);
  plan.hdr_case = std::move(c);

  optimise(plan, settings, where);
  try {
    plan.schedule =
        delivery::makeSchedule(plan.hdr_case, plan.planned_times_s, plan_id, settings.schedule);
  } catch (const std::exception& e) {
    throw std::runtime_error(where + ": schedule: " + e.what());
  }
  if (plan.schedule.channels.empty())
    throw std::runtime_error(where + ": the plan has no dwell time at all");
  for (const auto& ch : plan.schedule.channels)
    plan.transit_s += delivery::tripTransitSeconds(ch, settings.source_speed_m_s);
  doseIndices(plan, settings, where);
  for (double v : {plan.optimisation.seconds, plan.schedule.totalDwellTime(), plan.transit_s,
                   plan.schedule.current_air_kerma_strength_U})
    requireFinite(v, where + ": plan summary value");

  std::ostringstream summary;
  summary << "plan " << plan_id << ": " << where << " with " << toString(settings.method)
          << ", objective " << plan.optimisation.objective;
  if (plan.planned_indices.count("prostate_V100"))
    summary << ", prostate V100 " << plan.planned_indices.at("prostate_V100") << " %";
  summary << ", " << plan.schedule.dwellCount() << " dwells in " << plan.schedule.channels.size()
          << " channels, " << plan.schedule.totalDwellTime() << " s dwell + " << plan.transit_s
          << " s transit; planned in "
          << std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count()
          << " s";
  plan.summary = summary.str();
  return plan;
}

DeliveryEvaluation evaluateDelivery(const HdrPlan& plan, const DeliveryRecord& record,
                                    const HdrPlanSettings& settings) {
  const dose::HdrCase& c = plan.hdr_case;
  const std::vector<double> delivered = deliveredTimes(plan, record);
  const std::vector<dose::ExtraDwell> transit =
      transitDwells(plan, record, settings.source_speed_m_s);

  const auto delivered_doses =
      dose::structureDoses(c, *plan.source, delivered, settings.dose_grid_m);
  auto with_transit = delivered_doses;
  if (!transit.empty()) {
    const auto transit_doses = dose::structureDoses(
        c, *plan.source, std::vector<double>(c.dwells.size(), 0.0), transit, settings.dose_grid_m);
    for (std::size_t s = 0; s < with_transit.size(); ++s) {
      for (std::size_t i = 0; i < with_transit[s].dose_Gy.size(); ++i)
        with_transit[s].dose_Gy[i] += transit_doses[s].dose_Gy[i];
    }
  }
  const auto delivered_indices = dose::dosimetricIndices(delivered_doses, c.prescription_Gy);
  const auto transit_indices = dose::dosimetricIndices(with_transit, c.prescription_Gy);

  DeliveryEvaluation out;
  double transit_target_sum = 0.0;
  int target_points = 0;
  for (const auto& p : c.points) {
    double dose_Gy = 0.0;
    for (const auto& e : transit)
      dose_Gy += e.time_s * dose::dwellDoseRate(c, *plan.source, e.dwell, p.position_m);
    out.transit_dose_max_Gy = std::max(out.transit_dose_max_Gy, dose_Gy);
    if (p.structure >= 0 && static_cast<std::size_t>(p.structure) < c.structures.size() &&
        c.structures[static_cast<std::size_t>(p.structure)].role == dose::StructureRole::kTarget) {
      transit_target_sum += dose_Gy;
      ++target_points;
    }
  }
  out.transit_dose_mean_Gy = target_points > 0 ? transit_target_sum / target_points : 0.0;
  requireFinite(out.transit_dose_max_Gy, "transit dose max");
  requireFinite(out.transit_dose_mean_Gy, "transit dose mean");

  for (const auto& [name, planned] : plan.planned_indices) {
    const auto d = delivered_indices.find(name);
    const auto w = transit_indices.find(name);
    if (d == delivered_indices.end() || w == transit_indices.end())
      throw std::runtime_error("index " + name + " missing from the delivered dose");
    requireFinite(d->second, "delivered " + name);
    requireFinite(w->second, "delivered + transit " + name);
    out.indices.push_back({name, planned, d->second, w->second});
  }
  double delivered_total_s = 0.0;
  for (const auto& e : record.dwells)
    delivered_total_s += e.delivered_s;
  std::ostringstream message;
  message << "plan " << plan.schedule.plan_id << ": " << record.dwells.size()
          << " delivered dwells, " << delivered_total_s << " s (of "
          << plan.schedule.totalDwellTime() << " s scheduled), " << transit.size()
          << " transit samples, transit dose max " << out.transit_dose_max_Gy << " Gy";
  out.message = message.str();
  return out;
}

}  // namespace procedures
}  // namespace needle_guidance
