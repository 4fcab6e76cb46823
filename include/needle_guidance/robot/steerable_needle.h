// The simulated steerable bevel-tip needle: "the world" of the insertion robot in steerable mode.
// The needle enters on the line x = start_x at an entry height
// and angle and then follows the continuous model of dissertation 5.3: it traces arcs of radius
// r, counter-clockwise with the bevel left and clockwise with the bevel right; at the start of
// every insertion command the tip orientation is deflected by beta ~ N(0, sigma_r) when a bevel
// flip came before it (u = 1) and by beta ~ N(0, sigma_i) otherwise (u = 0). An insertion that
// touches an expanded obstacle or leaves the workspace stops at the contact point. Retraction
// follows the inserted path back exactly. Plain C++; no ROS.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "needle_guidance/needle_model/planar_world.h"
#include "needle_guidance/robot/insertion_stage.h"
#include "needle_guidance/status.h"

namespace needle_guidance::robot {

/// Fixed properties of the simulated needle and its entry.
struct SteerableNeedleConfig {
  double start_x_m = 0.0;     ///< the needle enters on the line x = start_x_m of frame scene [m]
  double min_height_m = 0.0;  ///< lowest entry height y allowed [m]
  double max_height_m = 0.0;  ///< highest entry height y allowed [m], >= min_height_m
  double sigma_insert_rad = 0.0;  ///< sigma_i: std. dev. of beta on a plain insertion [rad], >= 0
  double sigma_flip_rad = 0.0;    ///< sigma_r: std. dev. of beta after a bevel flip [rad], >= 0
  std::uint64_t seed = 1;         ///< seed of the deflection stream (std::mt19937_64)
  /// Contact checks follow each arc as chords at most this far inside the true arc [m], > 0.
  double chord_tolerance_m = 1e-5;
};

/// Where and how the needle enters: tip at (start_x, height_m) with tangent angle angle_rad.
struct EntryPose {
  double height_m = 0.0;   ///< y of the entry point [m]
  double angle_rad = 0.0;  ///< insertion angle from +x, in [-pi/2, pi/2] [rad]
  needle_model::Bevel bevel = needle_model::Bevel::kLeft;
};

/// One insertion command's arc of the inserted needle.
struct NeedleSegment {
  double start_length_m = 0.0;  ///< inserted length where the segment begins [m]
  double length_m = 0.0;        ///< arc length of the segment [m], >= 0
  /// Tip pose at the segment's start after the deflection (theta = previous theta + beta) and
  /// the bevel that traces the arc [m, rad].
  needle_model::TipPose start;
  needle_model::Control control =
      needle_model::Control::kInsert;  ///< kFlip when a flip preceded it
  double beta_rad = 0.0;               ///< deflection drawn for this insertion [rad]
  double sigma_rad = 0.0;              ///< std. dev. it was drawn with [rad]
  std::uint64_t draw_index = 0;        ///< index of the draw in the seed's stream (0 = first)
};

/// Contact of the tip with an expanded obstacle or the workspace boundary.
struct NeedleContact {
  /// kFree: no contact; kObstacle: touched `obstacle`; kLeftWorkspace: reached the boundary.
  needle_model::ArcOutcome outcome = needle_model::ArcOutcome::kFree;
  std::string obstacle;        ///< name of the obstacle touched ("" unless kObstacle)
  double length_m = 0.0;       ///< inserted length at the contact [m]
  needle_model::TipPose pose;  ///< tip pose at the contact [m, rad]
  explicit operator bool() const { return outcome != needle_model::ArcOutcome::kFree; }
  /// "obstacle 'NAME' at (x, y) m", "left the workspace at (x, y) m" or "no contact".
  std::string toString() const;
};

/// What an advanceTo / retractTo / insertTo call did.
enum class MotionOutcome {
  kMoved,    ///< moved to the requested length
  kContact,  ///< moved, and stopped at a contact before the requested length
  kRefused,  ///< refused; nothing changed
};

/// Outcome of a motion with a one-line message; true only for kMoved (the
/// shared Status shape of status.h).
class MotionStatus : public Status<MotionOutcome, MotionOutcome::kMoved> {
public:
  using Status::Status;
  MotionOutcome outcome() const { return code(); }
};

/// One line of the needle's journal: every command (accepted or refused), every drawn
/// deflection and every contact.
struct NeedleJournalEntry {
  std::uint64_t sequence = 0;  ///< 0, 1, 2, ... in the order written
  /// "set_entry", "reseed", "flip", "insert" (beginInsertion: the deflection drawn), "advance",
  /// "retract", "contact", "contact_cleared".
  std::string event;
  bool accepted = true;
  std::string message;
  double length_m = 0.0;         ///< inserted length after the event [m]
  needle_model::TipPose tip;     ///< tip() after the event [m, rad]
  double beta_rad = 0.0;         ///< "insert": the deflection drawn [rad]
  double sigma_rad = 0.0;        ///< "insert": its standard deviation [rad]
  std::int64_t draw_index = -1;  ///< "insert": index in the seed's stream; -1 otherwise
};

/// The steerable needle in its workspace. State: entry pose, bevel, the inserted path (one
/// segment per insertion command), whether a flip is pending and whether the tip is in contact.
/// Every refusal leaves the state unchanged.
///
/// Deflections: each beginInsertion() draws z ~ N(0, 1) from std::mt19937_64(seed) by the
/// Box-Muller transform of two engine outputs (draw k uses outputs 2k and 2k + 1, whatever the
/// sigmas), so the stream is reproducible on every platform, and beta = sigma z with sigma_r if
/// flip() was called since the last insertion (or the entry), else sigma_i.
class SteerableNeedle {
public:
  /// @param[in] workspace rectangle, obstacles (expanded by their clearance; the target is not
  ///            used) and the radius of curvature r
  /// @param[in] config entry line, heights, sigmas, seed
  /// @param[in] entry the initial entry pose (must pass checkEntry)
  /// Throws std::invalid_argument for negative or non-finite sigmas, an empty height range, a
  /// non-finite start_x, a bad entry, or whatever PlanarWorld refuses.
  SteerableNeedle(const needle_model::PlanarWorkspace& workspace,
                  const SteerableNeedleConfig& config, const EntryPose& entry);

