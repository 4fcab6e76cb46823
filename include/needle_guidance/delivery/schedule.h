// HDR delivery schedule: an optimised dwell plan (dissertation ch. 6) turned into what a remote
// afterloader executes — channel order, dwell positions as distances from the channel's
// reference (the afterloader's indexer), dwell times scaled for the source's decay since its
// calibration (Ir-192), and the source's transit between positions. No ROS here.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "needle_guidance/dose/hdr_case.h"

namespace needle_guidance::delivery {

using dose::Point3;

constexpr double kIr192HalfLifeDays = 73.83;

/// Fraction of an Ir-192 source's air-kerma strength left after `days` (>= 0, finite; throws).
double ir192DecayFactor(double days);

/// Seconds since 1970-01-01 UTC of "YYYY-MM-DD" or "YYYY-MM-DDTHH:MM[:SS]" (UTC). Throws
/// std::invalid_argument naming the text for anything else (month 13, day 32, trailing text).
double parseUtcSeconds(const std::string& text);

/// One afterloader channel. Distances are measured along the channel from the indexer (0: the
/// source parked in the afterloader's safe); the catheter tip is at length_m and the catheter
/// enters the patient at transfer_length_m. Dwells in delivery order: tip first, backwards.
struct ChannelSchedule {
  int channel = 0;  ///< afterloader channel number, 1-based
  std::string catheter;
  double length_m = 0.0;
  double transfer_length_m = 0.0;
  std::vector<int> dwell_index;    ///< DwellPosition::index (position number from the tip)
  std::vector<double> distance_m;  ///< from the indexer, strictly decreasing [m]
  std::vector<double> time_s;      ///< at the current air-kerma strength [s], >= 0
  std::vector<Point3> position_m;  ///< dwell positions in the patient frame (display) [m]
  std::vector<Point3> path_m;      ///< catheter from its tip to the patient surface [m]

  /// Source position in the patient frame at `distance_m` from the indexer: on the catheter path
  /// inside the patient, on the path's straight extension outside it.
  Point3 sourcePosition(double distance_m) const;
  bool inPatient(double distance_m) const { return distance_m > transfer_length_m; }
};

struct Schedule {
  std::string plan_id;
  std::string source = "microselectron_v2_hdr";
  double plan_air_kerma_strength_U = 0.0;     ///< S_K the plan was optimised for [U]
  double current_air_kerma_strength_U = 0.0;  ///< S_K at treatment [U]
  double decay_days = 0.0;
  std::vector<ChannelSchedule> channels;  ///< in delivery order

  std::size_t dwellCount() const;
  double totalDwellTime() const;  ///< [s]
  /// Index of the channel with this number, -1 if absent.
  int channelIndex(int channel) const;
  /// FNV-1a hash of the channels, distances (0.1 µm) and times (1 µs): the journal uses it to
  /// make sure a resumed delivery is the same schedule.
  std::uint64_t contentHash() const;
};

struct ScheduleOptions {
  /// Air-kerma strength at the source's calibration [U]; 0: the plan's S_K is the current one
  /// (no decay correction).
  double calibration_air_kerma_strength_U = 0.0;
  double days_since_calibration = 0.0;  ///< >= 0
  double transfer_length_m = 1.0;       ///< indexer to the patient along every channel [m]
  int first_channel = 1;                ///< catheter k goes to channel first_channel + k
  /// Dwell times at or below this are dropped (the source does not stop there) [s].
  double min_dwell_s = 1e-3;
};

/// The schedule of `times_s` (one per c.dwells, at the plan's S_K c.air_kerma_strength_U):
/// catheters in order, each with its dwells of non-negligible time from the tip backwards; times
/// scaled by S_K(plan) / S_K(now), S_K(now) = calibration S_K x ir192DecayFactor(days). Throws
/// std::invalid_argument for a size mismatch, negative or non-finite times, a dwell off its
/// catheter, or a decayed source weaker than 1 % of the plan's S_K.
Schedule makeSchedule(const dose::HdrCase& c, const std::vector<double>& times_s,
                      const std::string& plan_id, const ScheduleOptions& options = {});

/// Characters of a plan id (it names the journal file): [A-Za-z0-9_.-], 1-100, not starting with
/// '.'.
constexpr const char* kPlanIdCharacters =
    "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-.";
bool isValidPlanId(const std::string& id);

/// What the device can do; a schedule outside it is refused before anything moves.
struct DeviceLimits {
  int channels = 18;           ///< channel numbers 1..channels
  double max_length_m = 1.5;   ///< longest channel (indexer to tip) [m]
  double max_dwell_s = 999.0;  ///< longest single dwell [s]
};

/// Every problem of `s` for a device with `limits` (empty: deliverable): empty or unsafe plan id
/// (it names a file), unknown or repeated channel, array lengths that differ, non-finite or
/// negative times, distances outside (0, length_m] or not strictly decreasing, no dwell time at
/// all.
std::vector<std::string> validateSchedule(const Schedule& s, const DeviceLimits& limits);

/// Seconds the source spends moving inside the patient on one trip into `channel`: out to the
/// most distal dwell with time and back to the patient surface, at speed_m_s.
double tripTransitSeconds(const ChannelSchedule& channel, double speed_m_s);

/// The transit of one trip into `channel` as equivalent short dwells: positions every step_m
/// along the path inside the patient up to the most distal dwell, each with the time the source
/// spends within step_m of it (out and back: 2 step / speed) [s].
struct TransitSample {
  Point3 position_m;
  Point3 axis;  ///< towards the catheter tip
  double time_s = 0.0;
};
std::vector<TransitSample> tripTransitSamples(const ChannelSchedule& channel, double speed_m_s,
                                              double step_m = 1e-3);

}  // namespace needle_guidance::delivery
