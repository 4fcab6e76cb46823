// Needle insertion into 3-D tissue (dissertation 2.3.3-2.3.6 and 2.4, in 3-D). The mesh never
// changes: the needle acts through constraints on tissue points embedded in tetrahedra
// (barycentric weights). A step is solved on the condensed system of those points
// (fem::CondensedCompliance: K is factored once, columns of K^-1 are formed only for the nodes
// of elements the needle passes and reused), so its cost grows with the number of needle
// points, not with the mesh.
//
// Interaction (the semantics of the 2-D tissue::NeedleInsertion):
//  * tip: before puncture the tip pins the surface point it touches; when the tip force
//    reaches the cutting force f_b the tissue is cut continuously: the tip's tissue point
//    advances along +x in the reference so that the tip force stays f_b. The tip holds the
//    tissue it cuts on the needle axis, so the cut track is the reference line at the needle's
//    lateral position; the lateral shear just ahead of the tip (F^-1 e_x of 2.3.4) is
//    neglected: evaluated on the tip's element it is dominated by the tip's own point load
//    and made the track wander with the mesh;
//  * shaft: the cut track's tissue points, one per track_spacing of cut, lie on the needle axis;
//    along it each is stuck (moves with the needle) or slips with the kinetic friction force
//    (per unit length times its share of shaft); a stuck point slips when holding it needs
//    more than the static friction (2.3.5). Points cut during insertion slip (the needle slides
//    past them at the insertion speed, above stick_velocity); when the needle reverses their
//    relative speed passes zero and they stick, then slip again one by one as the drag grows;
//  * seed release at the tip (2.4); retraction releases the track points the tip passes.
// Events (puncture, a new track point, stick to slip) are located where they happen within a
// step (bisection on the tip position), so the result does not depend on the step length.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/fem/condensed_compliance.h"
#include "needle_guidance/fem/fixed_point.h"
#include "needle_guidance/tissue_3d/scene_tissue_3d.h"
#include "needle_guidance/tissue_3d/tet_mesh_3d.h"

namespace needle_guidance::tissue_3d {

/// A tissue point embedded in a tetrahedron.
struct EmbeddedPoint {
  Vector3 reference_m = Vector3::Zero();
  int element = -1;
  Eigen::Vector4d weights = Eigen::Vector4d::Zero();
};

/// The FEM tissue: mesh, stiffness factored once, and a locator for embedded points.
class TissueModel3 {
public:
  /// Throws std::invalid_argument if the mesh is invalid or not held by fixed nodes.
  /// corotational: the elements follow their rotation (scene key `tissue.model`).
  TissueModel3(TetMesh3 mesh, const std::vector<fem::Material>& materials,
               bool corotational = false);
  ~TissueModel3();
  const TetMesh3& mesh() const { return mesh_; }
  bool corotational() const { return corotational_; }
  /// The corotational part of the displacement at displacement u (3 * node order) [m]:
  /// v = -K^-1 g(u), g(u) = sum over elements of R K_e (R^T x - X) - K_e u, the corotated
  /// element forces (fem::corotatedElement) less the linear ones. Equilibrium under nodal
  /// forces f is the fixed point u = K^-1 f + v(u), solved with the factored linear K as the
  /// preconditioner on the rotation residual (warped stiffness, Mueller et al. 2002). Empty for
  /// a linear model. Throws std::runtime_error if the result is not finite.
  Eigen::VectorXd corotationDisplacement(const Eigen::VectorXd& u) const;
  /// Elements inverted (det F <= 0) at the u of the last corotationDisplacement; they take the
  /// proper rotation nearest to F.
  int invertedElements() const { return inverted_elements_; }
  /// CPU time spent in corotationDisplacement so far [s].
  double corotationCpuSeconds() const { return corotation_cpu_s_; }
  fem::CondensedCompliance& compliance() { return *compliance_; }
  const fem::CondensedCompliance& compliance() const { return *compliance_; }
  /// The element containing p (reference), or nullopt outside the mesh.
  std::optional<EmbeddedPoint> locate(const Vector3& p) const;
  double assemblyCpuSeconds() const { return assembly_cpu_s_; }

private:
  TetMesh3 mesh_;
  std::unique_ptr<fem::CondensedCompliance> compliance_;
  struct Grid;
  std::unique_ptr<Grid> grid_;
  double assembly_cpu_s_ = 0.0;
  bool corotational_ = false;
  /// Per element, when corotational: shape gradients and the linear stiffness K_e.
  std::vector<Eigen::Matrix<double, 4, 3>> gradients_;
  std::vector<fem::ElementMatrix<3>> element_stiffness_;
  mutable double corotation_cpu_s_ = 0.0;
  mutable int inverted_elements_ = 0;
};

/// Figures of the last move, for reports.
struct InsertionInfo3 {
  double tip_force_N = 0.0;       ///< needle force on the tissue at the tip along +x
  double friction_force_N = 0.0;  ///< total shaft force on the tissue along +x
  int shaft_points = 0;
  int slipping = 0;
  int events = 0;              ///< located events in the last move
  int solves = 0;              ///< condensed solves in the last move
  int corotation_updates = 0;  ///< corotational fixed-point updates in the last move
};

class NeedleInsertion3 {
public:
  /// The needle moves along +x at lateral position (y, z); the tissue's entry face is x =
  /// entry_x_m; the tip goes no deeper than max_tip_x_m (the compliance columns along the
  /// needle line are solved up to there in one batch when the needle enters). Throws
  /// std::invalid_argument for invalid parameters.
  NeedleInsertion3(TissueModel3& model, const Needle3& needle, double entry_x_m,
                   double max_tip_x_m);

