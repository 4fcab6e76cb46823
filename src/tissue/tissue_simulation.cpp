#include "needle_guidance/tissue/tissue_simulation.h"

#include <cmath>
#include <stdexcept>

namespace needle_guidance::tissue {
namespace {

constexpr double kOnBoundaryTol_m = 1e-9;

IntegratorKind integratorFor(scene::TissueModel model) {
  switch (model) {
    case scene::TissueModel::kNewmark:
      return IntegratorKind::kNewmark;
    case scene::TissueModel::kExplicit:
      return IntegratorKind::kExplicit;
    case scene::TissueModel::kQuasiStatic:
      return IntegratorKind::kQuasiStatic;
    case scene::TissueModel::kNone:
      break;
  }
  throw std::invalid_argument("TissueSimulation: the scene has no tissue model (models.tissue: none)");
}

}  // namespace

TissueSimOptions optionsFromScene(const scene::Scene& scene) {
  TissueSimOptions options;
  options.integrator = integratorFor(scene.models.tissue);
  options.corotational = scene.models.corotational;
  options.formulation = scene.models.averaged_volumetric ? ElementFormulation::kAveragedVolumetric
                                                         : ElementFormulation::kLinear;
  options.meshing.max_edge_m = scene.mesh.max_edge_m;
  options.meshing.min_edge_m = scene.mesh.min_edge_m;
  options.meshing.grading_length_m = scene.mesh.grading_length_m;
  options.meshing.min_angle_deg = scene.mesh.min_angle_deg;
  if (scene.mesh.refine_targets) {
    // Fine at the targets and along the straight needle paths from the entry face to them
    // (DESIGN.md: graded meshes, fine along the needle path).
    for (const auto& target : scene.targets) {
      options.meshing.refine_points.push_back(target.position);
      options.meshing.refine_lines.push_back(
          {Point2(scene.workspace_min.x(), target.position.y()), target.position});
    }
  }
  return options;
}

NeedleParams needleParamsFromScene(const scene::Scene& scene) {
  NeedleParams params;
  params.cutting_force_N = scene.needle.cutting_force_N;
  params.cut_length_m = scene.needle.cut_length_m > 0.0 ? scene.needle.cut_length_m : params.cut_length_m;
  params.static_friction_N_per_m = scene.needle.static_friction_N_per_m;
  params.kinetic_friction_N_per_m = scene.needle.kinetic_friction_N_per_m;
  params.stick_velocity_m_s = scene.needle.stick_velocity_m_s;
  params.tip_radius_m = 0.5 * scene.needle.diameter_m;
  return params;
}

TissueSimulation::TissueSimulation(const scene::Scene& scene, const TissueSimOptions& options)
    : scene_(scene), options_(options) {
  integratorFor(scene_.models.tissue);  // refuses scenes without tissue
  initial_mesh_ = geometry::meshDomain(scene_.workspacePolygon(), scene_.background_material,
                                       scene_.meshRegions(), options_.meshing);

  element_materials_.reserve(initial_mesh_.triangleCount());
  std::vector<char> node_fixed(initial_mesh_.nodeCount(), 0);
  for (std::size_t t = 0; t < initial_mesh_.triangleCount(); ++t) {
    const int region = initial_mesh_.triangle_region[t];
    const std::string& material_name =
        region == 0 ? scene_.background_material
                    : scene_.regions[static_cast<std::size_t>(region - 1)].material;
    const scene::Material& m = scene_.material(material_name);
    element_materials_.push_back({m.young_modulus_Pa, m.poisson_ratio, m.density_kg_m3,
                                  m.rayleigh_alpha_per_s, m.rayleigh_beta_s});
    if (region > 0 && scene_.regions[static_cast<std::size_t>(region - 1)].rigid) {
      for (int node : initial_mesh_.triangles[t]) {  // bone: its nodes are fixed (2.3.2)
        node_fixed[static_cast<std::size_t>(node)] = 1;
      }
    }
  }
  for (int node : initial_mesh_.boundaryNodes()) {
    const Point2& p = initial_mesh_.nodes[static_cast<std::size_t>(node)];
    if (scene_.boundaryConditionAt(p) == scene::BoundaryCondition::kFixed) {
      node_fixed[static_cast<std::size_t>(node)] = 1;
    } else if (std::abs(p.x() - scene_.workspace_min.x()) < kOnBoundaryTol_m) {
      entry_nodes_.push_back(node);
    }
  }
  for (std::size_t node = 0; node < node_fixed.size(); ++node) {
    if (node_fixed[node]) {
      fixed_dofs_.push_back(dofX(static_cast<int>(node)));
      fixed_dofs_.push_back(dofY(static_cast<int>(node)));
    }
  }
  build();
}

void TissueSimulation::build() {
  FemOptions fem_options;
  fem_options.formulation = options_.formulation;
  fem_options.thickness_m = scene_.thickness_m;
  model_ = std::make_unique<FemModel>(initial_mesh_, element_materials_, fem_options);
  IntegratorOptions integrator_options;
  integrator_options.corotational = options_.corotational;
  integrator_ = makeIntegrator(options_.integrator, *model_, fixed_dofs_, integrator_options);
  needle_ = std::make_unique<NeedleInsertion>(*model_, *integrator_, entry_nodes_, fixed_dofs_,
                                              scene_.workspace_min, scene_.workspace_max,
                                              needleParamsFromScene(scene_));
}

StepStatus TissueSimulation::step(double dt_s, double needle_height_m, double tip_x_m) {
  return needle_->step(dt_s, needle_height_m, tip_x_m);
}

void TissueSimulation::reset() {
  needle_.reset();
  integrator_.reset();
  model_.reset();
  build();
}

}  // namespace needle_guidance::tissue
