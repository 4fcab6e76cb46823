// Simulated HDR remote afterloader: steps the source through channels and dwell positions of a
// schedule, keeps the dose record durable as it goes (journal.h: every exposure is committed
// before it happens, so a crash can never lose delivered time nor deliver a quantum twice),
// pauses, resumes, aborts, and obeys its interlocks (door open -> pause; catheter obstruction ->
// the source retracts and the channel is skipped). The device model behind the afterloader node;
// no ROS here.
#pragma once

#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "needle_guidance/delivery/journal.h"
#include "needle_guidance/delivery/schedule.h"
#include "needle_guidance/status.h"

namespace needle_guidance::delivery {

struct AfterloaderConfig {
  DeviceLimits limits;
  double source_speed_m_s = 0.5;  ///< source drive speed, all moves [m/s]
  /// Longest exposure one journal commit covers [s]: a crash can leave the record at most this
  /// much above what the source really delivered at one dwell.
  double commit_quantum_s = 0.05;
  std::string journal_dir = ".";  ///< one file <plan_id>.journal per plan
};

enum class DeliveryState { kIdle, kDelivering, kPaused, kStopped, kCompleted };
const char* toString(DeliveryState state);

/// Outcome of a command: accepted or refused with the reason (status.h).
using Status = CommandStatus;

/// Planned and delivered time of one scheduled dwell.
struct DwellRecord {
  int channel = 0;
  int dwell = 0;
  double planned_s = 0.0;
  double delivered_s = 0.0;
};

class Afterloader {
public:
  /// Throws std::invalid_argument for a non-positive speed or quantum, or no channels.
  explicit Afterloader(AfterloaderConfig config);
  ~Afterloader();

  /// Starts (or resumes from its journal) the delivery of `schedule`. Refused, before anything
  /// moves or is written: a schedule validateSchedule() rejects, a delivery already running or
  /// paused, the door open, a plan whose journal shows it fully delivered, a plan id whose
  /// journal holds a different schedule, an unreadable or damaged journal.
  Status start(const Schedule& schedule);
  /// Delivering -> paused: the source retracts (what it dwelt is settled in the journal).
  Status pause(const std::string& reason);
  /// Paused -> delivering. Refused while the door is open.
  Status resume();
  /// Stops the delivery (delivering or paused -> stopped; the source retracts). A later start()
  /// of the same schedule resumes it.
  Status abort(const std::string& reason);
  /// Door interlock: opening it pauses a running delivery.
  void setDoorOpen(bool open);
  /// Catheter obstruction on `channel` (1..limits.channels): if the source is in that channel it
  /// retracts at once and the channel's remaining dwells are skipped for this session; the
  /// session then ends stopped, and a later start() delivers them once the obstruction is cleared.
  Status setObstruction(int channel, bool obstructed);

  /// Advances device time by dt_s (finite, >= 0) [s]. Throws std::runtime_error if the journal
  /// cannot be written (the delivery is then stopped and the source retracted).
  void step(double dt_s);

  DeliveryState state() const { return state_; }
  bool doorOpen() const { return door_open_; }
  std::vector<int> obstructedChannels() const;
  /// Channel number the source is in (0: parked in the safe).
  int sourceChannel() const;
  /// Dwell index where the source dwells now, -1 in transit or parked.
  int sourceDwell() const;
  double sourceDistance() const { return distance_m_; }
  bool sourceInPatient() const;
  /// Source position in the patient frame (only meaningful when sourceChannel() != 0).
  Point3 sourcePosition() const;
  double plannedTotal() const;
  double deliveredTotal() const;
  double deliveredFraction() const;
  double remainingDwellTime() const { return plannedTotal() - deliveredTotal(); }
  double time() const { return time_s_; }  ///< device time since construction [s]
  const std::string& lastMessage() const { return last_message_; }
  const Schedule* schedule() const { return schedule_ ? schedule_.get() : nullptr; }
  /// Per scheduled dwell, delivered time from the journal's view (committed or settled).
  std::vector<DwellRecord> records() const;
  /// The journal of the current plan replayed (trips, transit, interruptions, anomalies).
  Ledger ledger() const;
  std::string journalPath() const;  ///< "" before the first start()
  /// Journal lines written since the last call, in order (to publish).
  std::vector<std::string> takeJournalLines();

private:
  struct Dwell {
    int channel_index;
    int k;  ///< index within the channel's arrays
  };
  void write(JournalRecord r);
  void settleCurrent();
  bool nextDwell(Dwell& next) const;
  void finish();
  void moveToward(double target_m, double& dt_s);
  void beginMove(int channel_index, double target_m);

  AfterloaderConfig config_;
  std::unique_ptr<Schedule> schedule_;
  std::unique_ptr<Journal> journal_;
  std::vector<std::string> new_lines_;
  DeliveryState state_ = DeliveryState::kIdle;
  bool door_open_ = false;
  std::map<int, bool> obstructed_;
  std::map<std::pair<int, int>, double> delivered_;  ///< what the source really dwelt
  std::map<std::pair<int, int>, double> committed_;  ///< what the journal covers (>= delivered_)
  int channel_index_ = -1;   ///< schedule channel the source is in, -1 parked
  double distance_m_ = 0.0;  ///< from the indexer
  bool moving_ = false;
  double move_target_m_ = 0.0;
  int dwell_k_ = -1;             ///< index in the channel of the dwell the source is at, -1 if none
  std::map<int, bool> skipped_;  ///< channels skipped this session (obstruction)
  double time_s_ = 0.0;
  std::string last_message_;
};

}  // namespace needle_guidance::delivery
