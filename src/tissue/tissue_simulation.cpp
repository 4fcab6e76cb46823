#include "needle_guidance/tissue/tissue_simulation.h"

#include <cmath>
#include <stdexcept>

#include "needle_guidance/fem/embedded_needle.h"

namespace needle_guidance::tissue {
namespace {

constexpr double kOnBoundaryTol_m = 1e-9;
/// A tip this fraction of a grid step short of a grid point stands on it (a robot that stops
/// on a commanded grid depth reports it to rounding error).
constexpr double kGridSnap = 1e-3;

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
  throw std::invalid_argument(
      "TissueSimulation: the scene has no tissue model (models.tissue: none)");
}

}  // namespace

const char* toString(NeedleModel model) {
  return model == NeedleModel::kEmbeddedTrack ? "embedded_track" : "node_moving";
}

NeedleModel needleModelFor(const TissueSimOptions& options) {
  return options.integrator == IntegratorKind::kQuasiStatic && !options.corotational &&
                 options.formulation == ElementFormulation::kLinear
             ? NeedleModel::kEmbeddedTrack
             : NeedleModel::kNodeMoving;
}

TissueSimOptions optionsFromScene(const scene::Scene& scene) {
  TissueSimOptions options;
  options.integrator = integratorFor(scene.models.tissue);
  options.corotational = scene.models.corotational;
  options.formulation = scene.models.averaged_volumetric ? ElementFormulation::kAveragedVolumetric
                                                         : ElementFormulation::kLinear;
  options.needle_model = needleModelFor(options);
  options.depth_grid.insert_velocity_m_s = scene.needle.insertion_velocity_m_s;
  options.depth_grid.retract_velocity_m_s = 2.0 * scene.needle.insertion_velocity_m_s;
  options.meshing.max_edge_m = scene.mesh.max_edge_m;
  options.meshing.min_edge_m = scene.mesh.min_edge_m;
  options.meshing.grading_length_m = scene.mesh.grading_length_m;
  options.meshing.min_angle_deg = scene.mesh.min_angle_deg;
  if (scene.mesh.refine_targets) {
    // Fine at the targets and along the straight needle paths from the entry face to them
    // (graded meshes, fine along the needle path).
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
  params.cut_length_m =
      scene.needle.cut_length_m > 0.0 ? scene.needle.cut_length_m : params.cut_length_m;
  params.static_friction_N_per_m = scene.needle.static_friction_N_per_m;
  params.kinetic_friction_N_per_m = scene.needle.kinetic_friction_N_per_m;
  params.stick_velocity_m_s = scene.needle.stick_velocity_m_s;
  params.tip_radius_m = 0.5 * scene.needle.diameter_m;
  return params;
}

TissueSimulation::TissueSimulation(const scene::Scene& scene, const TissueSimOptions& options)
    : scene_(scene), options_(options) {
  integratorFor(scene_.models.tissue);  // refuses scenes without tissue
  const DepthGrid& grid = options_.depth_grid;
  if (!(grid.step_m >= 0.0) || !std::isfinite(grid.step_m) || grid.retract_stride < 1 ||
      !(grid.insert_velocity_m_s > 0.0) || !(grid.retract_velocity_m_s > 0.0) ||
      !std::isfinite(grid.insert_velocity_m_s) || !std::isfinite(grid.retract_velocity_m_s)) {
    throw std::invalid_argument(
        "TissueSimulation: depth grid step must be >= 0 (0 = off), retract stride >= 1 and "
        "velocities > 0 (step " +
        std::to_string(grid.step_m) + " m, stride " + std::to_string(grid.retract_stride) + ")");
  }
  if (embedded() &&
      (options_.integrator != IntegratorKind::kQuasiStatic || options_.corotational ||
       options_.formulation != ElementFormulation::kLinear || !(options_.track_spacing_m > 0.0))) {
    throw std::invalid_argument(
        "TissueSimulation: the embedded track needs the quasi-static integrator, linear "
        "elements (not corotational, not averaged volumetric) and a track spacing > 0 (" +
        std::to_string(options_.track_spacing_m) + " m)");
  }
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
  if (embedded()) {
    buildTrack();
  } else {
    build();
  }
}

/// The embedded track's tissue: the mesh as generated (never cut) and its factored compliance.
struct TissueSimulation::Track {
  fem::SimplexMesh<2> mesh;
  std::unique_ptr<fem::EmbeddingTissue<2>> tissue;
  fem::EmbeddedNeedleParams params;
  double max_tip_x_m = 0.0;
};

void TissueSimulation::buildTrack() {
  auto track = std::make_shared<Track>();
  track->mesh.nodes = initial_mesh_.nodes;
  std::vector<fem::Material> materials;
  for (std::size_t t = 0; t < initial_mesh_.triangleCount(); ++t) {
    track->mesh.elements.push_back(initial_mesh_.triangles[t]);
    track->mesh.element_material.push_back(static_cast<int>(t));
    materials.push_back(
        {element_materials_[t].young_modulus_Pa, element_materials_[t].poisson_ratio});
  }
  std::vector<char> node_fixed(initial_mesh_.nodeCount(), 0);
  for (std::size_t i = 0; i < fixed_dofs_.size(); i += 2) {
    node_fixed[static_cast<std::size_t>(fixed_dofs_[i] / 2)] = 1;
  }
  track->tissue = std::make_unique<fem::EmbeddingTissue<2>>(track->mesh, node_fixed, materials,
                                                            scene_.thickness_m);
  const NeedleParams needle = needleParamsFromScene(scene_);
  track->params.cutting_force_N = needle.cutting_force_N;
  track->params.static_friction_N_per_m = needle.static_friction_N_per_m;
  track->params.kinetic_friction_N_per_m = needle.kinetic_friction_N_per_m;
  track->params.stick_velocity_m_s = needle.stick_velocity_m_s;
  track->params.insertion_velocity_m_s = scene_.needle.insertion_velocity_m_s;
  track->params.track_spacing_m = options_.track_spacing_m;
  track->params.follow_tissue = scene_.needle.follow_tissue;
  track->params.tip_radius_m =
      scene_.needle.diameter_m > 0.0 ? 0.5 * scene_.needle.diameter_m : track->params.tip_radius_m;
  // The compliance along the needle line is solved in one batch up to the deepest tip the
  // needle may reach; deeper elements are solved as the tip meets them.
  track->max_tip_x_m = scene_.needle.max_depth_m > scene_.workspace_min.x()
                           ? std::min(scene_.needle.max_depth_m, scene_.workspace_max.x())
                           : scene_.workspace_max.x();
  track_ = track;
  track_needle_ = std::make_unique<fem::EmbeddedNeedle<2>>(
      *track_->tissue, track_->params, scene_.workspace_min.x(), track_->max_tip_x_m);
}

struct TissueSimulation::Pristine {
  std::unique_ptr<FemModel> model;
  std::unique_ptr<Integrator> integrator;
  std::unique_ptr<NeedleInsertion> needle;
};

TissueSimulation::TissueSimulation(const TissueSimulation& other)
    : scene_(other.scene_),
      options_(other.options_),
      initial_mesh_(other.initial_mesh_),
      element_materials_(other.element_materials_),
      fixed_dofs_(other.fixed_dofs_),
      entry_nodes_(other.entry_nodes_),
      pristine_(other.pristine_),
      grid_k_(other.grid_k_),
      fem_steps_(other.fem_steps_),
      solver_work_(other.solver_work_) {
  if (other.embedded()) {
    track_ = other.track_;
    track_needle_ = std::make_unique<fem::EmbeddedNeedle<2>>(*other.track_needle_);
    track_seeds_ = other.track_seeds_;
    track_info_ = other.track_info_;
    return;
  }
  if (!other.copyable()) {
    throw std::logic_error("TissueSimulation: the " +
                           std::string(toString(other.integrator_->kind())) +
                           " integrator's state cannot be copied");
  }
  copyParts(*other.model_, *other.integrator_, *other.needle_);
}

TissueSimulation::~TissueSimulation() = default;

void TissueSimulation::copyParts(const FemModel& model, const Integrator& integrator,
                                 const NeedleInsertion& needle) {
  auto model_copy = std::make_unique<FemModel>(model);
  std::unique_ptr<Integrator> integrator_copy = integrator.clone(*model_copy);
  if (!integrator_copy) {
    throw std::logic_error("TissueSimulation: the integrator cannot be copied");
  }
  needle_.reset();
  integrator_.reset();
  model_ = std::move(model_copy);
  integrator_ = std::move(integrator_copy);
  needle_ = std::make_unique<NeedleInsertion>(needle, *model_, *integrator_);
}

void TissueSimulation::build() {
  FemOptions fem_options;
  fem_options.formulation = options_.formulation;
  fem_options.thickness_m = scene_.thickness_m;
  model_ = std::make_unique<FemModel>(initial_mesh_, element_materials_, fem_options);
  IntegratorOptions integrator_options;
  integrator_options.corotational = options_.corotational;
  integrator_ = makeIntegrator(options_.integrator, *model_, fixed_dofs_, integrator_options);
  NeedleParams needle_params = needleParamsFromScene(scene_);
  needle_params.locate_events = options_.locate_events;
  needle_ =
      std::make_unique<NeedleInsertion>(*model_, *integrator_, entry_nodes_, fixed_dofs_,
                                        scene_.workspace_min, scene_.workspace_max, needle_params);
  if (pristine_ || options_.integrator != IntegratorKind::kQuasiStatic) {
    return;
  }
  // Keep the state at rest, factorised (the unloaded solve every insertion starts with), for
  // reset() and copies: a reset then copies instead of re-assembling and re-analysing.
  Eigen::VectorXd reactions;
  const StepStatus rest =
      integrator_->step(1.0, Eigen::VectorXd::Zero(model_->dofCount()), Prescribed{}, reactions);
  if (!rest) {
    throw std::invalid_argument("TissueSimulation: the unloaded model cannot be solved: " +
                                rest.toString());
  }
  auto pristine = std::make_shared<Pristine>();
  pristine->model = std::move(model_);
  pristine->integrator = std::move(integrator_);
  pristine->needle = std::move(needle_);
  pristine_ = pristine;
  copyParts(*pristine->model, *pristine->integrator, *pristine->needle);
}

StepStatus TissueSimulation::needleStep(double dt_s, double needle_height_m, double tip_x_m) {
  ++fem_steps_;
  if (embedded()) {
    return trackStep(dt_s, needle_height_m, tip_x_m);
  }
  const Integrator::SolverCounters before = integrator_->solverCounters();
  const StepStatus status = needle_->step(dt_s, needle_height_m, tip_x_m);
  const Integrator::SolverCounters after = integrator_->solverCounters();
  // Cost of each operation relative to a solve: a least-squares fit of thread CPU time to the
  // counters over 415 windows of 20 grid steps on five scenes (55k-98k factor entries; per-scene
  // totals within 4 %): a factorisation ~30 solves, a row deletion/addition ~0.12, a rank-1
  // update ~0.10.
  constexpr double kFactorization = 30.0, kRowChange = 0.12, kRankUpdate = 0.10;
  const double solves =
      kFactorization * static_cast<double>(after.factorizations - before.factorizations) +
      kRowChange * static_cast<double>(after.row_deletions - before.row_deletions +
                                       after.row_additions - before.row_additions) +
      kRankUpdate * static_cast<double>(after.rank_updates - before.rank_updates) +
      static_cast<double>(after.solves - before.solves);
  solver_work_ += 1e-6 * solves * static_cast<double>(after.factor_entries);
  return status;
}

StepStatus TissueSimulation::step(double dt_s, double needle_height_m, double tip_x_m) {
  return needleStep(dt_s, needle_height_m, tip_x_m);
}

long TissueSimulation::gridIndex(double tip_x_m) const {
  const double step = options_.depth_grid.step_m;
  if (!(step > 0.0)) {
    throw std::logic_error("TissueSimulation::gridIndex: the depth grid is off");
  }
  const double s = (tip_x_m - scene_.workspace_min.x()) / step + kGridSnap;
  return s < 0.0 ? -1 : static_cast<long>(std::floor(s));
}

double TissueSimulation::gridDepth(long k) const {
  return scene_.workspace_min.x() + static_cast<double>(k) * options_.depth_grid.step_m;
}

StepStatus TissueSimulation::gridStep(long k, double needle_height_m, double dt_s) {
  const StepStatus status = needleStep(dt_s, needle_height_m, gridDepth(k));
  if (status) {
    grid_k_ = k;
  }
  return status;
}

StepStatus TissueSimulation::advance(double dt_s, double needle_height_m, double tip_x_m) {
  const DepthGrid& grid = options_.depth_grid;
  if (!(grid.step_m > 0.0) || !std::isfinite(tip_x_m) || tip_x_m >= scene_.workspace_max.x()) {
    return step(dt_s, needle_height_m, tip_x_m);  // grid off, or step() says why it refuses
  }
  const long k_cmd = gridIndex(tip_x_m);
  StepStatus status;
  if (k_cmd > grid_k_) {  // insertion: every grid point, at the nominal speed
    const double dt = grid.step_m / grid.insert_velocity_m_s;
    for (long k = grid_k_ + 1; k <= k_cmd && status; ++k) {
      status = gridStep(k, needle_height_m, dt);
    }
  } else if (k_cmd < grid_k_) {
    // Retraction: the multiples of the stride below the tip, then outside; the tip waits on the
    // last multiple until the command passes the next one.
    const long stride = grid.retract_stride;
    const double dt = static_cast<double>(stride) * grid.step_m / grid.retract_velocity_m_s;
    long k = grid_k_ - 1 - ((grid_k_ - 1) % stride + stride) % stride;
    for (; k >= std::max(k_cmd, 0L) && status; k -= stride) {
      status = gridStep(k, needle_height_m, dt);
    }
    if (status && k_cmd < 0) {
      status = gridStep(-1, needle_height_m, dt);
    }
  } else if (options_.integrator != IntegratorKind::kQuasiStatic) {
    status = needleStep(dt_s, needle_height_m, gridDepth(grid_k_));  // dynamics at rest
  }
  return status;
}

void TissueSimulation::reset() {
  grid_k_ = -1;
  if (embedded()) {
    track_needle_ = std::make_unique<fem::EmbeddedNeedle<2>>(
        *track_->tissue, track_->params, scene_.workspace_min.x(), track_->max_tip_x_m);
    track_seeds_.clear();
    track_info_ = InsertionStepInfo{};
    return;
  }
  if (pristine_) {
    copyParts(*pristine_->model, *pristine_->integrator, *pristine_->needle);
    return;
  }
  needle_.reset();
  integrator_.reset();
  model_.reset();
  build();
}

StepStatus TissueSimulation::trackStep(double dt_s, double needle_height_m, double tip_x_m) {
  auto refuse = [](const std::string& why) { return StepStatus{false, "needle step: " + why}; };
  if (!std::isfinite(dt_s) || !(dt_s > 0.0) || !std::isfinite(needle_height_m) ||
      !std::isfinite(tip_x_m)) {
    return refuse("non-finite input or dt <= 0");
  }
  if (needle_height_m <= scene_.workspace_min.y() || needle_height_m >= scene_.workspace_max.y()) {
    return refuse("needle height " + std::to_string(needle_height_m * 1e3) +
                  " mm is outside the tissue (" + std::to_string(scene_.workspace_min.y() * 1e3) +
                  " to " + std::to_string(scene_.workspace_max.y() * 1e3) + " mm)");
  }
  if (tip_x_m >= scene_.workspace_max.x()) {
    return refuse("tip x " + std::to_string(tip_x_m * 1e3) + " mm is beyond the tissue (" +
                  std::to_string(scene_.workspace_max.x() * 1e3) + " mm)");
  }
  const fem::CondensedCompliance& compliance = track_->tissue->compliance();
  const long long solves_before = track_needle_->totalSolves();
  const long long columns_before = compliance.solvedColumns();
  const int shaft_before = track_needle_->lastMove().shaft_points;
  // A move refused half-way (the track meets bone, or leaves the mesh) leaves the state as it
  // was: the needle is moved on a copy.
  auto moved = std::make_unique<fem::EmbeddedNeedle<2>>(*track_needle_);
  std::string why;
  if (!moved->moveTo(Eigen::Matrix<double, 1, 1>(needle_height_m), tip_x_m, &why)) {
    return refuse(why);
  }
  track_needle_ = std::move(moved);
  const fem::EmbeddedNeedleInfo& info = track_needle_->lastMove();
  track_info_ = InsertionStepInfo{};
  track_info_.events = info.events;
  track_info_.slipping = info.slipping;
  track_info_.promoted = std::max(0, info.shaft_points - shaft_before);
  track_info_.released = std::max(0, shaft_before - info.shaft_points);
  track_info_.tip_force_N = info.tip_force_N;
  track_info_.friction_force_N = info.friction_force_N;
  // Work in the node-moving model's unit (millions of factor entries touched): each compliance
  // column is one solve with the sparse factor (counted by the doubles of the factor and the
  // cached columns), each condensed solve touches its dense system.
  const double points = info.shaft_points + 1.0;
  const double doubles =
      static_cast<double>(compliance.factorBytes()) / sizeof(double) +
      static_cast<double>(compliance.cachedColumns()) * static_cast<double>(compliance.dofCount());
  solver_work_ +=
      1e-6 *
      (static_cast<double>(compliance.solvedColumns() - columns_before) * doubles / 8.0 +
       static_cast<double>(track_needle_->totalSolves() - solves_before) * 4.0 * points * points);
  return StepStatus{};
}

std::optional<int> TissueSimulation::implantSeed(std::string* why_not) {
  if (!embedded()) {
    return needle_->implantSeed(why_not);
  }
  const std::optional<int> id = track_needle_->implantSeed(why_not);
  if (!id) {
    return id;
  }
  Seed seed;
  seed.id = static_cast<int>(track_seeds_.size());
  seed.p_ref = track_needle_->seedReference(*id);
  if (const auto p = track_->tissue->locate(seed.p_ref)) {
    seed.triangle = p->element;
    seed.barycentric = {p->weights(0), p->weights(1), p->weights(2)};
  }
  track_seeds_.push_back(seed);
  return seed.id;
}

const std::vector<Seed>& TissueSimulation::seeds() const {
  return embedded() ? track_seeds_ : needle_->seeds();
}

Point2 TissueSimulation::seedPosition(const Seed& seed) const {
  return embedded() ? Point2(track_needle_->worldOf(seed.p_ref)) : needle_->seedPosition(seed);
}

Eigen::VectorXd TissueSimulation::displacement() const {
  return embedded() ? track_needle_->displacementField() : integrator_->displacement();
}

std::vector<Point2> TissueSimulation::deformedNodes() const {
  if (!embedded()) {
    return needle_->deformedNodes();
  }
  const Eigen::VectorXd u = displacement();
  std::vector<Point2> nodes = initial_mesh_.nodes;
  for (std::size_t i = 0; i < nodes.size(); ++i) {
    nodes[i] += u.segment<2>(2 * static_cast<Eigen::Index>(i));
  }
  return nodes;
}

const geometry::TriangleMesh& TissueSimulation::mesh() const {
  return embedded() ? initial_mesh_ : model_->mesh();
}

bool TissueSimulation::needleInTissue() const {
  return embedded() ? track_needle_->inTissue() : needle_->inTissue();
}

double TissueSimulation::tipX() const {
  return embedded() ? track_needle_->tipX() : needle_->tipX();
}

std::optional<Point2> TissueSimulation::tipReference() const {
  if (!embedded()) {
    return needle_->tipReference();
  }
  if (!track_needle_->inTissue()) {
    return std::nullopt;
  }
  return Point2(track_needle_->tipReference());
}

int TissueSimulation::shaftCount() const {
  return embedded() ? track_needle_->lastMove().shaft_points
                    : static_cast<int>(needle_->shaftNodes().size());
}

std::vector<Point2> TissueSimulation::shaftReference() const {
  std::vector<Point2> out;
  if (embedded()) {
    for (const auto& p : track_needle_->shaftReference()) {
      out.emplace_back(p);
    }
    return out;
  }
  for (int node : needle_->shaftNodes()) {
    out.push_back(model_->mesh().nodes[static_cast<std::size_t>(node)]);
  }
  return out;
}

const InsertionStepInfo& TissueSimulation::lastStep() const {
  return embedded() ? track_info_ : needle_->lastStep();
}

namespace {

[[noreturn]] void notOnTrack(const char* what) {
  throw std::logic_error(std::string("TissueSimulation::") + what +
                         ": the embedded track has no node-moving model; use the needle-model "
                         "independent accessors");
}

}  // namespace

const FemModel& TissueSimulation::model() const {
  if (embedded()) {
    notOnTrack("model");
  }
  return *model_;
}

const Integrator& TissueSimulation::integrator() const {
  if (embedded()) {
    notOnTrack("integrator");
  }
  return *integrator_;
}

const NeedleInsertion& TissueSimulation::needle() const {
  if (embedded()) {
    notOnTrack("needle");
  }
  return *needle_;
}

const fem::EmbeddedNeedle<2>& TissueSimulation::trackNeedle() const {
  if (!embedded()) {
    throw std::logic_error("TissueSimulation::trackNeedle: the node-moving model has no track");
  }
  return *track_needle_;
}

}  // namespace needle_guidance::tissue