  /// Moves the tip to x = tip_x_m (forwards or back) at lateral position `lateral` (y, z),
  /// locating every event on the way. The lateral position may change only outside tissue.
  /// Returns false and leaves the state unchanged (why_not says why) for non-finite input, a
  /// lateral change in tissue, or a lateral position outside the tissue block's mesh.
  bool moveTo(const Eigen::Vector2d& lateral_m, double tip_x_m, std::string* why_not = nullptr);

  /// Releases a seed at the tip (2.4); its tissue point is the tip's. Refused outside tissue.
  std::optional<int> implantSeed(std::string* why_not = nullptr);
  /// A seed placed earlier (by another needle) at this tissue point (reference, in the mesh):
  /// it moves with the tissue like the seeds this needle releases. Returns its id.
  int addSeed(const Vector3& reference_m);
  /// Seed's tissue point (reference) and its current world position [m].
  const Vector3& seedReference(int seed) const;
  Vector3 seedWorld(int seed) const;
  int seedCount() const { return static_cast<int>(seeds_.size()); }

  bool inTissue() const { return in_tissue_; }
  bool punctured() const { return punctured_; }
  double tipX() const { return s_; }
  const Eigen::Vector2d& lateral() const { return lateral_; }
  /// Reference position of the tip's tissue point (when in tissue) [m].
  Vector3 tipReference() const { return tip_.reference_m; }
  /// Reference positions of the shaft's tissue points [m].
  std::vector<Vector3> shaftReference() const;
  const InsertionInfo3& lastMove() const { return info_; }
  /// Displacement of every mesh node now (one full solve) [m], Dim*node order.
  Eigen::VectorXd displacementField() const;
  /// World position of a reference point now (it must lie in the mesh) [m].
  Vector3 worldOf(const Vector3& reference_m) const;

private:
  struct ShaftPoint {
    EmbeddedPoint point;
    bool stuck = false;
    double offset_m = 0.0;   ///< world x - tip x while stuck
    double share_m = 0.0;    ///< length of shaft it stands for
    double world_x_m = 0.0;  ///< after the last committed solve
  };
  struct Solution {
    Eigen::VectorXd forces;        ///< per constraint point (shaft..., tip), xyz, on the tissue [N]
    Eigen::VectorXd displacement;  ///< the same points' displacements [m]
    double tip_force_N = 0.0;
  };
  /// Quasi-static solution with the tip at x = s and the tip's tissue point `tip` (nullptr:
  /// no tip constraint), the shaft in its current stick/slip state.
  Solution solveAt(double s, const EmbeddedPoint* tip) const;
  Eigen::Matrix3d block(const EmbeddedPoint& p, const EmbeddedPoint& q) const;
  void requireColumns(const EmbeddedPoint& p) const;
  void prefetchLine(const Eigen::Vector2d& lateral) const;
  /// Length cut beyond the current tip point for the tip at x = s (tip force then f_b).
  double cutLength(double s) const;
  EmbeddedPoint along(double cut_m) const;
  /// One segment of a move towards target without events inside; true when target is reached.
  bool insertSegment(double target);
  /// Cutting towards target, up to the next track point (true when target is reached).
  bool cutTo(double target);
  /// Largest excess of a stuck point's force over its static friction at tip x = s, with
  /// the cut solved there (-inf when no point is stuck) [N].
  double stuckExcess(double s) const;
  /// Tip x where a stuck point first slips on the way to target (target if none does).
  double firstSlip(double target) const;
  bool retractSegment(double target);
  void commit(double s, const EmbeddedPoint* tip);
  void addTrackPoint(const EmbeddedPoint& p);
  void releaseShaftPoint(std::size_t k);
  Vector3 nodeDisplacement(int node) const;
  /// The corotational part of the displacement at p (zero for a linear model) [m].
  Vector3 warpAt(const EmbeddedPoint& p) const;
  /// Corotational model: one fixed-point update of the warp at the committed state (Anderson
  /// mixing over the updates since the constraints last changed, i.e. since `fresh`), which is
  /// then solved again; true when the update changed the warp by at most the convergence
  /// tolerance (always true for a linear model). Throws std::runtime_error if it does not
  /// converge.
  bool settleWarp(bool fresh);

  TissueModel3& model_;
  Needle3 needle_;
  double entry_x_m_;
  double max_tip_x_m_;
  Eigen::Vector2d lateral_ = Eigen::Vector2d::Zero();
  double s_ = 0.0;
  int direction_ = 1;
  bool in_tissue_ = false;
  bool punctured_ = false;
  bool tip_active_ = false;
  EmbeddedPoint tip_;
  EmbeddedPoint
      pending_track_;         ///< the next track point, added when the cut is one spacing past it
  double cut_total_m_ = 0.0;  ///< cut length along the track
  double next_event_cut_m_ = 0.0;
  Eigen::Vector3d cut_dir_ = Eigen::Vector3d::UnitX();
  std::vector<ShaftPoint> shaft_;
  Eigen::MatrixXd shaft_compliance_;  ///< condensed compliance among the shaft points [m/N]
  Solution committed_;
  std::vector<Vector3> seeds_;
  InsertionInfo3 info_;
  mutable int solves_ = 0;
  Eigen::VectorXd warp_;  ///< corotational part of the displacement (empty: none) [m]
  int warp_updates_ = 0;  ///< consecutive updates without convergence
  fem::AndersonAcceleration warp_mixer_;
};

}  // namespace needle_guidance::tissue_3d
