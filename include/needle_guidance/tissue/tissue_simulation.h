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

/// Choices a scene makes, which a caller (benchmark, planner) may override.
struct TissueSimOptions {
  DepthGrid depth_grid;  ///< the scene's needle velocity (retraction at twice it), 0.1 mm
  IntegratorKind integrator = IntegratorKind::kQuasiStatic;
  bool corotational = false;
  ElementFormulation formulation = ElementFormulation::kLinear;
  geometry::MeshingOptions meshing;  ///< element sizes and refinement features
  bool locate_events = true;         ///< NeedleParams::locate_events
};

/// The options a scene asks for: its tissue model, mesh sizes, refinement towards its targets.
/// Throws std::invalid_argument if the scene has no tissue model.
TissueSimOptions optionsFromScene(const scene::Scene& scene);

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
  bool copyable() const { return pristine_ != nullptr; }

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

  std::optional<int> implantSeed(std::string* why_not = nullptr) {
    return needle_->implantSeed(why_not);
  }
  const std::vector<Seed>& seeds() const { return needle_->seeds(); }
  Point2 seedPosition(const Seed& seed) const { return needle_->seedPosition(seed); }
  std::vector<Point2> deformedNodes() const { return needle_->deformedNodes(); }

  const scene::Scene& scene() const { return scene_; }
  const TissueSimOptions& options() const { return options_; }
  const FemModel& model() const { return *model_; }
  const Integrator& integrator() const { return *integrator_; }
  const NeedleInsertion& needle() const { return *needle_; }
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
  long grid_k_ = -1;
  long fem_steps_ = 0;
  double solver_work_ = 0.0;
};

}  // namespace needle_guidance::tissue
