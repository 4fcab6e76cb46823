// Benchmark of 3-D tissue: tetrahedral FEM needle insertion and the 3-D rigid seed implant.
// Reports insertion steps per second (CPU, one core) and peak memory against the tetrahedron
// count (5k to 200k; --quick: 5k to 50k), and per scene and target the planned seed error
// measured by an independent full simulation, the planning CPU time, the step convergence
// (halving the step), the unplanned error (aiming straight at the target), the lateral
// correction and what the other cut track (rest_line / follow_tissue) does to the plan; and the
// same targets planned in a 2-D slice of the scene (the sagittal section through the target, meshed
// and simulated by the planar model): how far a 2-D model's errors are from the 3-D ones.
// --model corotational: the corotational insertion at about 50k tetrahedra runs on every scene
// (each meshed to about 50k), not only on the first, and every target of every scene is planned
// in corotational tissue (plans_corotational.csv), each plan checked by an independent full
// simulation at the scene's step. --corotational-plans: only those plans;
// --corotational-step-scale S: the planner's long moves; --corotational-moves: each plan also
// simulated with moves of 2-16 scene steps (the seed against the move length, and its CPU).
// Usage: bench_tissue_3d --out DIR [--quick] [--scene FILE ...] [--model corotational]
//        [--corotational-plans] [--corotational-step-scale S] [--corotational-moves]

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/cpu_time.h"
#include "needle_guidance/package_paths.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/process_usage.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/rigid_planning/rigid_planner.h"
#include "needle_guidance/tissue_3d/offset_planner_3d.h"

namespace ng = needle_guidance;
using needle_guidance::report::peakMb;
namespace t3 = ng::tissue_3d;
using ng::report::jsonNumber;

