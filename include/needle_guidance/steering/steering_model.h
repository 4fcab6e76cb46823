// Steerable bevel-tip needle: the discrete MDP of dissertation 5.4.2 (state space, controls,
// transition stencils with discretised deflection, obstacles and target as absorbing states).
// Plain C++ and Eigen; no ROS. The solver is in value_iteration.h, the solved look-up table in
// policy_table.h.
//
// Frames and conventions: everything lives in the x-y plane of frame `scene`, insertion mostly
// along +x (the dissertation's z is our x, its y our y). The tip orientation theta is the angle
// of the tip tangent from +x, counter-clockwise [rad]. Bevel left (b = 0) traces the control
// circle counter-clockwise (theta grows), bevel right (b = 1) clockwise (5.4.2).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/needle_model/needle_2d.h"
#include "needle_guidance/scene/scene.h"

namespace needle_guidance::steering {

using geometry::Point2;

// The needle's vocabulary, from the needle model the MDP discretises.
using needle_model::advanceTip;
using needle_model::Bevel;
using needle_model::bevelFromString;
using needle_model::Control;
using needle_model::flipped;
using needle_model::TipPose;
using needle_model::toString;

/// How a transition's end point and deflection enter the MDP.
enum class TransitionModel : std::uint8_t {
  /// 5.4.2 exactly: the tip moves by the vector between rounded control-circle points; the
  /// deflection density is integrated over bins of the orientation step at their centres.
  kRounded = 0,
  /// Not in 5.4.2: the exact arc end from the grid point, its probability split bilinearly
  /// between the four surrounding grid points (only those outside obstacles; an end inside the
  /// target disc succeeds exactly), and deflection bins whose discrete variance equals sigma^2
  /// (the bins of a normal with a smaller sigma', so quantisation does not inflate the spread).
  kInterpolated = 1,
};
/// "rounded" | "interpolated".
std::string toString(TransitionModel model);
/// The inverse of toString(TransitionModel); nullopt for anything else.
std::optional<TransitionModel> transitionModelFromString(const std::string& text);

/// Discretisation and motion-uncertainty parameters (5.4.2).
struct SteeringParams {
  double grid_spacing_m = 1e-3;  ///< Delta, spacing of the position grid [m], > 0
  int orientations = 40;         ///< N_c, number of control-circle arcs; a multiple of 4
  /// s: the MDP tracks orientation in steps of alpha / s while each insertion still traces one
  /// arc of alpha = 2 pi / N_c (delta = 2 pi r / N_c). s = 1 is 5.4.2 exactly; s > 1 (our
  /// extension) quantises deflections finer, so the MDP's deflection variance approaches
  /// sigma^2, at s times the states. In [1, 64].
  int orientation_subdivision = 1;
  double radius_m = 0.05;         ///< r, radius of curvature of the needle path [m], > 0
  double sigma_insert_rad = 0.0;  ///< sigma_i, std. dev. of the deflection on insertion [rad]
  double sigma_flip_rad = 0.0;    ///< sigma_r, std. dev. of the deflection on a flip [rad]
  /// The discrete deflections cover +-m alpha with m the smallest count whose two tails
  /// (|beta| > (m + 1/2) alpha) hold less than this mass; the tails are folded into the end
  /// transitions (5.4.2: 1 %). In (0, 1).
  double tail_mass = 0.01;
  /// Collision checks follow each arc as a polyline whose chords lie at most this far inside
  /// the true arc [m], > 0.
  double arc_chord_tolerance_m = 1e-5;
  /// kRounded is 5.4.2 (and keeps its table hashes); kInterpolated splits probabilities.
  TransitionModel transition_model = TransitionModel::kRounded;
};

/// What the MDP needs from a scene: workspace rectangle, obstacles (expanded by their
/// clearance), one circular target and the parameters.
struct SteeringProblem {
  Point2 workspace_min = Point2::Zero();   ///< [m]
  Point2 workspace_max = Point2::Zero();   ///< [m]
  std::vector<scene::Obstacle> obstacles;  ///< polygons as given plus clearance_m [m]
  scene::Target target;                    ///< success region: the closed disc [m]
  SteeringParams params;
  /// Wanted mean |P_s error| (model_selection.h); 0 = params as given. Not part of the hash:
  /// it chooses the params, which are.
  double ps_tolerance = 0.0;
};

/// The steering problem of a scene: its workspace, obstacles, the target named target_name
/// (the first target when empty), r = needle.radius_of_curvature_m and the scene's steering
/// section. Throws std::invalid_argument if the scene has no steering section or no targets,
/// and std::out_of_range for an unknown target name.
SteeringProblem problemFromScene(const scene::Scene& scene, const std::string& target_name = "");

/// 64-bit FNV-1a hash of everything the solved table depends on (geometry, target, parameters
/// and the discretisation's version). Not of the solver's epsilon.
std::uint64_t problemHash(const SteeringProblem& problem);

/// Flat index of a discrete state; also the index into value and policy arrays.
using StateId = std::int64_t;
/// The absorbing failure state (obstacle hit, workspace left) in transition lists.
constexpr StateId kFailState = -1;
/// kInterpolated only: the exact end point of the arc lies in the target disc (success).
constexpr StateId kSuccessState = -2;

/// What a grid position is (5.4.2 "special cases").
enum class Cell : std::uint8_t {
  kFree = 0,      ///< an ordinary state: the solver chooses a control here
  kTarget = 1,    ///< inside the target disc: absorbing, P_s = 1
  kObstacle = 2,  ///< inside an expanded obstacle: absorbing, P_s = 0
};

/// The discrete state space s = {q, Theta, b} (5.4.2): grid point q = origin + (ix, iy) Delta
/// with ix in [0, nx), iy in [0, ny); orientation index k in [0, nc) meaning theta = k 2 pi / nc,
/// where nc = N_c s (N_c when orientation_subdivision s = 1, as in 5.4.2);
/// bevel b. The grid is aligned at workspace_min and has nx = floor(width / Delta) columns, so a
/// 10 cm workspace at Delta = 1 mm gives 100 x 100 positions and N = 2 * 100 * 100 * 40 =
/// 800,000 states at N_c = 40 (5.5). Flat layout: ((ix * ny + iy) * 2 + b) * N_c + k, so the
/// 2 N_c states of one position are contiguous and a column of positions is contiguous.
struct GridSpec {
  Point2 origin = Point2::Zero();  ///< position of grid point (0, 0) [m]
  double spacing_m = 0.0;          ///< Delta [m]
  int nx = 0;                      ///< columns (along x)
  int ny = 0;                      ///< rows (along y)
  int nc = 0;                      ///< orientations tracked: N_c s (N_c in 5.4.2)

