// Needle insertion on a cut track embedded in a fixed simplex mesh, one implementation for 2-D
// (plane-strain triangles) and 3-D (tetrahedra); dissertation 2.3.3-2.3.6 and 2.4. The mesh never
// changes: the needle acts through constraints on tissue points embedded in elements
// (barycentric weights). A step is solved on the condensed system of those points
// (CondensedCompliance: K is factored once, columns of K^-1 are formed only for the nodes of
// elements the needle passes and reused), so its cost grows with the number of needle points,
// not with the mesh.
//
// The needle moves along +x at a lateral position (y in 2-D; y, z in 3-D). Interaction:
//  * tip: before puncture the tip pins the surface point it touches; when the tip force
//    reaches the cutting force f_b the tissue is cut continuously: the tip's tissue point
//    advances in the reference so that the tip force stays f_b. Which tissue it advances
//    through is the cut track model (EmbeddedNeedleParams::follow_tissue):
//    - rest_line: along +x, the reference line at the needle's lateral position (the tissue
//      ahead of the tip is taken where it was at rest);
//    - follow_tissue: the tip cuts the tissue that is now in front of it. At puncture and at
//      each new track point the tissue now on the needle axis one track spacing ahead,
//      X = p - u(X), is found by fixed-point iteration (to 1e-10 m), and the track heads there
//      until the next track point. u is the displacement averaged over the tip's cross-section
//      (a disc of the needle's radius about X, normal to the needle) under the shaft's axial
//      (friction) loads. The tip's own cutting load is left out: a tip of finite size pushes
//      the tissue it cuts symmetrically aside, while the point load's displacement next to it
//      is set by the element size and its lateral part by the mesh's asymmetry (it made the
//      track wander by up to 1 mm). The direction is found at located events only, so it does
//      not depend on the step length;
//  * shaft: the cut track's tissue points, one per track_spacing of cut. On the rest line the
//    needle holds them on its axis; on a followed track they are free sideways (the track
//    bends between them within an element, and a linear element cannot hold several
//    non-collinear points on one line without straining by the bend over the point spacing).
//    Along the needle each is stuck (moves with the needle) or slips with the kinetic friction
//    force (per unit length times its share of shaft); a stuck point slips when holding it
//    needs more than the static friction (2.3.5). Points cut during insertion slip (the needle
//    slides past them at the insertion speed, above stick_velocity); when the needle reverses
//    their relative speed passes zero and they stick, then slip again one by one as the drag
//    grows;
//  * seed release at the tip (2.4); retraction releases the track points the tip passes.
// Events (puncture, a new track point, stick to slip) are located where they happen within a
// step (with the other constraints fixed the forces are affine in the tip position; stick to
// slip by bisection with the cut solved at each depth), so the result does not depend on the
// step length.
#pragma once

#include <Eigen/Core>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "needle_guidance/fem/condensed_compliance.h"
#include "needle_guidance/fem/corotation.h"
#include "needle_guidance/fem/fixed_point.h"
#include "needle_guidance/fem/linear_elasticity.h"

namespace needle_guidance::fem {

/// A node and its weight in a load spread over several nodes.
struct NodeWeight {
  int node = -1;
  double weight = 0.0;
};

/// A tissue point embedded in a simplex.
template <int Dim>
struct EmbeddedPoint {
  Point<Dim> reference_m = Point<Dim>::Zero();
  int element = -1;
  Eigen::Matrix<double, Dim + 1, 1> weights = Eigen::Matrix<double, Dim + 1, 1>::Zero();
  /// The nodes a force at the point acts on and its displacement is read from, weights summing
  /// to 1 (EmbeddingTissue::locateSection): the needle's cross-section about the point. Empty:
  /// the point itself (the element's corners with the barycentric weights).
  std::vector<NodeWeight> section;
};

/// The linear tissue a needle is embedded in: the mesh (owned by the caller, who keeps it alive
/// and unchanged), its stiffness factored once (corotational tissue: again when a needle
/// re-warps it), and a uniform-grid locator of embedded points.
template <int Dim>
class EmbeddingTissue {
public:
  /// node_fixed: per node, 1 if held fixed. thickness_m: out-of-plane thickness in 2-D (plane
  /// strain; forces are per that thickness), 1 in 3-D. corotational: the elements follow their
  /// rotation (CorotationalForces). Throws std::invalid_argument if the mesh is invalid or not
  /// held by fixed nodes.
  EmbeddingTissue(const SimplexMesh<Dim>& mesh, const std::vector<char>& node_fixed,
                  const std::vector<Material>& materials, double thickness_m = 1.0,
                  bool corotational = false);
  ~EmbeddingTissue();
  EmbeddingTissue(const EmbeddingTissue&) = delete;
  EmbeddingTissue& operator=(const EmbeddingTissue&) = delete;