  /// Why `entry` cannot be set now: the needle is in tissue (inserted length > 0), the angle is
  /// outside [-pi/2, pi/2], the height outside [min_height_m, max_height_m], or a value is not
  /// finite. Accepted otherwise. Changes nothing.
  CommandStatus checkEntry(const EntryPose& entry) const;
  /// Places the needle guide: entry pose and bevel, empty path, no contact, no pending flip.
  CommandStatus setEntry(const EntryPose& entry);
  /// Restarts the deflection stream from `seed` (draw 0 next), journaled as "reseed": lets a
  /// series of trials give every trial its own reproducible stream. Never refused.
  CommandStatus reseed(std::uint64_t seed);
  /// Rotates the needle by 180 degrees (bevel left <-> right) where it is; the next insertion's
  /// deflection uses sigma_r (two flips in a row still count as a direction change). Ends the
  /// open insertion, if any. Never refused.
  CommandStatus flip();

  /// Starts an insertion command at the current length: draws beta (journaled) and opens a new
  /// segment whose start is the tip turned by beta, with the current bevel. Refused while in
  /// contact. The tip orientation includes beta even before the segment grows.
  CommandStatus beginInsertion();
  /// Moves the tip of the open insertion to inserted length `length_m` (>= the current one)
  /// along its arc, checking contact over the newly travelled part with
  /// PlanarWorld::traceArc; on contact the tip stops at the contact point (kContact).
  /// Refused without an open insertion, in contact, for a non-finite or shorter length.
  MotionStatus advanceTo(double length_m);
  /// One whole insertion command: beginInsertion() then advanceTo(length_m) (refused, without
  /// drawing, if either would refuse).
  MotionStatus insertTo(double length_m);
  /// Pulls the tip back along its own path to `length_m` in [0, insertedLength_m()] (exact);
  /// segments beyond it are dropped and the open insertion ends; the contact is cleared when
  /// length_m is shorter than the contact length. At 0 the tip is back at the entry (position
  /// and angle); the bevel stays where it is, as retraction does not rotate the needle.
  MotionStatus retractTo(double length_m);