  std::int64_t numPositions() const { return static_cast<std::int64_t>(nx) * ny; }
  std::int64_t numStates() const { return numPositions() * 2 * nc; }
  /// Orientation quantum 2 pi / nc [rad]: alpha = 2 pi / N_c when s = 1.
  double alphaRad() const;
  /// Position index of grid point (ix, iy).
  std::int64_t position(int ix, int iy) const { return static_cast<std::int64_t>(ix) * ny + iy; }
  /// Flat state index; arguments must be in range (not checked).
  StateId state(int ix, int iy, int k, Bevel b) const {
    return (position(ix, iy) * 2 + static_cast<int>(b)) * nc + k;
  }
  /// Grid point of a state [m].
  Point2 point(int ix, int iy) const;
  /// Decodes a flat index (must be in [0, numStates())).
  void decode(StateId s, int& ix, int& iy, int& k, Bevel& b) const;
  /// The state nearest to a continuous pose (5.4.2: q rounded to the grid, Theta the control-
  /// circle point whose tangent is closest to theta). Every pose of the workspace has one: a
  /// pose beyond the last column or row (the workspace extends less than one spacing past it)
  /// takes that column or row. -1 for a pose more than half a spacing before the first column
  /// or row, or a spacing past the last, or not finite. O(1).
  StateId nearestState(const TipPose& pose) const;
  /// The continuous pose a state stands for.
  TipPose pose(StateId s) const;
};

/// One outcome of a control: the next state (kFailState for failure) and its probability.
struct Transition {
  StateId next = kFailState;
  double probability = 0.0;
};

/// One stencil entry: the outcome of one discrete deflection, the same at every position.
/// Used by the solver's inner loop; exposed so tests can check the discretisation.
struct StencilEntry {
  std::int32_t offset = 0;   ///< next state's flat index minus this state's
  float probability = 0.0f;  ///< P(deflection)
  std::uint16_t arc = 0;     ///< traced arc id: bevel * nc + start orientation
  std::int16_t dy = 0;       ///< row displacement of the next position [grid steps]
  /// kInterpolated: which of the four corners of the end point's grid cell (0..3) this entry
  /// is; the four entries of one deflection are contiguous. 0 for kRounded.
  std::uint8_t corner = 0;
  std::int32_t dpos = 0;  ///< next position index minus this position index
};

/// The discretised MDP of 5.4.2 for one problem: grid, cells (free, target, obstacle),
/// transition stencils shared by all positions, and per position a bitmask of the arcs that
/// stay inside the workspace and the grid and cross no expanded-obstacle edge.
///
/// Transitions (5.4.2, figure 5.3): from a state (q, k, b) the control picks the bevel b' (b
/// for insert, the other for flip; a flip is the 180-degree rotation of the control-circle
/// point, i.e. the same orientation traced on the opposite circle), a deflection d alpha is
/// drawn (d in -m..m, figure 5.4; for sigma so large that 2m + 1 > N_c, the normal is wrapped
/// onto all N_c orientations), and the tip traces one control-circle arc from orientation
/// o = k + d with bevel b'. The position moves by the vector between the two rounded control-
/// circle points of that arc, so orientation is exact and position error bounded (5.4.2); the
/// next orientation is o + 1 (left) or o - 1 (right). With orientation_subdivision s > 1 (not
/// in 5.4.2) the orientation index counts alpha / s: deflections are integrated into alpha / s
/// bins, the rounded control-circle points are the N_c s points of that spacing, and an arc
/// still turns alpha, from o to o + s (left) or o - s (right). The arc fails when the true arc from
/// q leaves the workspace, crosses an expanded obstacle's boundary, or its rounded end point is off
/// the grid. A grid point inside an expanded obstacle is an obstacle cell even if it is in the
/// target too (the needle cannot get there without crossing the obstacle edge). Success is judged
/// at decision points, as the tip is imaged every delta (5.3): an arc that passes through the
/// target but ends outside it does not count.
class SteeringModel {
public:
  /// Builds the discretisation. Throws std::invalid_argument naming the value for: N_c not a
  /// multiple of 4 or < 4, non-positive Delta or r, negative or non-finite sigma, tail_mass or
  /// arc_chord_tolerance_m out of range, an empty workspace or one narrower than Delta, more
  /// than 2^31 states, a negative clearance or target radius. A target with no free grid point
  /// (e.g. inside an obstacle) is not refused: P_s is then 0 everywhere, and diagnostics()
  /// says so.
  /// @param[in] threads worker threads for the collision pre-computation (>= 1)
  explicit SteeringModel(SteeringProblem problem, int threads = 2);