  const SimplexMesh<Dim>& mesh() const { return *mesh_; }
  /// The compliance and its cache of columns (filled as needles need them; thread-safe).
  CondensedCompliance& compliance() const { return *compliance_; }
  /// The element containing p (reference), or nullopt outside the mesh.
  std::optional<EmbeddedPoint<Dim>> locate(const Point<Dim>& p) const;
  /// The needle's cross-section at p: locate(p) with its section filled, a disc of radius_m
  /// about p normal to +x (in 2-D the segment across the needle), sampled at equal-area points
  /// no farther apart than half the size of the element at p (7 to 256 samples in 3-D, 3 to
  /// 64 in 2-D); the samples' barycentric weights, averaged, spread a force
  /// over the tissue under the disc and average the displacement over it. A point force in
  /// elastic tissue displaces its own element without bound as the mesh is refined (~ 1/r in
  /// 3-D, ~ log r in 2-D); over the disc the answer converges with the mesh. Samples outside
  /// the mesh are left out. radius_m = 0: the point (empty section). nullopt if p is outside.
  std::optional<EmbeddedPoint<Dim>> locateSection(const Point<Dim>& p, double radius_m) const;
  /// True when every node of the element is fixed (rigid tissue: nothing there can deform).
  bool rigidElement(int element) const;
  double assemblyCpuSeconds() const { return assembly_cpu_s_; }

