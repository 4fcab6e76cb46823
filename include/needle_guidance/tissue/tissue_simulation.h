// A tissue simulation built from a scene: graded mesh, FEM model, integrator, needle and seeds.
// The one entry point the tissue_sim node, the benchmarks and the planners use.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue/fem_model.h"
#include "needle_guidance/tissue/integrator.h"
#include "needle_guidance/tissue/needle_insertion.h"

namespace needle_guidance::fem {
template <int Dim>
class EmbeddedNeedle;  // fem/embedded_needle.h
}  // namespace needle_guidance::fem

namespace needle_guidance::tissue {

/// The fixed depth grid the needle advances on. Cutting (2.3.4) and stick-slip
/// friction (2.3.5) make the seed's release point depend on the depths the FEM is solved at, so
/// TissueSimulation::advance() sub-steps every command onto this grid: the live node (stepping on
/// the robot's messages), the planner's scans and verifying simulations, and the bench's
/// independent simulation execute the same schedule however the motion is sampled.
struct DepthGrid {
  /// Grid spacing along +x from the entry face [m]; 0: off (every command is one FEM step).
  double step_m = 1e-4;
  /// Retraction visits every retract_stride-th grid point (it cuts nothing, 2.3.6), >= 1.
  int retract_stride = 5;
  double insert_velocity_m_s = 0.01;   ///< nominal speed: dt of an insertion sub-step [m/s]
  double retract_velocity_m_s = 0.02;  ///< nominal speed: dt of a retraction sub-step [m/s]
};

/// How the needle cuts the tissue.
enum class NeedleModel {
  /// The cut track is a line of tissue points embedded in the fixed triangle mesh
  /// (fem::EmbeddedNeedle, the 3-D insertion's algorithm): the tip cuts continuously, every
  /// track_spacing_m of cut a tissue point joins the shaft, each step is a small dense system on
  /// the condensed compliance of those points. Quasi-static, linear elements only.
  kEmbeddedTrack,
  /// Cutting moves mesh nodes onto the needle (NeedleInsertion, 2.3.4): any integrator and
  /// element formulation; every cut changes the factor.
  kNodeMoving,
};
const char* toString(NeedleModel model);

/// Choices a scene makes, which a caller (benchmark, planner) may override.
struct TissueSimOptions {
  DepthGrid depth_grid;  ///< the scene's needle velocity (retraction at twice it), 0.1 mm
  IntegratorKind integrator = IntegratorKind::kQuasiStatic;
  bool corotational = false;
  ElementFormulation formulation = ElementFormulation::kLinear;
  geometry::MeshingOptions meshing;  ///< element sizes and refinement features
  bool locate_events = true;         ///< NeedleParams::locate_events (node-moving model)
  /// kEmbeddedTrack for a quasi-static, linear, not corotational scene; else kNodeMoving.
  NeedleModel needle_model = NeedleModel::kEmbeddedTrack;
  /// Spacing of the shaft's tissue points on the embedded track [m], > 0.
  double track_spacing_m = 1e-3;
};

/// The options a scene asks for: its tissue model, mesh sizes, refinement towards its targets.
/// Throws std::invalid_argument if the scene has no tissue model.
TissueSimOptions optionsFromScene(const scene::Scene& scene);

/// kEmbeddedTrack when the options allow it (quasi-static, linear elements, not corotational),
/// else kNodeMoving.
NeedleModel needleModelFor(const TissueSimOptions& options);

/// Needle interaction parameters from the scene's needle section.
NeedleParams needleParamsFromScene(const scene::Scene& scene);

class TissueSimulation {
public:
  /// Meshes the scene and builds the model. Throws std::invalid_argument for a scene without
  /// tissue or a mesh the FEM refuses.
  TissueSimulation(const scene::Scene& scene, const TissueSimOptions& options);
  explicit TissueSimulation(const scene::Scene& scene)
      : TissueSimulation(scene, optionsFromScene(scene)) {}
  /// A deep copy of the whole state (mesh as cut, factorisation, needle, seeds): stepping the
  /// copy gives the same results, bit for bit, as stepping the original (a planner
  /// verifies a release from the state its scan reached there). Throws std::logic_error when
  /// the integrator cannot be copied (copyable() is false).
  TissueSimulation(const TissueSimulation& other);
  TissueSimulation& operator=(const TissueSimulation&) = delete;
  ~TissueSimulation();
  /// The state can be copied (the quasi-static integrator can; the dynamic ones cannot).
  bool copyable() const { return pristine_ != nullptr || track_ != nullptr; }