  const SteeringProblem& problem() const { return problem_; }
  const SteeringParams& params() const { return problem_.params; }
  const GridSpec& grid() const { return grid_; }
  /// problemHash(problem()).
  std::uint64_t hash() const { return hash_; }
  /// delta = 2 pi r / N_c, the insertion distance of one step [m].
  double arcLength_m() const;
  std::int64_t numStates() const { return grid_.numStates(); }

  /// Expanded obstacles (counter-clockwise) [m].
  const std::vector<geometry::Polygon>& expandedObstacles() const { return expanded_; }
  /// Cell of a position index.
  Cell cell(std::int64_t position) const {
    return static_cast<Cell>(cells_[static_cast<std::size_t>(position)]);
  }
  const std::vector<std::uint8_t>& cells() const { return cells_; }
  /// Number of grid positions inside the target that are not obstacles.
  std::int64_t targetCells() const { return target_cells_; }
  /// Human-readable warnings found while building (empty when none), e.g. an unreachable
  /// target.
  const std::vector<std::string>& diagnostics() const { return diagnostics_; }

  /// Probabilities of the discrete deflections d = first..first + size - 1 (in units of alpha)
  /// for a control (sum 1).
  const std::vector<double>& deflectionProbabilities(Control control) const {
    return deflection_p_[static_cast<int>(control)];
  }
  /// The first d of deflectionProbabilities(control).
  int firstDeflection(Control control) const { return first_d_[static_cast<int>(control)]; }

  /// Grid displacement (dx, dy) of arc id (bevel * nc + start orientation).
  std::pair<int, int> arcDisplacement(int arc) const {
    return {disp_x_[static_cast<std::size_t>(arc)], disp_y_[static_cast<std::size_t>(arc)]};
  }
  /// Stencil of (orientation k, bevel b, control u): entries [begin, end).
  const StencilEntry* stencilBegin(int k, Bevel b, Control u) const {
    return stencil_.data() + stencil_start_[stencilSlot(k, b, u)];
  }
  const StencilEntry* stencilEnd(int k, Bevel b, Control u) const {
    return stencil_.data() + stencil_start_[stencilSlot(k, b, u) + 1];
  }
  /// Most stencil entries of any control.
  int maxTransitions() const { return max_transitions_; }
  /// Largest |dy| of any stencil entry [grid steps].
  int maxRowReach() const { return max_row_reach_; }