  bool corotational() const { return corotation_ != nullptr; }
  /// The corotational part of the displacement at displacement u (Dim * node order) [m]:
  /// v = -K_0^-1 g(u), g the corotated element forces less K_0 u (CorotationalForces::
  /// correction), K_0 the factored reference stiffness: the linear K until warpReference, then
  /// the warped stiffness; solved in single precision (CondensedCompliance::
  /// solveSinglePrecision: to about 1e-7 relative, far below the warp's tolerances). Equilibrium
  /// under nodal forces f is the fixed point
  /// u = K_0^-1 f + v(u) (warped stiffness, Mueller et al. 2002). Empty for a linear tissue.
  /// Throws std::runtime_error if the result is not finite.
  Eigen::VectorXd corotationDisplacement(const Eigen::VectorXd& u) const;
  /// Elements inverted at the u of the last corotationDisplacement (they take the proper
  /// rotation nearest to F).
  int invertedElements() const { return inverted_elements_; }
  /// The largest angle between an element's rotation at the u of the last
  /// corotationDisplacement and its reference rotation [rad].
  double lastTurnRad() const { return last_turn_rad_; }
  /// Corotational tissue: re-factors the compliance with the warped stiffness at displacement u
  /// (the rotations at u become the reference; every cached column is dropped and
  /// referenceVersion() grows). The tissue's needles share the reference: a needle finding a
  /// new version rebuilds what it derived from the old one.
  void warpReference(const Eigen::VectorXd& u) const;
  int referenceVersion() const { return reference_version_; }
  /// CPU time spent in corotationDisplacement and warpReference so far [s].
  double corotationCpuSeconds() const { return corotation_cpu_s_; }

private:
  const SimplexMesh<Dim>* mesh_;
  std::vector<char> node_fixed_;
  std::unique_ptr<CondensedCompliance> compliance_;
  struct Grid;
  std::unique_ptr<Grid> grid_;
  double assembly_cpu_s_ = 0.0;
  std::unique_ptr<CorotationalForces<Dim>> corotation_;
  mutable double corotation_cpu_s_ = 0.0;
  mutable int inverted_elements_ = 0;
  mutable double last_turn_rad_ = 0.0;
  mutable int reference_version_ = 0;
};

/// The seeds' step-halving target: halving the simulation step moves no seed by more than this
/// [m]. The corotational warp's tolerances derive from it (docs/tissue_3d.md, "Settled to the
/// accuracy the seed needs").
constexpr double kSeedStepTolerance_m = 5e-6;

/// Interaction parameters of the embedded needle [SI].
struct EmbeddedNeedleParams {
  double cutting_force_N = 0.5;            ///< tip force at which the tissue is cut (2.3.4), >= 0
  double static_friction_N_per_m = 30.0;   ///< per unit length of shaft (2.3.5)
  double kinetic_friction_N_per_m = 20.0;  ///< per unit length of shaft, <= static
  double stick_velocity_m_s = 5e-4;        ///< the shaft slips while the needle slides faster
  double insertion_velocity_m_s = 5e-3;    ///< nominal insertion speed
  double track_spacing_m = 1e-3;           ///< spacing of the shaft's tissue points, > 0
  /// The tissue the tip cuts (see the file comment): false = rest_line, true = follow_tissue.
  bool follow_tissue = false;
  /// Radius of the needle's cross-section, > 0 on a followed track (its aim averages the
  /// tissue's displacement over it) or with section_load.
  double tip_radius_m = 6.35e-4;
  /// The needle's forces on the tissue: false = at its tissue points (point forces), true =
  /// spread over its cross-section about each (a disc of tip_radius_m normal to the needle,
  /// EmbeddingTissue::locateSection). A point force's displacement grows without bound as the
  /// elements at it shrink; over the disc it converges once they are well below the radius.
  bool section_load = false;
  /// Corotational tissue: the warp at each located event (the puncture, a track point, stick to
  /// slip, a move's end, a retraction's events) is settled until an update changes no node's
  /// warp by more than this, and a relocation ends once it moves its segment's end by at most
  /// this; the state a seed is released from is settled to kSeedStepTolerance_m / 50 whatever
  /// this is. The default, half the seeds' step-halving target, keeps a seed within about a
  /// twentieth of that target of the tightly settled insertion's; a user that needs a seed only
  /// to a coarser accuracy (the offset planner, to a fraction of its placement tolerance) may
  /// loosen it: the seed then moves by about a tenth of it, by up to two thirds where a point
  /// tip crushes a soft surface before the puncture (measured, docs/tissue_3d.md). > 0.
  double event_warp_tolerance_m = kSeedStepTolerance_m / 2.0;
};

/// Figures of the last move, for reports.
struct EmbeddedNeedleInfo {
  double tip_force_N = 0.0;       ///< needle force on the tissue at the tip along +x
  double friction_force_N = 0.0;  ///< total shaft force on the tissue along +x
  int shaft_points = 0;
  int slipping = 0;
  int events = 0;              ///< located events in the last move
  int solves = 0;              ///< condensed solves in the last move
  int corotation_updates = 0;  ///< corotational fixed-point updates in the last move
  int rewarps = 0;             ///< warped-stiffness refactorisations in the last move
  int relocations = 0;         ///< corotational: segments solved again on the warp of their events
  /// corotational: the largest move of a segment's end (tip position, tip's tissue point, cut
  /// length) by its last relocation [m]
  double relocation_m = 0.0;
  int aim_iterations = 0;  ///< follow_tissue: fixed-point iterations aiming the cut
  /// The move stopped where the tip's tissue point reached the stop (stopAtTissueX).
  bool stopped = false;
};

template <int Dim>
class EmbeddedNeedle {
public:
  using Lateral = Eigen::Matrix<double, Dim - 1, 1>;
  using Vector = Point<Dim>;