  /// Tip pose at inserted length `length_m` in [0, insertedLength_m()] along the current path,
  /// with the bevel that traced that point (the entry pose at 0). Throws std::out_of_range.
  needle_model::TipPose tipAt(double length_m) const;
  /// The current tip: the end of the path (the entry point and angle when empty, the deflected
  /// start of an open insertion that has not moved yet) with the current bevel.
  needle_model::TipPose tip() const;
  /// Points of the inserted needle from the entry to the tip, at most max_spacing_m (> 0)
  /// apart along the arcs [m].
  std::vector<geometry::Point2> pathPoints(double max_spacing_m) const;

  double insertedLength_m() const { return length_m_; }
  const EntryPose& entry() const { return entry_; }
  /// The entry point (start_x, height) [m].
  geometry::Point2 entryPoint() const;
  needle_model::Bevel bevel() const { return bevel_; }
  const std::vector<NeedleSegment>& segments() const { return segments_; }
  const NeedleContact& contact() const { return contact_; }
  bool inContact() const { return static_cast<bool>(contact_); }
  /// True between beginInsertion() and the next flip, retraction, entry or insertion.
  bool insertionOpen() const { return insertion_open_; }
  /// True if the next insertion follows a flip (its beta uses sigma_r).
  bool flipPending() const { return flip_pending_; }
  /// Deflections drawn so far (the next draw's stream index).
  std::uint64_t deflectionsDrawn() const { return draws_; }
  const SteerableNeedleConfig& config() const { return config_; }
  double radius_m() const { return radius_m_; }
  const needle_model::PlanarWorld& world() const { return *world_; }

  /// Everything the needle did, in order. `sink`, when set, also receives each entry as it is
  /// written (e.g. to persist it).
  const std::vector<NeedleJournalEntry>& journal() const { return journal_; }
  void setJournalSink(std::function<void(const NeedleJournalEntry&)> sink) {
    sink_ = std::move(sink);
  }

private:
  double drawStandardNormal();
  needle_model::TipPose segmentPose(const NeedleSegment& segment, double along_m) const;
  /// Appends a journal entry (with the deflection of `drawn`, if given) and passes it to sink_.
  void record(const std::string& event, bool accepted, const std::string& message,
              const NeedleSegment* drawn = nullptr);
  MotionStatus refuseMotion(const std::string& event, const std::string& reason);

  SteerableNeedleConfig config_;
  std::unique_ptr<needle_model::PlanarWorld> world_;
  double radius_m_ = 0.0;
  std::mt19937_64 rng_;
  std::uint64_t draws_ = 0;

  EntryPose entry_;
  needle_model::Bevel bevel_ = needle_model::Bevel::kLeft;
  std::vector<NeedleSegment> segments_;
  double length_m_ = 0.0;
  bool insertion_open_ = false;
  bool flip_pending_ = false;
  NeedleContact contact_;

  std::vector<NeedleJournalEntry> journal_;
  std::function<void(const NeedleJournalEntry&)> sink_;
};

/// Writes needle journal entries as CSV lines, flushed after every line so that nothing is lost
/// if the process dies. Throws std::runtime_error if the file cannot be opened.
class NeedleJournalFile {
public:
  explicit NeedleJournalFile(const std::string& path);
  ~NeedleJournalFile();
  NeedleJournalFile(const NeedleJournalFile&) = delete;
  NeedleJournalFile& operator=(const NeedleJournalFile&) = delete;
  /// @param[in] time_s the writer's clock (e.g. the stage's simulated time) [s]
  void write(const NeedleJournalEntry& entry, double time_s);
  static const char* header();

private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace needle_guidance::robot
