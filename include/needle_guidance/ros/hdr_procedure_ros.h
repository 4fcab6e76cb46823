// The HDR delivery procedure (dissertation ch. 6 end to end): plan -> schedule -> deliver ->
// evaluate, and the delivery report (node hdr_procedure).
#pragma once

#include <ros/ros.h>

#include <string>

#include "needle_guidance/DeliverAction.h"
#include "needle_guidance/DwellPlan.h"
#include "needle_guidance/procedures/hdr_report.h"
#include "needle_guidance/ros/node_supervisor.h"

namespace needle_guidance {

/// Reads parameters once (throws std::runtime_error on a bad one). run() asks `dwell_scheduler`
/// for a plan of the case, sends its schedule to the afterloader's `deliver` action (optionally
/// pausing it once at a delivered fraction, as an operator would), asks the scheduler to
/// evaluate what was delivered, and writes report_dir/{summary.json, summary.md, delivery.csv,
/// indices.csv}. Returns true when the delivery completed with every dwell within tolerance.
/// It watches dwell_scheduler and the afterloader during the delivery: when one dies it stops
/// (the source retracts if the afterloader lives), writes a report naming the node with the
/// dose delivered so far from the afterloader's journal, and returns false; with ~respawn the
/// restarted afterloader is sent the schedule again and resumes from its journal.
class HdrProcedureRos {
public:
  HdrProcedureRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);
  bool run();

private:
  /// A node died during the delivery: the report names it, when, and what the journal says
  /// was delivered. Returns false (the procedure failed).
  bool reportNodeDeath(const DwellPlan& p, procedures::HdrDeliveryReport base,
                       const NodeSupervisor::Death& death, double detect_s,
                       const ros::WallTime& t0);
  /// No delivery started (a node missing at start-up, planning refused or its node died): the
  /// report names the node (or none) and the cause. Returns false.
  bool reportNotStarted(const std::string& node, const std::string& cause, const ros::WallTime& t0);
  /// The report's plan part, with the scheduler's DVH of the plan when it is published.
  procedures::HdrDeliveryReport planReport(const DwellPlan& p) const;
  /// Asks the scheduler to evaluate the delivery; fills r.indices (left empty if refused).
  void evaluate(const DwellPlan& p, const DeliverResult& result,
                procedures::HdrDeliveryReport& r) const;

  double startup_wait_s_ = 60.0;  ///< for the nodes and services to come up [s, wall]
  ros::NodeHandle nh_;
  std::string report_dir_, case_dir_, dicom_dir_, method_, scheduler_, afterloader_;
  int synthetic_seed_ = 1;
  double pause_at_fraction_ = -1.0;
  double pause_wall_s_ = 1.0;
  double timeout_s_ = 600.0;
  double tolerance_s_ = 0.1;
  std::string journal_dir_;  ///< the afterloader's (its ~journal_dir), to read after a crash
  bool respawn_ = false;     ///< the afterloader respawns: wait for it and resume
};

}  // namespace needle_guidance