  /// The needle moves along +x; the tissue's entry face is x = entry_x_m; the tip goes no deeper
  /// than max_tip_x_m (the compliance columns along the needle line are solved up to there in
  /// one batch when the needle enters). The tissue must outlive the needle; copies share it.
  /// Throws std::invalid_argument for invalid parameters.
  EmbeddedNeedle(const EmbeddingTissue<Dim>& tissue, const EmbeddedNeedleParams& params,
                 double entry_x_m, double max_tip_x_m);

  /// From now on the needle moves in the tissue's linear model: its reference stiffness alone,
  /// without the corotational warp, on the factor and the compliance columns the corotational
  /// needles share (a linear estimate in corotational tissue at the cost of a linear
  /// insertion, nothing factored or solved twice). Valid while the reference is the linear
  /// stiffness (EmbeddingTissue::referenceVersion() 0); after a refactorisation moves refuse.
  void useLinearModel() { linear_model_ = true; }

  /// Moves the tip to x = tip_x_m (forwards or back) at the lateral position, locating every
  /// event on the way. The lateral position may change only outside tissue. Returns false and
  /// leaves the state unchanged (why_not says why) for non-finite input, a lateral change in
  /// tissue, a lateral position outside the mesh, or re-insertion before the needle left.
  bool moveTo(const Lateral& lateral_m, double tip_x_m, std::string* why_not = nullptr);
  /// moveTo for an insertion that goes on from tip_x_m: every event on the way is located on
  /// its own settled warp as in moveTo, but the warp at the end is not settled (in corotational
  /// tissue; elsewhere this is moveTo). The end is a transit state: a start for the next move,
  /// whose events do not depend on it (each track point fixes the tip's tissue point afresh),
  /// not an equilibrium to read; its tip's tissue point holds to about the warp's first change
  /// there. A retraction is settled as in moveTo.
  bool passTo(const Lateral& lateral_m, double tip_x_m, std::string* why_not = nullptr);
  /// From now on (nullopt: no longer) an insertion stops where the tip's tissue point reaches
  /// reference x = x_m on its cut track: located within the move like a track point (the tip's
  /// tissue point there, the tip where its force reaches the cutting force), on the warp
  /// settled there; lastMove().stopped says so, and the tip stays short of the move's target.
  /// A move that starts with the tip's tissue point already at or beyond x_m stops at once.
  void stopAtTissueX(std::optional<double> x_m) { stop_tissue_x_ = x_m; }

  /// Releases a seed at the tip (2.4); its tissue point is the tip's. Refused outside tissue.
  /// Corotational tissue: the state it is released from is first settled to the warp's release
  /// tolerance (the events before it to the looser event tolerance); refused, with the state
  /// unchanged, if that warp does not converge.
  std::optional<int> implantSeed(std::string* why_not = nullptr);
  /// A seed placed earlier (by another needle) at this tissue point (reference, in the mesh):
  /// it moves with the tissue like the seeds this needle releases. Returns its id. Throws
  /// std::invalid_argument outside the mesh.
  int addSeed(const Vector& reference_m);
  /// Seed's tissue point (reference) and its current world position [m].
  const Vector& seedReference(int seed) const;
  Vector seedWorld(int seed) const;
  int seedCount() const { return static_cast<int>(seeds_.size()); }