namespace {

/// A figure for the CSV, empty when undefined (< 0: never computed).
ng::report::Cell orUndefined(double v) {
  return v < 0.0 ? ng::report::Cell(std::string()) : ng::report::Cell(v);
}

/// A length in mm for the CSV, empty when undefined (< 0: never computed).
ng::report::Cell mmOrUndefined(double m) {
  return orUndefined(m < 0.0 ? m : m * 1e3);
}

std::vector<std::string> defaultScenes() {
  std::vector<std::string> files;
  for (const auto& e :
       std::filesystem::directory_iterator(needle_guidance::configDir() / "scenes" / "tissue_3d")) {
    if (e.path().extension() == ".yaml") {
      files.push_back(e.path().string());
    }
  }
  std::sort(files.begin(), files.end());
  return files;
}

struct ScalingRow {
  int tets = 0;
  double steps_per_s = 0.0;
  double factor_cpu_s = 0.0;
  double mesh_cpu_s = 0.0;
  double peak_mb = 0.0;
  double columns_mb = 0.0;
  double insertion_cpu_s = 0.0;
  double corotation_cpu_s = 0.0;  ///< CPU in the corotational updates of the insertion
  int steps = 0;
  int corotation_updates = 0;  ///< corotational fixed-point updates of the insertion
  int rewarps = 0;             ///< refactorisations of the warped stiffness in the insertion
  double refactor_cpu_s = 0.0;
  t3::Vector3 seed_m = t3::Vector3::Constant(std::nan(""));  ///< with_seed: after retraction
};

/// One insertion to the scene's first target at its step (times step_scale); CPU per step.
/// corotational: the same with the corotational elasticity. with_seed: then a seed released at
/// the tip and the needle retracted at the same step (not timed).
ScalingRow scalingRun(const t3::TissueScene3d& scene, double scale, bool corotational = false,
                      double step_scale = 1.0, bool with_seed = false) {
  ScalingRow row;
  t3::TetMeshReport report;
  t3::TetMesh3 mesh = t3::meshTissue3d(scene, {}, scale, &report);
  row.tets = mesh.elementCount();
  row.mesh_cpu_s = report.cpu_s;
  t3::TissueModel3 model(std::move(mesh), scene.materialTable(), corotational);
  row.factor_cpu_s = model.assemblyCpuSeconds();
  const t3::Target3& target = scene.targets.front();
  t3::NeedleInsertion3 needle(model, scene.needle, scene.block_min_m.x(), target.position_m.x());
  const double step = scene.needle.insertion_velocity_m_s * scene.needle.step_s * step_scale;
  const ng::CpuStopwatch clock(ng::CpuStopwatch::Scope::kProcess);
  int steps = 0;
  std::string why;
  for (double s = scene.block_min_m.x() - step; s < target.position_m.x();) {
    s = std::min(s + step, target.position_m.x());
    if (!needle.moveTo(target.position_m.tail<2>(), s, &why)) {
      throw std::runtime_error("scaling run: " + why);
    }
    ++steps;
    row.corotation_updates += needle.lastMove().corotation_updates;
    row.rewarps += needle.lastMove().rewarps;
  }
  const double cpu = clock.seconds();
  row.steps_per_s = steps / std::max(cpu, 1e-9);
  row.insertion_cpu_s = cpu;
  row.peak_mb = peakMb();
  row.columns_mb = model.compliance().memoryBytes() / 1048576.0;
  row.corotation_cpu_s = model.corotationCpuSeconds();
  row.refactor_cpu_s = model.compliance().refactorCpuSeconds();
  row.steps = steps;
  if (with_seed) {
    const int seed = needle.implantSeed(&why).value();
    for (double s = target.position_m.x(); s > scene.block_min_m.x() - step;) {
      s -= step;
      if (!needle.moveTo(target.position_m.tail<2>(), s, &why)) {
        throw std::runtime_error("scaling run, retraction: " + why);
      }
    }
    row.seed_m = needle.seedWorld(seed);
  }
  return row;
}

/// The scaling insertion in corotational tissue at about 50k tetrahedra, at the scene's step
/// and at half of it (the seed's change; halving_m < 0 and the refusal when refused).
struct CorotationalRun {
  std::string scene;
  ScalingRow row;
  double halving_m = -1.0;
  std::string refusal;
};

CorotationalRun corotationalRun50k(const t3::TissueScene3d& scene) {
  CorotationalRun run;
  run.scene = scene.name;
  run.row.steps_per_s = -1.0;
  const double scale = t3::sizeScaleForTets(scene, 5e4);
  try {
    run.row = scalingRun(scene, scale, true, 1.0, true);
    // The run at half the step: its refusal leaves the figures of the converged run defined.
    try {
      run.halving_m = (scalingRun(scene, scale, true, 0.5, true).seed_m - run.row.seed_m).norm();
    } catch (const std::runtime_error& e) {
      run.refusal = std::string("at half the step: ") + e.what();
    }
  } catch (const std::runtime_error& e) {
    run.row.steps_per_s = -1.0;
    run.refusal = e.what();
  }
  std::cout << "  corotational " << scene.name << ", " << run.row.tets
            << " tets: " << run.row.steps_per_s << " steps/s, " << run.row.corotation_updates
            << " updates and " << run.row.rewarps << " refactorisations in " << run.row.steps
            << " steps; halving the step moves the seed by " << run.halving_m * 1e3 << " mm "
            << run.refusal << "\n";
  return run;
}

/// The corotational 50k runs: on every scene, or on the first only; one row each in csv.
struct CorotationalSummary {
  std::vector<CorotationalRun> runs;
  int converged = 0;
  double halving_max_m = -1.0;    ///< over the converged runs (-1: none)
  double steps_per_s_min = -1.0;  ///< over the converged runs (-1: none)
};

CorotationalSummary corotationalRuns(const std::vector<std::string>& files, bool every_scene,
                                     const std::string& csv) {
  ng::report::Table table({"scene", "tets", "steps_per_s", "updates_per_step", "refactorisations",
                           "refactor_cpu_s", "corotation_cpu_fraction", "step_halving_mm",
                           "refusal"});
  CorotationalSummary out;
  const ng::report::Cell undefined{std::string()};
  for (const std::string& file : files) {
    out.runs.push_back(corotationalRun50k(t3::loadTissueScene3d(file)));
    const CorotationalRun& c = out.runs.back();
    const bool ok = c.row.steps_per_s > 0.0;  // the run at the scene's step converged
    table.addRow(
        {c.scene, double(c.row.tets), ok ? ng::report::Cell(c.row.steps_per_s) : undefined,
         ok ? ng::report::Cell(double(c.row.corotation_updates) / std::max(c.row.steps, 1))
            : undefined,
         double(c.row.rewarps), c.row.refactor_cpu_s,
         ok ? ng::report::Cell(c.row.corotation_cpu_s / std::max(c.row.insertion_cpu_s, 1e-9))
            : undefined,
         mmOrUndefined(c.halving_m), c.refusal});
    if (ok && c.refusal.empty()) {  // converged at the step and at half of it
      ++out.converged;
      out.halving_max_m = std::max(out.halving_max_m, c.halving_m);
      out.steps_per_s_min = out.steps_per_s_min < 0.0
                                ? c.row.steps_per_s
                                : std::min(out.steps_per_s_min, c.row.steps_per_s);
    }
    if (!every_scene) {
      break;  // the scaling scene only
    }
  }
  table.writeCsv(csv);
  return out;
}

/// A placed plan of the linear model, to be simulated again with corotational elasticity.
struct PlacedPlan {
  std::string file, target;
  Eigen::Vector2d lateral;
  double tip_x_m = 0.0;
  t3::Vector3 seed_linear;
};

/// What the corotational model changes on the shipped scenes: each linear plan is simulated
/// again (same mesh, same lateral position and depth) in corotational tissue; the seed moves by
/// `change_mm`. Writes corotation.csv; returns the largest change [m] (-1: none simulated).
double corotationChanges(const std::vector<PlacedPlan>& plans, const std::string& csv) {
  ng::report::Table table(
      {"scene", "target", "change_mm", "corotational_cpu_s", "linear_mm", "refusal"});
  double worst = -1.0;
  for (std::size_t i = 0; i < plans.size();) {
    const t3::TissueScene3d scene = t3::loadTissueScene3d(plans[i].file);
    t3::TissueModel3 model(t3::meshTissue3d(scene, {}, 1.0), scene.materialTable(), true);
    t3::OffsetPlanner3 planner(scene, model);
    for (; i < plans.size() && plans[i].file == scene.source; ++i) {
      const PlacedPlan& p = plans[i];
      const ng::CpuStopwatch clock(ng::CpuStopwatch::Scope::kProcess);
      const t3::Target3& target =
          *std::find_if(scene.targets.begin(), scene.targets.end(),
                        [&](const t3::Target3& t) { return t.name == p.target; });
      double change = -1.0;
      std::string refusal;
      try {
        change = (planner.simulateImplant(p.lateral, p.tip_x_m) - p.seed_linear).norm();
        worst = std::max(worst, change);
      } catch (const std::runtime_error& e) {
        refusal = e.what();
      }
      table.addRow({scene.name, p.target, mmOrUndefined(change), clock.seconds(),
                    (p.seed_linear - target.position_m).norm() * 1e3, refusal});
      std::cout << "  corotational " << scene.name << "/" << p.target << ": seed moves "
                << change * 1e3 << " mm " << refusal << "\n";
    }
  }
  table.writeCsv(csv);
  return worst;
}

/// A corotational plan checked by an independent full simulation at the scene's step (the
/// planner's own corotational insertions move by PlannerOptions3::corotational_step_scale
/// steps): the seed's error there and its distance from the planner's verified seed.
struct IndependentCheck {
  double error_m = -1.0;
  double step_error_m = -1.0;
  double cpu_s = 0.0;
  std::string refusal;
  t3::Vector3 seed = t3::Vector3::Zero();  ///< the seed at the scene's step (when error_m >= 0)
};

IndependentCheck independentCheck(t3::OffsetPlanner3& planner, const t3::PlanResult3& r,
                                  const t3::Target3& target) {
  IndependentCheck c;
  const ng::CpuStopwatch clock(ng::CpuStopwatch::Scope::kProcess);
  try {
    c.seed = planner.simulateImplant(r.lateral_m, r.tip_x_m);
    c.error_m = (c.seed - target.position_m).norm();
    c.step_error_m = (c.seed - r.verified_seed_m).norm();
  } catch (const std::runtime_error& e) {
    c.refusal = e.what();
  }
  c.cpu_s = clock.seconds();
  return c;
}

/// --corotational-moves: the move lengths (multiples of the scene's step) at which the plan is
/// simulated again; each seed's distance from the one at the scene's step is a column.
constexpr double kMoveScales[] = {2.0, 4.0, 8.0, 16.0};

/// The plan simulated with moves of each of kMoveScales: per scale, the seed's distance from
/// `reference` (the seed at the scene's step; < 0 undefined: refused) and the simulation's CPU.
std::vector<std::pair<double, double>> moveChanges(t3::OffsetPlanner3& planner,
                                                   const t3::PlanResult3& r,
                                                   const t3::Vector3& reference) {
  std::vector<std::pair<double, double>> out;
  for (double scale : kMoveScales) {
    const ng::CpuStopwatch clock(ng::CpuStopwatch::Scope::kProcess);
    double change = -1.0;
    try {
      change = (planner.simulateImplant(r.lateral_m, r.tip_x_m, scale) - reference).norm();
    } catch (const std::runtime_error& e) {
      std::cout << "    moves x" << scale << " refused: " << e.what() << "\n";
    }
    out.emplace_back(change, clock.seconds());
  }
  return out;
}

/// Every target of every scene planned in corotational tissue (tissue.model forced to
/// corotational, default mesh), each plan checked by an independent full simulation at the
/// scene's step; one row per target in csv. placed: within the tolerance in that simulation.
struct CorotationalPlans {
  int reachable = 0, placed = 0;
  double cpu_max_s = -1.0, error_max_m = -1.0, step_error_max_m = -1.0;
  double simulation_cpu_max_s = -1.0, setup_max_s = -1.0;
  int simulations_max = 0;
};

/// step_scale: the planner's corotational moves (PlannerOptions3::corotational_step_scale; <= 0
/// its default); moves: also simulate each plan at kMoveScales (moveChanges).
CorotationalPlans corotationalPlans(const std::vector<std::string>& files, const std::string& csv,
                                    double step_scale, bool moves) {
  std::vector<std::string> columns{
      "scene",          "target",     "placed",           "verified_mm",       "independent_mm",
      "step_error_mm",  "plan_cpu_s", "simulation_cpu_s", "simulations",       "linear_simulations",
      "holes_verified", "tets",       "setup_cpu_s",      "independent_cpu_s", "refusal"};
  for (double scale : moves ? std::vector<double>(std::begin(kMoveScales), std::end(kMoveScales))
                            : std::vector<double>{}) {
    const std::string x = "x" + std::to_string(static_cast<int>(scale));
    columns.push_back("moves_" + x + "_change_mm");
    columns.push_back("moves_" + x + "_cpu_s");
  }
  ng::report::Table table(columns);
  CorotationalPlans out;
  const double tolerance = t3::PlannerOptions3{}.tolerance_m;
  for (const std::string& file : files) {
    t3::TissueScene3d scene = t3::loadTissueScene3d(file);
    scene.corotational = true;
    t3::TetMesh3 mesh = t3::meshTissue3d(scene, {}, 1.0);
    const int tets = mesh.elementCount();
    t3::TissueModel3 model(std::move(mesh), scene.materialTable(), true);
    t3::PlannerOptions3 options;
    options.unplanned = false;
    if (step_scale > 0.0) {
      options.corotational_step_scale = step_scale;
    }
    t3::OffsetPlanner3 planner(scene, model, options);
    out.setup_max_s = std::max(out.setup_max_s, planner.setupCpuSeconds());
    for (const t3::Target3& target : scene.targets) {
      const t3::PlanResult3 r = planner.plan(target);
      IndependentCheck check;
      if (!r.unreachable) {
        ++out.reachable;
      }
      if (r.placed) {
        check = independentCheck(planner, r, target);
        if (check.error_m >= 0.0 && check.error_m <= tolerance) {
          ++out.placed;
        }
        out.cpu_max_s = std::max(out.cpu_max_s, r.plan_cpu_s);
        out.simulation_cpu_max_s = std::max(out.simulation_cpu_max_s, r.simulation_cpu_s);
        out.error_max_m = std::max(out.error_max_m, check.error_m);
        out.step_error_max_m = std::max(out.step_error_max_m, check.step_error_m);
        out.simulations_max = std::max(out.simulations_max, r.simulations);
      }
      std::vector<ng::report::Cell> row{scene.name,
                                        target.name,
                                        std::string(r.placed        ? "yes"
                                                    : r.unreachable ? "unreachable"
                                                                    : "no"),
                                        mmOrUndefined(r.verified_error_m),
                                        mmOrUndefined(check.error_m),
                                        mmOrUndefined(check.step_error_m),
                                        r.plan_cpu_s,
                                        r.simulation_cpu_s,
                                        double(r.simulations),
                                        double(r.linear_simulations),
                                        double(r.holes_verified),
                                        double(tets),
                                        planner.setupCpuSeconds(),
                                        check.cpu_s,
                                        r.refusal.empty() ? check.refusal : r.refusal};
      if (moves) {
        std::vector<std::pair<double, double>> changes;
        if (check.error_m >= 0.0) {
          changes = moveChanges(planner, r, check.seed);
        }
        changes.resize(std::size(kMoveScales), {-1.0, -1.0});  // undefined: no seed to compare
        for (const auto& [change, cpu] : changes) {
          row.push_back(mmOrUndefined(change));
          row.push_back(orUndefined(cpu));
        }
      }
      model.compliance().clearCache();
      table.addRow(row);
      std::cout << "  corotational plan " << scene.name << "/" << target.name << ": "
                << (r.placed ? "placed" : "not placed") << ", verified " << r.verified_error_m * 1e3
                << " mm, independent " << check.error_m * 1e3 << " mm, " << r.plan_cpu_s
                << " s CPU (simulations " << r.simulation_cpu_s << " s, " << r.simulations
                << " corotational + " << r.linear_simulations << " linear) " << r.refusal
                << std::endl;
    }
  }
  table.writeCsv(csv);
  return out;
}

/// The summary keys of the corotational plans (null when they were not run).
std::string corotationalPlanKeys(const CorotationalPlans* c) {
  auto key = [&](const char* name, bool defined, const std::string& value) {
    return std::string(",\n  \"") + name + "\": " + (c && defined ? value : "null");
  };
  const CorotationalPlans z;
  const CorotationalPlans& p = c ? *c : z;
  return key("corotational_plans_reachable", true, std::to_string(p.reachable)) +
         key("corotational_plans_placed", true, std::to_string(p.placed)) +
         key("corotational_plan_cpu_s_max", p.cpu_max_s >= 0.0, jsonNumber(p.cpu_max_s)) +
         key("corotational_plan_simulation_cpu_s_max", p.simulation_cpu_max_s >= 0.0,
             jsonNumber(p.simulation_cpu_max_s)) +
         key("corotational_plan_simulations_max", true, std::to_string(p.simulations_max)) +
         key("corotational_planned_error_mm_max", p.error_max_m >= 0.0,
             jsonNumber(p.error_max_m * 1e3)) +
         key("corotational_plan_step_error_mm_max", p.step_error_max_m >= 0.0,
             jsonNumber(p.step_error_max_m * 1e3)) +
         key("corotational_plan_setup_cpu_s_max", p.setup_max_s >= 0.0, jsonNumber(p.setup_max_s));
}

constexpr const char* kCorotationalPlanPlot =
    R"json({"csv": "plans_corotational.csv", "x": "plan_cpu_s", "y": "independent_mm", "group": "scene",
  "filter": {"placed": "yes"}, "title": "Corotational plans: seed error (independent simulation) vs planning CPU time",
  "points": true, "png": "corotational_plan_error_vs_cpu.png"})json";

