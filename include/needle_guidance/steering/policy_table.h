// The DP look-up table of dissertation 5.4.3: P_s and the optimal control for every discrete
// state, O(1) control look-up for a continuous tip pose, the best start state on the entry line
// (5.5, figure 5.7), and a binary file tied to the problem's hash. Plain C++; no ROS.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/status.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance::steering {

/// The result of a control look-up (an expected failure comes back as a status, not a throw).
struct ControlLookup {
  enum class Status {
    kOk,           ///< control and P_s valid
    kOutsideGrid,  ///< the rounded tip position is off the grid (or the pose is not finite)
    kInTarget,     ///< the tip is in the target: stop inserting (P_s = 1)
    kInObstacle,   ///< the tip is in an expanded obstacle (P_s = 0)
  };
  Status status = Status::kOutsideGrid;
  Control control = Control::kInsert;   ///< optimal control (kInsert unless status is kOk)
  float probability_of_success = 0.0f;  ///< P_s of the rounded state, in [0, 1]
  StateId state = -1;                   ///< the rounded state, -1 when off the grid

  explicit operator bool() const { return status == Status::kOk; }
  /// E.g. "ok: flip, P_s = 0.734" or "outside grid".
  std::string toString() const;
};

/// Where start states may lie (5.5: the left edge, theta in [-90, 90] degrees, either bevel).
struct StartOptions {
  double start_x_m = 0.0;        ///< the entry line x = start_x_m [m] (rounded to a grid column)
  double min_height_m = -1e300;  ///< lowest y [m]
  double max_height_m = 1e300;   ///< highest y [m]
  double min_theta_rad = -1.5707963267948966;  ///< [rad], within (-pi, pi]
  double max_theta_rad = 1.5707963267948966;   ///< [rad]
};

/// The start options of a scene: x = steering.start_x_m, heights needle.min/max_height_m.
/// Throws std::invalid_argument if the scene has no steering section.
StartOptions startOptionsFromScene(const scene::Scene& scene);

/// One feasible start state and its P_s.
struct StartCandidate {
  TipPose pose;  ///< the grid state's pose (theta in (-pi, pi])
  StateId state = -1;
  float probability_of_success = 0.0f;
};

/// The best start state (figure 5.7): true when some start state has P_s > 0.
struct BestStart {
  bool found = false;
  StartCandidate best;  ///< the maximiser (first in bevel, height, angle order on ties)
  std::string message;  ///< why nothing was found, else empty

  explicit operator bool() const { return found; }
  std::string toString() const;
};

/// Status of PolicyTable::load (the shared Status shape, status.h).
enum class LoadCode {
  kOk,
  kCannotOpen,  ///< missing or unreadable file
  kCorrupt,     ///< not a table file, truncated, or its checksum does not match
  kMismatch,    ///< solved for another scene or other parameters (hash differs)
  kTooLoose,    ///< solved with a larger epsilon than requested
};
class LoadStatus : public Status<LoadCode, LoadCode::kOk> {
public:
  using Code = LoadCode;
  using Status::Status;
  LoadStatus() : Status(LoadCode::kCannotOpen, "not loaded yet") {}
  LoadStatus(const Status& s) : Status(s) {}  // NOLINT: from Status::success()
};

/// P_s (float) and the optimal control (one bit) for every state, plus what the look-up needs
/// (grid, cells). Produced by solveValueIteration() or PolicyTable::load().
class PolicyTable {
public:
  /// Assembles a table; throws std::invalid_argument if the sizes disagree with the grid.
  /// @param[in] control_bits bit s set = flip is optimal in state s
  PolicyTable(GridSpec grid, std::uint64_t problem_hash, std::vector<float> values,
              std::vector<std::uint64_t> control_bits, std::vector<std::uint8_t> cells,
              double epsilon, int sweeps, bool converged);

  const GridSpec& grid() const { return grid_; }
  std::uint64_t problemHash() const { return hash_; }
  /// Convergence threshold the table was solved to (max change per state per sweep).
  double epsilon() const { return epsilon_; }
  int sweeps() const { return sweeps_; }
  bool converged() const { return converged_; }

  /// P_s of a state (unchecked index).
  float value(StateId s) const { return values_[static_cast<std::size_t>(s)]; }
  /// Optimal control of a state (unchecked index).
  Control control(StateId s) const {
    return (bits_[static_cast<std::size_t>(s) >> 6] >> (s & 63)) & 1u ? Control::kFlip
                                                                      : Control::kInsert;
  }
  Cell cell(std::int64_t position) const {
    return static_cast<Cell>(cells_[static_cast<std::size_t>(position)]);
  }
  const std::vector<float>& values() const { return values_; }

  /// Optimal control and P_s for a continuous tip pose by rounding to the nearest state
  /// (5.4.2): O(1), no allocation, never throws.
  ControlLookup lookup(const TipPose& pose) const noexcept;

  /// All grid start states allowed by `options` (both bevels; column nearest start_x_m).
  /// Empty if that column is off the grid.
  std::vector<StartCandidate> startCandidates(const StartOptions& options) const;
  /// The start state with maximal P_s by a linear scan (5.5, figure 5.7).
  BestStart bestStart(const StartOptions& options) const;

  /// Writes the table: a header (magic, format version, problem hash, grid, epsilon, sweeps),
  /// the values, cells and control bits, and an FNV-1a checksum. Little-endian host layout.
  /// Throws std::runtime_error if the file cannot be written.
  void save(const std::string& path) const;
  /// Reads a table written by save() if, and only if, it was solved for expected_hash (see
  /// problemHash()) to an epsilon <= max_epsilon. Never throws for a bad file: the status says
  /// why it was refused.
  static std::optional<PolicyTable> load(const std::string& path, std::uint64_t expected_hash,
                                         LoadStatus& status, double max_epsilon = 1.0);
  /// The table's file name in a table directory: "<scene>_<16 hex digits of the hash>.table",
  /// shared by the node that solves and every reader.
  static std::string fileName(const std::string& scene_name, std::uint64_t problem_hash);

private:
  GridSpec grid_;
  std::uint64_t hash_ = 0;
  std::vector<float> values_;
  std::vector<std::uint64_t> bits_;
  std::vector<std::uint8_t> cells_;
  double epsilon_ = 0.0;
  int sweeps_ = 0;
  bool converged_ = false;
};

}  // namespace needle_guidance::steering
