// Needle–tissue interaction (dissertation 2.3.3–2.3.6) and seeds (2.4): the needle is implicit
// (constraints and forces, no needle mesh). A node is kept at the tip; when the tip force exceeds
// the cutting force the tip advances in the reference mesh and nodes are promoted to the shaft
// by the distance rule of 2.3.4; shaft nodes lie on the needle axis; stick–slip friction acts
// along the shaft (2.3.5); retraction releases shaft nodes (2.3.6).
#pragma once

#include <Eigen/Core>
#include <array>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/tissue/fem_model.h"
#include "needle_guidance/tissue/integrator.h"

namespace needle_guidance::tissue {

/// Needle–tissue interaction parameters (SI). See scene::Needle.
struct NeedleParams {
  double cutting_force_N = 0.2;  ///< f_b: force that cuts cut_length_m of tissue (2.3.4) [N]
  double cut_length_m = 5e-4;    ///< b [m], > 0
  /// f_smax per unit length of shaft (2.3.5): a stuck node slips when holding it needs more than
  /// this times its share of the shaft (half the distance to each shaft neighbour) [N/m].
  double static_friction_N_per_m = 30.0;
  double kinetic_friction_N_per_m = 20.0;  ///< f_k per unit length of shaft [N/m]
  double stick_velocity_m_s = 5e-4;        ///< v_s: a slipping node sticks again below this [m/s]
  /// Bound on tip advances in one step; a step that needs more is refused (state unchanged):
  /// with event location it must cover step length / cut_length_m cuts.
  int max_cuts_per_step = 64;
  int max_friction_iterations = 8;  ///< bound on stick/slip re-solves in one step (dynamic models)
  /// Bound on stick–slip transitions and shaft releases located in one step (quasi-static
  /// model); a step that needs more is refused, state unchanged.
  int max_events_per_step = 4096;
  /// Node moves never make a triangle smaller than this fraction of its original area
  /// (prevents figure 2.9's inverted elements).
  double min_area_fraction = 0.05;
  /// Tip radius [m]. 0: the dissertation's point tip (one tip node), whose cutting force makes
  /// the tip displacement grow like log(1/h) as the mesh is refined (a 2-D point load). > 0:
  /// every free node within this radius ahead of the tip face moves with the tip node and the
  /// cutting force is their summed reaction, a finite-width load that converges with the mesh.
  double tip_radius_m = 0.0;
  /// Place cuts, stick–slip transitions and releases at the depth where they happen
  /// (interaction_events.h; quasi-static model), so the result does not depend on the step.
  /// false: they happen at the end of the step that crosses them (first order in the step; the
  /// dynamic models always do this).
  bool locate_events = true;
};

/// A seed implanted in the tissue: fixed in the reference mesh, tracked in its triangle by
/// barycentric coordinates (2.4).
struct Seed {
  int id = 0;
  Point2 p_ref = Point2::Zero();  ///< position in the reference mesh [m]
  int triangle = -1;
  std::array<double, 3> barycentric{1.0, 0.0, 0.0};
};

/// What happened in one step, for reports and markers.
struct InsertionStepInfo {
  int cuts = 0;         ///< tip advances this step
  int events = 0;       ///< events located in the step: cuts, stick–slip transitions, releases
  int promoted = 0;     ///< nodes added to the shaft
  int released = 0;     ///< nodes released by retraction
  int slipping = 0;     ///< shaft nodes slipping at the end of the step
  int relocations = 0;  ///< node moves shortened to avoid an inverted element
  double tip_force_N = 0.0;       ///< needle force on the tissue at the tip along +x [N]
  double friction_force_N = 0.0;  ///< total shaft friction force on the tissue along +x [N]
};

/// Needle insertion into a FEM tissue model. Frame scene: the needle moves along +x at height
/// y = needle_height; the tip is at x = tip_x. Owns nothing: the model and the integrator must
/// outlive it (the model's reference mesh is modified by cutting).
class NeedleInsertion {
public:
  /// @param[in] entry_nodes nodes of the free entry face x = bounds_min.x, where the needle
  ///            may enter
  /// @param[in] fixed_dofs the integrator's permanent fixed DOFs (never needle nodes)
  /// @param[in] bounds_min, bounds_max tissue bounding box, to validate commands [m]
  /// Throws std::invalid_argument for invalid parameters or an empty entry face.
  NeedleInsertion(FemModel& model, Integrator& integrator, std::vector<int> entry_nodes,
                  const std::vector<int>& fixed_dofs, const Point2& bounds_min,
                  const Point2& bounds_max, const NeedleParams& params);

  /// A copy of `other`'s state (needle, shaft, friction, seeds) acting on `model` and
  /// `integrator`, copies of other's.
  NeedleInsertion(const NeedleInsertion& other, FemModel& model, Integrator& integrator);
  NeedleInsertion(const NeedleInsertion&) = delete;
  NeedleInsertion& operator=(const NeedleInsertion&) = delete;

  /// Advances by dt_s with the needle at height needle_height_m and its tip at x = tip_x_m.
  /// The height may only change while the tip is outside the tissue. Refuses (status not ok,
  /// state unchanged) non-finite input, a height outside the tissue, a height change in tissue,
  /// a tip beyond the tissue, and dt_s <= 0.
  StepStatus step(double dt_s, double needle_height_m, double tip_x_m);

  /// Implants a seed at the needle tip (2.4). Refused when the needle is not in tissue.
  std::optional<int> implantSeed(std::string* why_not = nullptr);
  const std::vector<Seed>& seeds() const { return seeds_; }
  /// World position of a seed in the deformed tissue [m].
  Point2 seedPosition(const Seed& seed) const;

