// The HDR delivery report (dissertation ch. 6 end to end), ROS-free: what was planned, what the
// afterloader delivered (or, after a fault, what its journal says it delivered), the dose
// indices and the DVH. The hdr_procedure node, tests and benches write the same folder.
#pragma once

#include <string>
#include <utility>
#include <vector>

#include "needle_guidance/delivery/schedule.h"
#include "needle_guidance/procedures/hdr_pipeline.h"

namespace needle_guidance {
namespace procedures {

/// Everything a delivery report says. Fill it, then write().
struct HdrDeliveryReport {
  // The plan.
  std::string case_name, plan_id, method;
  double objective = 0.0;
  int channels = 0;
  double source_U = 0.0;    ///< S_K at treatment [U]
  double decay_days = 0.0;  ///< since the source's calibration [days]
  /// Planned DVH (bin edges [Gy], structure -> volume [%]), empty if the plan's DVH was not seen.
  std::vector<double> dvh_dose_Gy;
  std::vector<std::pair<std::string, std::vector<double>>> dvh;

  // The delivery.
  struct Dwell {
    int channel = 0;
    int dwell_index = 0;
    double planned_s = 0.0;
    double delivered_s = 0.0;
    double uncertainty_s = 0.0;  ///< journal replay after a crash: time that may or may not
                                 ///< have been given [s]
  };
  std::vector<Dwell> dwells;
  std::string status;   ///< the afterloader's (completed, aborted, ...) or "node_died"
  std::string message;  ///< the afterloader's result message, or the cause
  std::string delivered_from = "afterloader";  ///< or "journal" (the device died)
  std::string journal;                         ///< the journal file
  int interruptions = 0;
  double transit_in_patient_s = 0.0;
  std::vector<DeliveryEvaluation::Index> indices;  ///< empty when not evaluated
  double transit_dose_max_Gy = 0.0;

  // Faults (empty when none).
  std::string dead_node;         ///< resolved name of the node that died
  std::string cause;             ///< one line: what died, when, what was done
  double detect_s = 0.0;         ///< from the death being seen to the procedure stopping [s]
  double detected_unix_s = 0.0;  ///< wall clock when the supervisor saw the death [s since 1970]
  int afterloader_restarts = 0;  ///< the afterloader died and came back (respawn), delivery resumed

  double tolerance_s = 0.1;  ///< largest |delivered - planned| per dwell for success [s]
  double wall_s = 0.0;

  double plannedTotal_s() const;
  double deliveredTotal_s() const;
  double maxDwellError_s() const;
  /// The outcome: the delivery completed, every dwell within tolerance, and evaluated.
  bool success() const;

  /// After the afterloader died (its result is gone or not trusted): the delivered time per dwell
  /// of `schedule` and its uncertainty, replayed independently from the device's durable
  /// journal at `journal_path` (delivered_from "journal"). An unreadable journal gives zero
  /// delivered everywhere and says so in delivered_from. Replaces `dwells`.
  void deliveredFromJournal(const delivery::Schedule& schedule, const std::string& journal_path);
  /// Writes dir/{summary.json, summary.md, delivery.csv, indices.csv (when evaluated), dvh.png
  /// (when the DVH is known), dwells.png}; throws std::runtime_error naming a file it cannot
  /// write. The folder must exist (report::prepareReportDir).
  void write(const std::string& dir) const;
  /// The few lines a console shows at the end.
  std::string consoleSummary(const std::string& dir) const;
};

}  // namespace procedures
}  // namespace needle_guidance
