// The HDR planning pipeline (dissertation ch. 6), ROS-free: a case in (synthetic, plain case
// folder or DICOM-RT) -> optimised dwell times (LP of eq. 6.6 or the annealing baseline) ->
// afterloader schedule -> planned indices and DVHs; and the evaluation of what an afterloader
// delivered against that plan (with the source's transit dose). The dwell_scheduler node, the
// hdr_plan tool and the benches call these, so the pipeline exists once.
#pragma once

#include <map>
#include <memory>
#include <string>
#include <vector>

#include "needle_guidance/delivery/schedule.h"
#include "needle_guidance/dose/dwell_optimization.h"
#include "needle_guidance/dose/hdr_case.h"
#include "needle_guidance/dose/tg43.h"

namespace needle_guidance {
namespace procedures {

/// How the dwell times are optimised (dissertation 6.2.3).
enum class DwellMethod {
  kLp,         ///< the LP of eq. 6.6 (exact optimum of the IPSA penalty), Clp
  kAnnealing,  ///< simulated annealing, the clinical baseline
  kDvh,        ///< target V100 maximised under the dose-volume criteria (MIP, CBC)
};
/// "lp" | "sa" | "dvh".
const char* toString(DwellMethod method);
/// "lp" -> kLp, "sa" -> kAnnealing, "dvh" -> kDvh; throws std::invalid_argument naming `what`
/// otherwise.
DwellMethod parseDwellMethod(const std::string& text, const std::string& what = "method");

/// Where a case comes from: exactly one of dicom_dir, case_dir, or a synthetic seed >= 1.
struct HdrCaseInput {
  std::string dicom_dir;   ///< RTSTRUCT + RTPLAN folder (dose/dicom_case.h)
  std::string case_dir;    ///< plain case folder (dose/case_folder.h)
  int synthetic_seed = 0;  ///< seeded synthetic prostate case (dose/prostate_case.h)
};
/// Loads the case; throws std::invalid_argument naming the folder or seed and the reason.
dose::HdrCase loadHdrCase(const HdrCaseInput& input);

/// Loads each TG-43 source once (tables in config/sources); not thread-safe.
class SourceCache {
public:
  /// The source `name`; throws std::invalid_argument naming it if it cannot be loaded.
  std::shared_ptr<const dose::Tg43Source> get(const std::string& name);

private:
  std::map<std::string, std::shared_ptr<const dose::Tg43Source>> sources_;
};

/// Settings of the pipeline beyond the case (node parameters, tool flags).
struct HdrPlanSettings {
  DwellMethod method = DwellMethod::kLp;
  dose::AnnealingOptions annealing;    ///< moves and seed of the annealing baseline
  delivery::ScheduleOptions schedule;  ///< calibration, decay, transfer length, min dwell
  double source_speed_m_s = 0.5;       ///< source travel speed in the catheters [m/s]
  double dose_grid_m = 2e-3;           ///< structure dose grid for indices and DVHs [m]
  int dvh_bins = 200;                  ///< DVH dose bins from 0 to dvh_max_Gy
};

/// A planned case: everything the delivery and its evaluation need.
struct HdrPlan {
  dose::HdrCase hdr_case;
  std::shared_ptr<const dose::Tg43Source> source;
  DwellMethod method = DwellMethod::kLp;
  dose::DwellResult optimisation;  ///< objective, certified lower bound (LP), time, iterations
  /// One per hdr_case.dwells at the plan's S_K [s]: the optimiser's times with those the
  /// schedule drops (<= ScheduleOptions::min_dwell_s) set to 0, i.e. exactly the schedule.
  std::vector<double> planned_times_s;
  delivery::Schedule schedule;
  double transit_s = 0.0;                         ///< source transit time of all trips [s]
  std::map<std::string, double> planned_indices;  ///< V [%] and D [Gy] indices (6.3.2)
  std::vector<double> dvh_dose_Gy;                ///< DVH bin edges, 0 .. dvh_max [Gy]
  std::vector<std::pair<std::string, std::vector<double>>> dvh;  ///< structure -> volume [%]
  std::vector<std::string> notes;  ///< the penalty model's notes on the case
  std::string summary;             ///< one line for the log
};

/// Plans `c` under `plan_id`: optimises, schedules, computes the indices and DVHs. Throws
/// std::invalid_argument for a case that cannot be planned (no dwells, no points, unknown
/// source) and std::runtime_error for a solver or schedule failure, naming the case; nothing
/// it returns is non-finite.
HdrPlan planHdr(dose::HdrCase c, const std::string& plan_id, const HdrPlanSettings& settings,
                SourceCache& sources);

/// What the afterloader reports having delivered: time per dwell (an interrupted dwell may come
/// twice, its times add up) and the number of trips per channel.
struct DeliveryRecord {
  struct Dwell {
    int channel = 0;
    int dwell_index = 0;
    double delivered_s = 0.0;  ///< at the source's current strength [s]
  };
  struct Trips {
    int channel = 0;
    int trips = 0;
  };
  std::vector<Dwell> dwells;
  std::vector<Trips> trips;
};

/// The delivered dose against the plan.
struct DeliveryEvaluation {
  /// index name -> planned, delivered (dwells only), delivered with the transit dose.
  struct Index {
    std::string name;
    double planned = 0.0, delivered = 0.0, with_transit = 0.0;
  };
  std::vector<Index> indices;
  double transit_dose_max_Gy = 0.0;   ///< largest transit dose at a dose point
  double transit_dose_mean_Gy = 0.0;  ///< mean transit dose over the target's dose points
  std::string message;                ///< one line: dwells, seconds, transit
};

/// Evaluates `record` against `plan`; throws std::invalid_argument naming the first entry that
/// is not in the plan or is not finite and >= 0.
DeliveryEvaluation evaluateDelivery(const HdrPlan& plan, const DeliveryRecord& record,
                                    const HdrPlanSettings& settings);

}  // namespace procedures
}  // namespace needle_guidance