  /// One raw FEM step: the needle at height y [m] with its tip at x [m], dt [s]. The outcome
  /// depends on how a motion is cut into steps; advance() does not.
  StepStatus step(double dt_s, double needle_height_m, double tip_x_m);
  /// Moves the needle to height y, tip x along the depth grid (options().depth_grid): one FEM
  /// step per grid point passed (insertion) or per retract_stride points (retraction), each at
  /// the grid's nominal speed, the tip held at the last grid point reached. A command that
  /// passes no grid point steps nothing for the quasi-static model; a dynamic model keeps
  /// integrating for dt_s at rest. With the grid off it is step(). Refuses what step() refuses;
  /// a refused sub-step leaves the tip at the last grid point reached.
  StepStatus advance(double dt_s, double needle_height_m, double tip_x_m);
  /// Grid index of a tip x: floor((x - entry) / step) (x within 1e-3 step below a grid point
  /// counts as on it), -1 for any x outside the tissue. Needs the grid on.
  long gridIndex(double tip_x_m) const;
  /// Tip x of grid point k (k = -1: one step outside the entry face) [m].
  double gridDepth(long k) const;
  /// Grid point the tip stands at (-1: outside).
  long gridPosition() const { return grid_k_; }
  /// Back to the undeformed reference mesh, no needle, no seeds: a copy of the state kept
  /// after construction (mesh, model and its factorisation are not rebuilt) when copyable().
  void reset();
  /// FEM steps solved since construction (each step() and each grid sub-step of advance();
  /// reset() keeps counting; a copy starts from its original's count): a measure of work that
  /// does not depend on the machine's load.
  long femSteps() const { return fem_steps_; }
  /// Linear-solver work since construction (kept like femSteps()), in millions of factor entries
  /// touched: each solve, factor modification and factorisation weighted by its measured cost
  /// relative to a solve (TissueSimulation::needleStep), times the factor's
  /// entries. Unlike femSteps() it follows what a step costs (deep insertions solve more per
  /// step, a finer mesh more per solve), and unlike a clock it does not depend on the load.
  double solverWork() const { return solver_work_; }

  /// Implants a seed at the needle tip (2.4). Refused when the needle is not in tissue.
  std::optional<int> implantSeed(std::string* why_not = nullptr);
  const std::vector<Seed>& seeds() const;
  /// World position of a seed in the deformed tissue [m].
  Point2 seedPosition(const Seed& seed) const;
  /// Deformed position of every node of mesh() [m].
  std::vector<Point2> deformedNodes() const;
  /// Displacement of every node of mesh() [m], 2*node order.
  Eigen::VectorXd displacement() const;
  /// The mesh the tissue is simulated on now (the embedded track never changes it; the
  /// node-moving model cuts it).
  const geometry::TriangleMesh& mesh() const;

  /// The needle, whichever model runs it.
  NeedleModel needleModel() const { return options_.needle_model; }
  bool needleInTissue() const;
  double tipX() const;
  /// Reference position of the tip (the tip node's, or the tip's tissue point) when in tissue.
  std::optional<Point2> tipReference() const;
  /// Shaft nodes (node-moving) or shaft tissue points (embedded track) [count].
  int shaftCount() const;
  /// Reference positions of the shaft's tissue points (embedded track) or nodes [m].
  std::vector<Point2> shaftReference() const;
  /// The last step's figures.
  const InsertionStepInfo& lastStep() const;

  const scene::Scene& scene() const { return scene_; }
  const TissueSimOptions& options() const { return options_; }
  /// The node-moving model's parts; they throw std::logic_error on the embedded track.
  const FemModel& model() const;
  const Integrator& integrator() const;
  const NeedleInsertion& needle() const;
  /// The embedded track's needle; throws std::logic_error on the node-moving model.
  const fem::EmbeddedNeedle<2>& trackNeedle() const;
  const std::vector<int>& fixedDofs() const { return fixed_dofs_; }
  /// The mesh as first generated (cutting moves nodes of model().mesh()).
  const geometry::TriangleMesh& initialMesh() const { return initial_mesh_; }

private:
  /// Model, integrator and needle at rest, factorised: what reset() copies.
  struct Pristine;
  void build();
  /// Copies model, integrator and needle from `model`, `integrator`, `needle`.
  void copyParts(const FemModel& model, const Integrator& integrator,
                 const NeedleInsertion& needle);
  StepStatus needleStep(double dt_s, double needle_height_m, double tip_x_m);
  StepStatus gridStep(long k, double needle_height_m, double dt_s);
  /// The embedded track's step: the needle moved to (tip_x, height), events located.
  StepStatus trackStep(double dt_s, double needle_height_m, double tip_x_m);
  void buildTrack();
  bool embedded() const { return options_.needle_model == NeedleModel::kEmbeddedTrack; }
  /// Mesh and tissue of the embedded track, shared by copies.
  struct Track;
  scene::Scene scene_;
  TissueSimOptions options_;
  geometry::TriangleMesh initial_mesh_;
  std::vector<ElementMaterial> element_materials_;
  std::vector<int> fixed_dofs_;
  std::vector<int> entry_nodes_;
  std::unique_ptr<FemModel> model_;
  std::unique_ptr<Integrator> integrator_;
  std::unique_ptr<NeedleInsertion> needle_;
  std::shared_ptr<const Pristine> pristine_;  ///< shared by copies; null: not copyable
  std::shared_ptr<const Track> track_;        ///< embedded track: its tissue
  std::unique_ptr<fem::EmbeddedNeedle<2>> track_needle_;
  std::vector<Seed> track_seeds_;
  InsertionStepInfo track_info_;
  long grid_k_ = -1;
  long fem_steps_ = 0;
  double solver_work_ = 0.0;
};

}  // namespace needle_guidance::tissue