/// The section of region r of the 3-D scene in the plane z = z_m as a polygon (x, y), traced by
/// rays from an interior point of the section, each ending where another region (or the block's
/// outside) begins, less margin_m so sections of neighbouring regions do not touch. Exact for
/// sections star-shaped from that point (ellipsoids); nullopt when the plane misses the region.
std::optional<ng::geometry::Polygon> regionSection(const t3::TissueScene3d& scene,
                                                   const t3::RegionLocator3& locator, int r,
                                                   double z_m, double margin_m) {
  auto label = [&](const Eigen::Vector2d& p) {
    return locator.regionAt(t3::Vector3(p.x(), p.y(), z_m));
  };
  const double grid = 1e-3;
  std::vector<Eigen::Vector2d> inside;
  for (double x = scene.block_min_m.x() + grid / 2; x < scene.block_max_m.x(); x += grid) {
    for (double y = scene.block_min_m.y() + grid / 2; y < scene.block_max_m.y(); y += grid) {
      if (label({x, y}) == r) {
        inside.emplace_back(x, y);
      }
    }
  }
  if (inside.size() < 4) {
    return std::nullopt;
  }
  Eigen::Vector2d c = Eigen::Vector2d::Zero();
  for (const auto& p : inside) {
    c += p / double(inside.size());
  }
  if (label(c) != r) {
    c = *std::min_element(inside.begin(), inside.end(), [&](const auto& a, const auto& b) {
      return (a - c).squaredNorm() < (b - c).squaredNorm();
    });
  }
  const int rays = 72;
  const double step = 5e-4;
  std::vector<Eigen::Vector2d> vertices;
  for (int k = 0; k < rays; ++k) {
    const double a = 2.0 * M_PI * k / rays;
    const Eigen::Vector2d d(std::cos(a), std::sin(a));
    double lo = 0.0, hi = step;
    while (label(c + hi * d) == r) {
      lo = hi;
      hi += step;
    }
    for (int i = 0; i < 8; ++i) {
      const double mid = 0.5 * (lo + hi);
      (label(c + mid * d) == r ? lo : hi) = mid;
    }
    const double radius = std::max(lo - margin_m, 0.2 * lo);
    if (radius > 1e-5) {
      vertices.push_back(c + radius * d);
    }
  }
  if (vertices.size() < 3) {
    return std::nullopt;
  }
  return ng::geometry::Polygon(vertices);
}