  bool inTissue() const { return in_tissue_; }
  bool punctured() const { return punctured_; }
  double tipX() const { return s_; }
  const Lateral& lateral() const { return lateral_; }
  /// Reference position of the tip's tissue point (when in tissue) [m].
  Vector tipReference() const { return tip_.reference_m; }
  /// follow_tissue: the track's present direction in the reference (unit; +x on the rest line).
  const Vector& cutDirection() const { return cut_dir_; }
  /// Reference positions of the shaft's tissue points [m].
  std::vector<Vector> shaftReference() const;
  const EmbeddedNeedleInfo& lastMove() const { return info_; }
  /// Displacement of every mesh node now (one full solve) [m], Dim*node order.
  Eigen::VectorXd displacementField() const;
  /// World position of a reference point now (it must lie in the mesh) [m].
  Vector worldOf(const Vector& reference_m) const;
  /// Condensed solves since construction (a copy continues its original's count).
  long long totalSolves() const { return total_solves_; }

private:
  using Block = Eigen::Matrix<double, Dim, Dim>;
  using Point_ = EmbeddedPoint<Dim>;
  struct ShaftPoint {
    Point_ point;
    bool stuck = false;
    double offset_m = 0.0;   ///< world x - tip x while stuck
    double share_m = 0.0;    ///< length of shaft it stands for
    double world_x_m = 0.0;  ///< after the last committed solve
    bool held = true;        ///< held on the needle axis sideways
  };
  struct Solution {
    Eigen::VectorXd forces;        ///< per constraint point (shaft..., tip), on the tissue [N]
    Eigen::VectorXd displacement;  ///< the same points' displacements [m]
    double tip_force_N = 0.0;
  };
  /// Quasi-static solution with the tip at x = s and the tip's tissue point `tip` (nullptr:
  /// no tip constraint), the shaft in its current stick/slip state. tip_axial_free: the tip
  /// holds its tissue point on the needle axis but pushes it with no force along it.
  Solution solveAt(double s, const Point_* tip, bool tip_axial_free = false) const;
  Block block(const Point_& p, const Point_& q) const;
  /// The needle's tissue point at reference x with its cross-section (the element's corners for
  /// a point needle), or nullopt outside the mesh.
  std::optional<Point_> constraintPoint(const Vector& x) const;
  /// The tissue point at reference x with the section of radius_m about it (the element's
  /// corners at radius 0 or where every sample left the mesh), or nullopt outside the mesh.
  std::optional<Point_> sectionPoint(const Vector& x, double radius_m) const;
  void requireColumns(const Point_& p) const;
  /// end_x_m: the last x to prefetch (default: beyond the deepest tip position).
  void prefetchLine(const Lateral& lateral, std::optional<double> end_x_m = std::nullopt) const;
  Vector onLine(double x) const;
  /// Length cut beyond the current tip point for the tip at x = s (tip force then f_b).
  double cutLength(double s) const;
  Point_ along(double cut_m) const;
  /// One segment of a move towards target without events inside; true when target is reached.
  bool insertSegment(double target);
  /// The tip x in [s_, target] where, with the tip's tissue point held at p, the tip force
  /// reaches f_b (target if it does not). While a segment is located, that state is committed
  /// and settled with the event (settleBeforeEvent), and the tip x returned is where the settled
  /// warp puts it.
  double heldTipX(const Point_& p, double target);
  /// Cutting towards target, up to the next track point (true when target is reached).
  bool cutTo(double target);
  /// Largest excess of a stuck point's force over its static friction at tip x = s, with
  /// the cut solved there (-inf when no point is stuck) [N].
  double stuckExcess(double s) const;
  /// Tip x where a stuck point first slips on the way to target (target if none does).
  double firstSlip(double target) const;
  bool retractSegment(double target);
  /// Corotational insertion: the first guess of the warp at tip x = s, extended linearly in s
  /// from the warps settled at the last two ends of segments (events or move ends) on the current
  /// reference; nothing changes without two such warps. The converged answer does not depend on
  /// it; a close guess saves updates and relocations.
  void predictWarp(double s);
  /// Keeps the settled warp of the committed state (a segment's end) for predictWarp.
  void recordWarp();
  /// settleWarp until the warp has converged to tol_m at the committed state.
  void settle(double tol_m);
  /// While a segment is located (consistentSegment): the warp settled at the committed state,
  /// the one just before an event, kept in event_warp_; in a segment's first round from the
  /// guess of predictWarp, in a relocation not at all when the state repeats the end the last
  /// round settled at (within the event tolerance: that warp stands). tip_bracket: the event's
  /// tip holds its tissue point (a puncture, a track point) and its force reaches f_b between
  /// these tip x; the tip x is located again on each update of the warp, so the settle and the
  /// event's location converge together (end_before_event_ is where the warp was settled).
  void settleBeforeEvent(std::optional<std::pair<double, double>> tip_bracket = std::nullopt);
  /// One segment of a move towards target (insertSegment or retractSegment) with the warp
  /// settled at its end; true when target is reached. Corotational insertion: the segment is
  /// solved again from its start on the warp settled just before its event (or at its end)
  /// until its end (tip position, tip's tissue point and cut length) repeats to within the
  /// warp's tolerance or once (kMaxRelocations), so the event and the cut are located on the
  /// warp where they happen. A relocation whose end repeats the one the last round settled at
  /// keeps that warp without settling it again.
  bool consistentSegment(double target);
  /// Back to an earlier state of this needle, keeping the counts of the move; u: that state's
  /// displacement, to express its warp on the tissue's reference if that changed since.
  void restoreState(const EmbeddedNeedle& from, const Eigen::VectorXd* u);
  void commit(double s, const Point_* tip);
  void addTrackPoint(const Point_& p);
  void releaseShaftPoint(std::size_t k);
  /// Displacement of a node under the needle's forces (per constraint point: shaft..., tip) [m].
  Vector nodeDisplacement(int node, const Eigen::VectorXd& forces) const;
  /// follow_tissue: the displacement under those forces averaged over the tip's cross-section
  /// centred at the reference point x [m].
  Vector crossSectionDisplacement(const Vector& x, const Eigen::VectorXd& forces) const;
  /// Sets the cut direction at the committed state (follow_tissue; +x otherwise). Throws
  /// std::runtime_error if the aim does not converge or leaves the mesh.
  void aimCut();
  /// The corotational part of the displacement at p (zero for a linear tissue) [m].
  Vector warpAt(const Point_& p) const;
  /// Corotational tissue: one fixed-point update of the warp at the committed state (Anderson
  /// mixing over the updates of this move), which is then solved again; true when the update
  /// changed the warp by at most tol_m (always true for a linear tissue).
  /// When the updates converge too slowly the tissue's reference stiffness is re-warped at the
  /// current displacement (rewarp). Throws std::runtime_error if it does not converge.
  bool settleWarp(double tol_m);
  /// True when the warp's last changes predict more updates to convergence to tol_m than a
  /// rewarp is worth.
  bool slowWarp(double tol_m) const;
  /// Re-factors the tissue's warped stiffness at displacement u (the current state) and
  /// expresses the state on it: u = G f + warp with the new compliance G.
  void rewarp(const Eigen::VectorXd& u);
  /// The warp iteration starts afresh: no updates counted, no mixer history, no changes.
  void restartWarpIteration();
  /// Sets the warp so that the needle's state, solved on the current compliance, has the tissue
  /// displacement u (u = G f + warp); the caller commits the state.
  void holdDisplacement(const Eigen::VectorXd& u);
  /// Rebuilds what the needle derived from the tissue's compliance (the columns along its line
  /// and the shaft's condensed compliance) after the reference changed.
  void adoptReference();
  bool enter(const Lateral& lateral, std::string* why_not);