  /// Deformed position of every node [m].
  std::vector<Point2> deformedNodes() const;
  int tipNode() const { return tip_node_; }  ///< -1 when no tip node is kept
  /// Nodes that move rigidly with the tip node (empty for a point tip).
  const std::vector<int>& tipPatch() const { return tip_patch_; }
  const std::vector<int>& shaftNodes() const { return shaft_; }
  bool inTissue() const { return in_tissue_; }
  const InsertionStepInfo& lastStep() const { return info_; }
  double needleHeight() const { return height_m_; }
  double tipX() const { return tip_x_m_; }
  /// Reference-mesh position of the tip (p of 2.3.4) when a tip node is kept [m].
  std::optional<Point2> tipReference() const;

private:
  struct ShaftState {
    bool stuck = false;
    double offset_m = 0.0;   ///< world x - tip x while stuck (the node moves with the needle)
    double direction = 1.0;  ///< sign of the kinetic friction on the tissue while slipping
    /// Needle depth where the node last slipped: it may stick again only at a later event [m].
    double slip_x_m = -1e300;
  };
  /// The needle's constraints and loads at one depth and their reactions (2.3.3).
  struct Solved {
    double x_m = 0.0;  ///< tip x [m]
    Prescribed prescribed;
    Eigen::VectorXd reactions;
    Eigen::VectorXd u;
  };
  /// The step for a model that answers linearly (quasi-static): advances from from_x_m to
  /// tip_x_m_, placing every cut, stick–slip transition and release at the depth where it
  /// happens (interaction_events.h), so the result does not depend on the step.
  StepStatus solveLocated(double dt_s, double from_x_m, bool inserting, Solved& end);
  /// The step for a dynamic model: one solve at the step's end, then stick–slip re-solves and
  /// cuts at that depth (first order in the step).
  StepStatus solveFixed(double dt_s, bool inserting, Solved& end);
  /// Solves at depth x_m for the current constraints; dt_s for a dynamic model.
  StepStatus solveAt(double x_m, double dt_s, Solved& out);
  /// Fraction of the step a -> b where the tip cuts (events::kNever: it does not).
  double cutFraction(const Solved& a, const Solved& b) const;
  /// First event between solutions a and b as a fraction of the step (events::kNever: none).
  double firstEvent(const Solved& a, const Solved& b, bool inserting) const;
  /// Applies every event of the step a -> b at fraction s; false when the tip cannot cut
  /// (blocked for the rest of the step).
  void applyEvents(const Solved& a, const Solved& b, double s, bool inserting, bool& cut_blocked,
                   int& cuts);
  /// Slipping nodes (not slipped at depth a.x_m) that move with the needle over a -> b stick at
  /// a (2.3.5). True when one did.
  bool stickSlipping(const Solved& a, const Solved& b, double dt_s);
  /// f_ext: kinetic friction on every slipping shaft node, its share of the shaft times f_k.
  void applyKineticForces();
  Prescribed buildPrescribed() const;
  StepStatus solve(double dt_s, Eigen::VectorXd& reactions);
  bool enterTissue();
  bool cut();
  void releaseBehind();
  /// Recomputes the nodes that move rigidly with the tip node (tip_radius_m > 0).
  void refreshTipPatch();
  /// Length of shaft that shaft_[s] stands for: half the distance to each neighbour (the entry
  /// face and the tip at the ends) [m].
  double shaftShare(std::size_t s) const;
  /// Stick-slip transitions after a solve (2.3.5); slipping nodes may stick only when
  /// `allow_stick`. True when a node changed state (the step is solved again).
  bool updateFriction(const Prescribed& prescribed, const Eigen::VectorXd& reactions, double dt_s,
                      bool allow_stick);
  /// Moves a reference node towards target as far as no adjacent triangle drops below its
  /// minimum area; returns the fraction of the move made, in [0, 1].
  double moveNodeSafely(int node, const Point2& target);
  void relocateSeeds(int moved_node);
  void locateSeed(Seed& seed) const;
  Eigen::Matrix2d deformationGradient(int triangle) const;
  double triangleArea(int triangle) const;
  int prescribedIndex(const Prescribed& p, int dof) const;
  /// Needle force on the tissue along +x at the tip node and its patch [N].
  double tipForce(const Prescribed& prescribed, const Eigen::VectorXd& reactions) const;

  FemModel& model_;
  Integrator& integrator_;
  std::vector<int> entry_nodes_;
  std::vector<char> node_fixed_;
  Point2 bounds_min_, bounds_max_;
  NeedleParams params_;
  std::vector<double> original_area_;
  std::vector<Point2> original_nodes_;

  bool in_tissue_ = false;
  double height_m_ = 0.0;
  double tip_x_m_ = 0.0;
  double prev_tip_x_m_ = 0.0;
  int tip_node_ = -1;
  Point2 tip_start_ref_ = Point2::Zero();  ///< reference position where the tip node started
  std::vector<int> shaft_;                 ///< shaft nodes, from the entry towards the tip
  std::vector<int> tip_patch_;             ///< nodes moving with the tip node (finite tip)
  std::vector<ShaftState> shaft_state_;
  std::vector<Seed> seeds_;
  Eigen::VectorXd f_ext_;
  Eigen::VectorXd u_prev_;
  InsertionStepInfo info_;
  /// The last step's end: constraints, loads and reactions, reused as the next step's start
  /// when nothing changed in between.
  std::vector<int> last_dofs_;
  Eigen::VectorXd last_f_ext_;
  Eigen::VectorXd last_reactions_;
  double motion_direction_ = 1.0;  ///< +1 inserting, -1 retracting (the last step's)
};

}  // namespace needle_guidance::tissue