/// The planar scene of the section z = z_m of a 3-D scene: the block's x-y rectangle, its
/// fixed faces, each region's section (fixed regions rigid), the needle and its interaction,
/// the stage's (or template's) height range, a slice thickness of 1 cm (the planar scenes'
/// default) and the 3-D planner's tolerance.
ng::scene::Scene sliceScene(const t3::TissueScene3d& s, double z_m, double tolerance_m) {
  namespace sc = ng::scene;
  sc::Scene out;
  out.name = s.name + "_slice";
  out.source = s.source;
  out.workspace_min = s.block_min_m.head<2>();
  out.workspace_max = s.block_max_m.head<2>();
  out.thickness_m = 0.01;
  out.models.tissue = sc::TissueModel::kQuasiStatic;
  auto material = [](const std::string& name, const ng::fem::Material& m) {
    sc::Material out_m;
    out_m.name = name;
    out_m.young_modulus_Pa = m.young_modulus_Pa;
    out_m.poisson_ratio = m.poisson_ratio;
    return out_m;
  };
  out.materials.push_back(material("block", s.block_material));
  out.background_material = "block";
  const t3::RegionLocator3 locator(s);
  for (std::size_t r = 0; r < s.regions.size(); ++r) {
    const t3::Region3& region = s.regions[r];
    const auto polygon = regionSection(s, locator, int(r), z_m, 3e-4);
    if (!polygon) {
      continue;
    }
    out.materials.push_back(material(region.name, region.material));
    sc::Region planar;
    planar.name = region.name;
    planar.material = region.name;
    planar.polygon = *polygon;
    planar.rigid = region.fixed;
    out.regions.push_back(planar);
  }
  const Eigen::Vector2d lo = out.workspace_min, hi = out.workspace_max;
  const std::vector<std::pair<std::string, ng::geometry::Segment>> faces = {
      {"x_min", {{lo.x(), lo.y()}, {lo.x(), hi.y()}}},
      {"x_max", {{hi.x(), lo.y()}, {hi.x(), hi.y()}}},
      {"y_min", {{lo.x(), lo.y()}, {hi.x(), lo.y()}}},
      {"y_max", {{lo.x(), hi.y()}, {hi.x(), hi.y()}}}};
  for (const auto& [name, segment] : faces) {
    if (std::find(s.fixed_faces.begin(), s.fixed_faces.end(), name) != s.fixed_faces.end()) {
      out.boundary.push_back({name, segment, sc::BoundaryCondition::kFixed});
    }
  }
  const t3::Workspace3& w = s.workspace;
  const double reach =
      w.template_spacing_m * std::max(0, (w.template_rows - 1)) * (w.use_template ? 1.0 : 0.0);
  out.needle.min_height_m = std::max(lo.y(), w.use_template ? w.template_origin_m.x() : w.y_min_m);
  out.needle.max_height_m =
      std::min(hi.y(), w.use_template ? w.template_origin_m.x() + reach : w.y_max_m);
  out.needle.max_depth_m = w.max_tip_x_m;
  out.needle.insertion_velocity_m_s = s.needle.insertion_velocity_m_s;
  out.needle.cutting_force_N = s.needle.cutting_force_N;
  out.needle.cut_length_m = 1e-4;
  out.needle.static_friction_N_per_m = s.needle.static_friction_N_per_m;
  out.needle.kinetic_friction_N_per_m = s.needle.kinetic_friction_N_per_m;
  out.needle.stick_velocity_m_s = s.needle.stick_velocity_m_s;
  out.needle.diameter_m = s.needle.diameter_m;
  out.needle.placement_tolerance_m = tolerance_m;
  return out;
}

