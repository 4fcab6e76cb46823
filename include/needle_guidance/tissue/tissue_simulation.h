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

/// Choices a scene makes, which a caller (benchmark, planner) may override.
struct TissueSimOptions {
  IntegratorKind integrator = IntegratorKind::kQuasiStatic;
  bool corotational = false;
  ElementFormulation formulation = ElementFormulation::kLinear;
  geometry::MeshingOptions meshing;  ///< element sizes and refinement features
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

  /// One step: the needle at height y [m] with its tip at x [m], dt [s].
  StepStatus step(double dt_s, double needle_height_m, double tip_x_m);
  /// Back to the undeformed reference mesh, no needle, no seeds.
  void reset();

  std::optional<int> implantSeed(std::string* why_not = nullptr) { return needle_->implantSeed(why_not); }
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
  void build();
  scene::Scene scene_;
  TissueSimOptions options_;
  geometry::TriangleMesh initial_mesh_;
  std::vector<ElementMaterial> element_materials_;
  std::vector<int> fixed_dofs_;
  std::vector<int> entry_nodes_;
  std::unique_ptr<FemModel> model_;
  std::unique_ptr<Integrator> integrator_;
  std::unique_ptr<NeedleInsertion> needle_;
};

}  // namespace needle_guidance::tissue