  const EmbeddingTissue<Dim>* tissue_;
  EmbeddedNeedleParams params_;
  double entry_x_m_;
  double max_tip_x_m_;
  Lateral lateral_ = Lateral::Zero();
  double s_ = 0.0;
  int direction_ = 1;
  bool in_tissue_ = false;
  bool punctured_ = false;
  bool tip_active_ = false;
  Point_ tip_;
  Vector cut_dir_ = Vector::UnitX();  ///< direction of the cut in the reference (unit)
  Point_ pending_track_;      ///< the next track point, added when the cut is one spacing past it
  double cut_total_m_ = 0.0;  ///< cut length along the track
  double next_event_cut_m_ = 0.0;
  std::vector<ShaftPoint> shaft_;
  Eigen::MatrixXd shaft_compliance_;  ///< condensed compliance among the shaft points [m/N]
  Solution committed_;
  std::vector<Vector> seeds_;
  EmbeddedNeedleInfo info_;
  mutable int solves_ = 0;
  mutable long long total_solves_ = 0;
  Eigen::VectorXd warp_;  ///< corotational part of the displacement (empty: none) [m]
  int warp_updates_ = 0;  ///< consecutive updates without convergence
  AndersonAcceleration warp_mixer_;
  std::vector<double> warp_changes_;     ///< changes of the updates since the last reference change
  int reference_version_ = 0;            ///< the tissue's reference the compliance data came from
  bool locating_ = false;                ///< consistentSegment is locating a segment
  bool transit_ = false;                 ///< passTo: the move's end is not settled
  std::optional<double> stop_tissue_x_;  ///< stopAtTissueX [m]
  /// The stop, once punctured: the cut from the tip's tissue point to it along the track [m].
  std::optional<double> cutToStop() const;
  Eigen::VectorXd event_warp_;       ///< the warp settled just before the segment's event
  bool predict_event_warp_ = false;  ///< settleBeforeEvent starts from predictWarp
  using SegmentEnd = Eigen::Matrix<double, Dim + 2, 1>;  ///< tip x, tip's tissue point, cut [m]
  /// The end of the committed state (s_, tip_'s reference point, cut_total_m_).
  SegmentEnd segmentEnd() const;
  /// A relocation whose end repeats the end the last round settled at (within the event tolerance).
  bool repeatsRelocatedEnd(const SegmentEnd& end) const;
  /// A relocation: the end located by the last round before its warp was settled there (empty
  /// in a segment's first round), and the end of this round before its event.
  std::optional<SegmentEnd> relocated_from_;
  SegmentEnd end_before_event_ = SegmentEnd::Zero();
  bool settle_skipped_ = false;  ///< the relocated end repeated: its warp was not settled again
  /// The warps settled at the last two segment ends of the insertion (oldest first) and their
  /// tip x [m], on the reference warp_history_version_.
  std::vector<std::pair<double, Eigen::VectorXd>> warp_history_;
  int warp_history_version_ = -1;