/// Unplanned and planned (verified) seed errors of one target in the 2-D slice through it [m];
/// < 0 where the planar planner refuses (reason in `why`).
struct SliceErrors {
  double unplanned_m = -1.0;
  double planned_m = -1.0;
  std::string why;
};

SliceErrors sliceErrors(const t3::TissueScene3d& scene, const t3::Target3& target, bool plan_too) {
  SliceErrors e;
  try {
    const ng::rigid_planning::RigidPlanner planner(
        sliceScene(scene, target.position_m.z(), t3::PlannerOptions3{}.tolerance_m), {});
    const ng::geometry::Point2 t = target.position_m.head<2>();
    const auto unplanned = planner.unplanned(t);
    if (unplanned) {
      e.unplanned_m = unplanned.predicted_error_m;
    } else {
      e.why = unplanned.message;
    }
    if (!plan_too) {
      return e;
    }
    const auto plan = planner.plan(t);
    if (plan && std::isfinite(plan.verified_error_m)) {
      e.planned_m = plan.verified_error_m;
    } else if (e.why.empty()) {
      e.why = plan.message;
    }
  } catch (const std::exception& ex) {
    e.why = ex.what();
  }
  return e;
}

/// The plan's seed at the scene's step: the verified seed, or in corotational tissue (where the
/// planner's insertions move by longer steps) an independent full simulation at the scene's step.
t3::Vector3 seedAtSceneStep(t3::OffsetPlanner3& planner, const t3::TissueScene3d& scene,
                            const t3::PlanResult3& r) {
  return scene.corotational ? planner.simulateImplant(r.lateral_m, r.tip_x_m) : r.verified_seed_m;
}

/// This tool's own options (the rest go to the benches' common parser).
struct OwnOptions {
  bool corotational_every_scene = false;  ///< --model corotational
  bool corotational_plans_only = false;   ///< --corotational-plans
  double corotational_step_scale = 0.0;   ///< --corotational-step-scale S (<= 0: the planner's)
  bool corotational_moves = false;        ///< --corotational-moves
};

/// Takes this tool's options out of argv; the others are appended to rest. False (with the
/// reason on stderr) for a bad --model or --corotational-step-scale value.
bool parseOwnOptions(int argc, char** argv, OwnOptions& own, std::vector<char*>& rest) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--corotational-plans") {
      own.corotational_plans_only = true;
    } else if (a == "--corotational-moves") {
      own.corotational_moves = true;
    } else if (a == "--corotational-step-scale" && i + 1 < argc) {
      char* end = nullptr;
      own.corotational_step_scale = std::strtod(argv[++i], &end);
      if (end == argv[i] || *end != '\0' || !(own.corotational_step_scale > 0.0) ||
          !std::isfinite(own.corotational_step_scale)) {
        std::cerr << "bench_tissue_3d: --corotational-step-scale takes a number > 0, not `"
                  << argv[i] << "`\n";
        return false;
      }
    } else if (a == "--model" && i + 1 < argc) {
      if (std::string(argv[++i]) != "corotational") {
        std::cerr << "bench_tissue_3d: --model takes `corotational`, not `" << argv[i] << "`\n";
        return false;
      }
      own.corotational_every_scene = true;
    } else {
      rest.push_back(argv[i]);
    }
  }
  return true;
}