  /// True if arc `arc` from position index `position` is collision-free (and ends on the grid).
  bool arcValid(std::int64_t position, int arc) const {
    return (valid_[static_cast<std::size_t>(position * words_ + arc / 64)] >> (arc % 64)) & 1u;
  }
  /// True if every arc from the position is valid and, for kInterpolated, every end point's
  /// four neighbours are free grid points and no end point lies in the target (the solver's fast
  /// path: the stencil applies unchanged).
  bool allArcsValid(std::int64_t position) const {
    return all_valid_[static_cast<std::size_t>(position)] != 0;
  }
  /// kInterpolated only: for arc `arc` from `position`, bits 0..3 = corner i of the end point's
  /// cell is a free grid point (its probability share is kept), bit 4 = the exact end point lies
  /// in the target disc (success).
  std::uint8_t endMask(std::int64_t position, int arc) const {
    return end_mask_[static_cast<std::size_t>(position * 2 * grid_.nc + arc)];
  }
  static constexpr std::uint8_t kEndInTarget = 16;
  TransitionModel transitionModel() const { return problem_.params.transition_model; }
  /// The standard deviation [rad] whose orientation-bin probabilities the model uses for a
  /// control: sigma itself for kRounded, sigma' (discrete variance = sigma^2) for kInterpolated.
  double binSigma(Control control) const { return bin_sigma_[static_cast<int>(control)]; }
  /// 64-bit words of arc validity per position.
  int validityWords() const { return words_; }
  const std::uint64_t* validityMask(std::int64_t position) const {
    return valid_.data() + position * words_;
  }

  /// The successors of a state under a control, one per discrete deflection (failures as
  /// kFailState). An absorbing state (target or obstacle cell) returns itself with probability
  /// 1. Throws std::out_of_range for an invalid state index.
  std::vector<Transition> successors(StateId s, Control control) const;
  /// successors() grouped by discrete deflection (group i = deflection firstDeflection + i):
  /// one transition per group for kRounded; for kInterpolated the corners that keep a share
  /// (renormalised to the deflection's probability), or kSuccessState / kFailState alone.
  std::vector<std::vector<Transition>> successorGroups(StateId s, Control control) const;

private:
  std::size_t stencilSlot(int k, Bevel b, Control u) const {
    return static_cast<std::size_t>((k * 2 + static_cast<int>(b)) * 2 + static_cast<int>(u));
  }
  void buildDeflections();
  void buildStencils();
  void buildInterpolatedStencils();
  /// The stencil loop both transition models share: for every orientation, bevel and control,
  /// add(k, b, traced bevel, arc, end orientation, bin probability) appends the entries of each
  /// deflection bin (at most entries_per_bin of them).
  template <typename AddBin>
  void fillStencils(int entries_per_bin, AddBin&& add);
  void buildCells();
  void buildValidity(int threads);
  /// endMask of arc `arc` from grid point (ix, iy), computed from the cells (kInterpolated).
  std::uint8_t endMask(int ix, int iy, int arc) const;

  SteeringProblem problem_;
  GridSpec grid_;
  std::uint64_t hash_ = 0;
  std::vector<geometry::Polygon> expanded_;
  std::vector<std::uint8_t> cells_;
  std::int64_t target_cells_ = 0;
  std::vector<std::string> diagnostics_;
  std::vector<double> deflection_p_[2];
  int first_d_[2] = {0, 0};
  std::vector<int> disp_x_, disp_y_;     // per arc id (kInterpolated: floor of the exact end)
  std::vector<double> frac_x_, frac_y_;  // kInterpolated: fraction of the exact end [grid steps]
  std::vector<StencilEntry> stencil_;
  std::vector<std::size_t> stencil_start_;
  int max_transitions_ = 0;
  int max_row_reach_ = 0;
  int words_ = 0;
  std::vector<std::uint64_t> valid_;
  std::vector<std::uint8_t> all_valid_;
  std::vector<std::uint8_t> end_mask_;  // kInterpolated: per (position, arc)
  double bin_sigma_[2] = {0.0, 0.0};
};

}  // namespace needle_guidance::steering