  /// The displacements of states kept to fall back on (a settle or a relocation that does not
  /// converge) are formed only when needed: on the fall-back, or just before a refactorisation
  /// replaces the factor they are expressed on (rewarp runs these first). A solve per event and
  /// per relocation is saved on the common path. Held by the needle that iterates, never copied.
  class KeptFields {
  public:
    KeptFields() = default;
    KeptFields(const KeptFields&) {}
    KeptFields& operator=(const KeptFields&) { return *this; }
    /// Registers form until the returned guard goes out of scope.
    struct Guard {
      KeptFields* owner;
      ~Guard() { owner->form_.pop_back(); }
    };
    [[nodiscard]] Guard keep(std::function<void()> form) {
      form_.push_back(std::move(form));
      return Guard{this};
    }
    /// Forms every registered displacement not formed yet (on the current factor).
    void formAll() const {
      for (const auto& f : form_) {
        f();
      }
    }

  private:
    std::vector<std::function<void()>> form_;
  };
  KeptFields kept_fields_;
  /// A copy of the needle to fall back on (restoreState) with its displacement, formed only when
  /// needed: on the fall-back, or first thing in a refactorisation while it is kept.
  struct Fallback {
    std::unique_ptr<EmbeddedNeedle> state;
    Eigen::VectorXd u;
    void take(const EmbeddedNeedle& needle) {
      state = std::make_unique<EmbeddedNeedle>(needle);
      u.resize(0);
    }
    void form() {
      if (state && u.size() == 0) {
        u = state->displacementField();
      }
    }
  };
  /// Restores the needle to fallback's state (its displacement formed now if it was not).
  void restoreFallback(Fallback& fallback);
  bool linear_model_ = false;  ///< useLinearModel: the warp is left out
  /// Corotational tissue seen as such: the warp is iterated (not in the linear model).
  bool warped() const { return tissue_->corotational() && !linear_model_; }
  /// The displacement with these needle forces and this warp on the current factor (one solve).
  Eigen::VectorXd displacementField(const Eigen::VectorXd& forces,
                                    const Eigen::VectorXd& warp) const;
};

}  // namespace needle_guidance::fem