/// --corotational-plans: the corotational plans of every scene, their summary keys and plot.
void writeCorotationalPlansOnly(const std::vector<std::string>& files,
                                const ng::report::BenchArgs& args, const OwnOptions& own) {
  const CorotationalPlans c =
      corotationalPlans(files, args.out_dir + "/plans_corotational.csv",
                        own.corotational_step_scale, own.corotational_moves);
  ng::report::writeTextFile(args.out_dir + "/summary.json",
                            "{\n  \"benchmark\": \"tissue_3d\",\n  \"quick\": " +
                                std::string(args.quick ? "true" : "false") +
                                corotationalPlanKeys(&c) + "\n}\n");
  ng::report::writeTextFile(args.out_dir + "/plot.json",
                            std::string("[") + kCorotationalPlanPlot + "]");
}

}  // namespace

int main(int argc, char** argv) {
  constexpr const char* kUsage =
      "usage: bench_tissue_3d --out DIR [--quick] [--scene FILE]... [--model corotational]\n"
      "       [--corotational-plans] [--corotational-step-scale S] [--corotational-moves]\n"
      "Writes DIR/summary.json, its CSVs and plot.json (scripts/bench tissue_3d runs it and draws "
      "the plots).\n--model corotational: the corotational insertion at about 50k tetrahedra "
      "runs on every scene, not only on the first (corotational_50k.csv), and every target is "
      "planned in corotational tissue (plans_corotational.csv).\n--corotational-plans: only "
      "those corotational plans (plans_corotational.csv and their summary keys).\n"
      "--corotational-step-scale S: the planner's corotational moves, S times the scene's step "
      "(default: the planner's).\n--corotational-moves: each corotational plan also simulated "
      "with moves of 2, 4, 8 and 16 steps (the seed's change from the scene's step, and the "
      "CPU).\n";
  if (ng::report::helpRequested(argc, argv)) {
    std::cout << kUsage;
    return 0;
  }
  // --model corotational and --corotational-plans are this tool's own options; the rest are
  // the benches' common ones.
  OwnOptions own;
  std::vector<char*> rest{argv[0]};
  if (!parseOwnOptions(argc, argv, own, rest)) {
    std::cerr << kUsage;
    return 2;
  }
  const auto args =
      ng::report::parseBenchArgs(static_cast<int>(rest.size()), rest.data(), "bench_tissue_3d");
  if (!args) {
    return 2;
  }
  try {
    const std::vector<std::string> files = args->scenes.empty() ? defaultScenes() : args->scenes;
    if (own.corotational_plans_only) {
      writeCorotationalPlansOnly(files, *args, own);
      return 0;
    }
    // ---- steps/s and memory against the tetrahedron count --------------------------------
    const t3::TissueScene3d base = t3::loadTissueScene3d(files.front());
    const t3::TetMesh3 probe = t3::meshTissue3d(base, {}, 1.0);
    const std::vector<double> wanted = args->quick ? std::vector<double>{5e3, 2e4, 5e4}
                                                   : std::vector<double>{5e3, 2e4, 5e4, 1e5, 2e5};
    ng::report::Table scaling(
        {"tets", "steps_per_s", "factor_cpu_s", "mesh_cpu_s", "peak_mb", "columns_mb"});
    std::vector<ScalingRow> rows;
    for (double n : wanted) {
      const ScalingRow r = scalingRun(base, t3::sizeScaleForTets(base, n, probe.elementCount()));
      rows.push_back(r);
      scaling.addRow(
          {double(r.tets), r.steps_per_s, r.factor_cpu_s, r.mesh_cpu_s, r.peak_mb, r.columns_mb});
      std::cout << "  " << r.tets << " tets: " << r.steps_per_s << " steps/s, factor "
                << r.factor_cpu_s << " s, peak " << r.peak_mb << " MB\n";
    }
    auto nearestRow = [&](double n) {
      return *std::min_element(rows.begin(), rows.end(), [&](const auto& a, const auto& b) {
        return std::abs(std::log(a.tets / n)) < std::abs(std::log(b.tets / n));
      });
    };
    // ---- planning per scene ---------------------------------------------------------------
    ng::report::Table plans({"scene", "target", "placed", "predicted_mm", "verified_mm",
                             "unplanned_mm", "step_halving_mm", "plan_cpu_s", "simulations", "tets",
                             "track", "lateral_correction_mm", "other_track_error_mm", "hole",
                             "holes_verified", "nearest_hole_mm", "refusal"});
    ng::report::Table slices({"scene", "target", "unplanned_3d_mm", "unplanned_slice_mm",
                              "planned_3d_mm", "planned_slice_mm", "slice_refusal"});
    double slice_unplanned_diff_max = -1.0, slice_unplanned_diff_sum = 0.0;
    double unplanned_3d_sum = 0.0, unplanned_slice_sum = 0.0, slice_planned_max = -1.0;
    int slice_pairs = 0;
    double worst_error = 0.0, worst_cpu = 0.0, worst_halving = 0.0;
    double worst_lateral = 0.0, worst_straight_on_follow = -1.0, worst_track_difference = -1.0;
    int reachable = 0, placed = 0;
    std::vector<PlacedPlan> placed_plans;
    for (const std::string& file : files) {
      const t3::TissueScene3d scene = t3::loadTissueScene3d(file);
      t3::TetMesh3 mesh = t3::meshTissue3d(scene, {}, 1.0);
      const int tets = mesh.elementCount();
      t3::TissueModel3 model(std::move(mesh), scene.materialTable(), scene.corotational);
      t3::OffsetPlanner3 planner(scene, model);
      // The same tissue with the other cut track: what the track model changes in each plan.
      t3::TissueScene3d other_scene = scene;
      other_scene.needle.follow_tissue = !scene.needle.follow_tissue;
      t3::OffsetPlanner3 other_track(other_scene, model);
      for (const t3::Target3& target : scene.targets) {
        const t3::PlanResult3 r = planner.plan(target);
        double halving = -1.0, lateral_correction = -1.0, other_error = -1.0;
        if (!r.unreachable) {
          ++reachable;
        }
        if (r.placed) {
          ++placed;
          const t3::Vector3 full = seedAtSceneStep(planner, scene, r);
          const t3::Vector3 half = planner.simulateImplant(r.lateral_m, r.tip_x_m, 0.5);
          halving = (half - full).norm();
          worst_halving = std::max(worst_halving, halving);
          worst_error = std::max(worst_error,
                                 std::max(r.verified_error_m, (full - target.position_m).norm()));
          worst_cpu = std::max(worst_cpu, r.plan_cpu_s);
          lateral_correction = (r.lateral_m - target.position_m.tail<2>()).norm();
          worst_lateral = std::max(worst_lateral, lateral_correction);
          try {
            const t3::Vector3 other = other_track.simulateImplant(r.lateral_m, r.tip_x_m);
            other_error = (other - target.position_m).norm();
            worst_track_difference =
                std::max(worst_track_difference, (other - r.verified_seed_m).norm());
          } catch (const std::runtime_error& e) {
            std::cout << "  other track refused: " << e.what() << "\n";
          }
          if (!scene.needle.follow_tissue && other_error >= 0.0) {
            worst_straight_on_follow = std::max(worst_straight_on_follow, other_error);
          }
          if (!scene.corotational) {
            placed_plans.push_back(
                {scene.source, target.name, r.lateral_m, r.tip_x_m, r.verified_seed_m});
          }
        }
        model.compliance().clearCache();
        const SliceErrors slice = sliceErrors(scene, target, !args->quick);
        if (slice.unplanned_m >= 0.0 && r.unplanned_error_m >= 0.0) {
          const double diff = std::abs(slice.unplanned_m - r.unplanned_error_m);
          slice_unplanned_diff_max = std::max(slice_unplanned_diff_max, diff);
          slice_unplanned_diff_sum += diff;
          unplanned_3d_sum += r.unplanned_error_m;
          unplanned_slice_sum += slice.unplanned_m;
          ++slice_pairs;
        }
        slice_planned_max = std::max(slice_planned_max, slice.planned_m);
        slices.addRow({scene.name, target.name, mmOrUndefined(r.unplanned_error_m),
                       mmOrUndefined(slice.unplanned_m), mmOrUndefined(r.verified_error_m),
                       mmOrUndefined(slice.planned_m), slice.why});
        plans.addRow({scene.name, target.name,
                      std::string(r.placed        ? "yes"
                                  : r.unreachable ? "unreachable"
                                                  : "no"),
                      mmOrUndefined(r.predicted_error_m), mmOrUndefined(r.verified_error_m),
                      mmOrUndefined(r.unplanned_error_m), mmOrUndefined(halving), r.plan_cpu_s,
                      double(r.simulations), double(tets),
                      std::string(scene.needle.follow_tissue ? "follow_tissue" : "rest_line"),
                      mmOrUndefined(lateral_correction), mmOrUndefined(other_error),
                      r.hole.x() < 0
                          ? std::string()
                          : std::to_string(r.hole.x()) + ":" + std::to_string(r.hole.y()),
                      double(r.holes_verified), mmOrUndefined(r.nearest_hole_error_m), r.refusal});
        std::cout << "  " << scene.name << "/" << target.name << ": "
                  << (r.placed ? "placed" : "not placed") << ", " << r.plan_cpu_s << " s CPU "
                  << r.refusal << "\n";
      }
    }
    // ---- corotational elasticity: its cost at ~50k tetrahedra and what it changes ----------
    const ScalingRow r50_linear = nearestRow(5e4);
    const CorotationalSummary corot = corotationalRuns(files, own.corotational_every_scene,
                                                       args->out_dir + "/corotational_50k.csv");
    const ScalingRow r50_corot = corot.runs.front().row;
    const double corot_halving = corot.runs.front().halving_m;
    std::cout << "  linear at " << r50_linear.tets << " tets: " << r50_linear.steps_per_s
              << " steps/s; corotational converged on " << corot.converged << " of "
              << corot.runs.size() << " scenes\n";
    const double corot_change = corotationChanges(placed_plans, args->out_dir + "/corotation.csv");
    CorotationalPlans corot_plans;
    if (own.corotational_every_scene) {
      corot_plans = corotationalPlans(files, args->out_dir + "/plans_corotational.csv",
                                      own.corotational_step_scale, own.corotational_moves);
    }
    scaling.writeCsv(args->out_dir + "/scaling.csv");
    plans.writeCsv(args->out_dir + "/plans.csv");
    slices.writeCsv(args->out_dir + "/slice_vs_3d.csv");
    auto mmKey = [](bool defined, double m) { return defined ? jsonNumber(m * 1e3) : "null"; };
    const ScalingRow r50 = nearestRow(5e4);
    const ScalingRow r200 = nearestRow(2e5);
    std::ostringstream json;
    json << "{\n  \"benchmark\": \"tissue_3d\",\n  \"quick\": " << (args->quick ? "true" : "false")
         << ",\n  \"tets_50k\": " << r50.tets
         << ",\n  \"steps_per_s_50k_tets\": " << jsonNumber(r50.steps_per_s)
         << ",\n  \"tets_200k\": "
         << (args->quick ? std::string("null") : std::to_string(r200.tets))
         << ",\n  \"peak_mb_200k_tets\": "
         << (args->quick ? std::string("null") : jsonNumber(r200.peak_mb))
         << ",\n  \"planned_error_mm_max_3d\": "
         << (placed > 0 ? jsonNumber(worst_error * 1e3) : "null")
         << ",\n  \"reachable_placed_fraction_3d\": "
         << (reachable > 0 ? jsonNumber(double(placed) / reachable) : "null")
         << ",\n  \"reachable_targets_3d\": " << reachable
         << ",\n  \"placed_targets_3d\": " << placed
         << ",\n  \"plan_cpu_s_max_3d\": " << (placed > 0 ? jsonNumber(worst_cpu) : "null")
         << ",\n  \"step_halving_change_mm_max_3d\": "
         << (placed > 0 ? jsonNumber(worst_halving * 1e3) : "null")
         << ",\n  \"lateral_correction_mm_max_3d\": " << mmKey(placed > 0, worst_lateral)
         << ",\n  \"straight_plan_error_mm_max_follow\": "
         << mmKey(worst_straight_on_follow >= 0.0, worst_straight_on_follow)
         << ",\n  \"track_difference_mm_max_3d\": "
         << mmKey(worst_track_difference >= 0.0, worst_track_difference)
         << ",\n  \"slice_vs_3d_targets\": " << slice_pairs
         << ",\n  \"unplanned_error_mm_mean_3d\": "
         << mmKey(slice_pairs > 0, unplanned_3d_sum / std::max(slice_pairs, 1))
         << ",\n  \"unplanned_error_mm_mean_slice\": "
         << mmKey(slice_pairs > 0, unplanned_slice_sum / std::max(slice_pairs, 1))
         << ",\n  \"slice_vs_3d_unplanned_error_mm_mean\": "
         << mmKey(slice_pairs > 0, slice_unplanned_diff_sum / std::max(slice_pairs, 1))
         << ",\n  \"slice_vs_3d_unplanned_error_mm_max\": "
         << mmKey(slice_pairs > 0, slice_unplanned_diff_max)
         << ",\n  \"planned_error_mm_max_slice\": "
         << mmKey(slice_planned_max >= 0.0, slice_planned_max)
         << ",\n  \"tets_50k_corotational\": " << r50_corot.tets
         << ",\n  \"steps_per_s_50k_tets_corotational\": "
         << (r50_corot.steps_per_s > 0.0 ? jsonNumber(r50_corot.steps_per_s) : "null")
         << ",\n  \"corotation_cpu_fraction_50k\": "
         << (r50_corot.steps_per_s > 0.0 ? jsonNumber(r50_corot.corotation_cpu_s /
                                                      std::max(r50_corot.insertion_cpu_s, 1e-9))
                                         : "null")
         << ",\n  \"corotation_updates_per_step_50k\": "
         << (r50_corot.steps > 0
                 ? jsonNumber(double(r50_corot.corotation_updates) / r50_corot.steps)
                 : "null")
         << ",\n  \"corotation_refactorisations_50k\": "
         << (r50_corot.steps > 0 ? std::to_string(r50_corot.rewarps) : "null")
         << ",\n  \"corotation_refactor_cpu_s_50k\": "
         << (r50_corot.steps > 0 ? jsonNumber(r50_corot.refactor_cpu_s) : "null")
         << ",\n  \"corotational_step_halving_mm_50k\": "
         << mmKey(corot_halving >= 0.0, corot_halving)
         << ",\n  \"corotational_seed_change_mm_max\": " << mmKey(corot_change >= 0.0, corot_change)
         << ",\n  \"corotational_50k_scenes\": " << corot.runs.size()
         << ",\n  \"corotational_50k_converged\": " << corot.converged
         << ",\n  \"steps_per_s_50k_tets_corotational_min\": "
         << (corot.converged > 0 ? jsonNumber(corot.steps_per_s_min) : "null")
         << ",\n  \"corotational_step_halving_mm_50k_max\": "
         << mmKey(corot.halving_max_m >= 0.0, corot.halving_max_m)
         << corotationalPlanKeys(own.corotational_every_scene ? &corot_plans : nullptr) << "\n}\n";
    ng::report::writeTextFile(args->out_dir + "/summary.json", json.str());
    ng::report::writeTextFile(
        args->out_dir + "/plot.json",
        std::string(R"json([{"csv": "scaling.csv", "x": "tets", "y": "steps_per_s",
  "title": "Insertion steps per second (CPU, one core) vs tetrahedra", "logx": true, "logy": true,
  "png": "steps_per_s_vs_tets.png"},
 {"csv": "scaling.csv", "x": "tets", "y": "peak_mb", "title": "Peak memory vs tetrahedra",
  "logx": true, "logy": true, "png": "peak_mb_vs_tets.png"},
 {"csv": "plans.csv", "x": "plan_cpu_s", "y": "verified_mm", "group": "scene", "filter": {"placed": "yes"},
  "title": "Planned seed error (independent simulation) vs planning CPU time",
  "points": true, "logy": true, "png": "plan_error_vs_cpu.png"},
 {"csv": "slice_vs_3d.csv", "x": "unplanned_3d_mm", "y": "unplanned_slice_mm", "group": "scene",
  "title": "Unplanned seed error: 2-D slice vs 3-D (same targets)", "points": true,
  "png": "slice_vs_3d_unplanned.png"})json") +
            (own.corotational_every_scene ? std::string(",\n ") + kCorotationalPlanPlot
                                          : std::string()) +
            "]");
    std::cout << plans.toText();
  } catch (const std::exception& e) {
    std::cerr << "bench_tissue_3d: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
