// The cost of one corotational update in 3-D tissue (dissertation 2.2.1; docs/tissue_3d.md,
// "Cost of one update"): on the state of an insertion into a scene's first target, the CPU of
// the element pass (fem::CorotationalForces::correction), a solve with the factor, one update
// (the pass and its solve), the needle's field (its forces' displacement, from the cached
// compliance columns of the nodes they act on), the warped stiffness's assembly, a
// refactorisation, a compliance column (batched) and the element pass again against the warped
// stiffness's rotations. Each part is repeated on the same state; CPU time of the process.
// Usage: corotational_update_cost SCENE [TETS] [DEPTH_FRACTION] [REPEATS]
//   TETS: mesh the scene to about this many tetrahedra (0: the scene's default mesh);
//   DEPTH_FRACTION: the insertion's depth as a fraction of the first target's (default 0.7),
//   by moves of 8 scene steps; REPEATS: repetitions of each part (default 20).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <string>
#include <vector>

#include "needle_guidance/cpu_time.h"
#include "needle_guidance/fem/corotation.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/tissue_3d/needle_insertion_3d.h"
#include "needle_guidance/tissue_3d/scene_tissue_3d.h"
#include "needle_guidance/tissue_3d/tet_mesh_3d.h"

namespace ng = needle_guidance;
namespace t3 = needle_guidance::tissue_3d;
namespace fem = needle_guidance::fem;

namespace {

constexpr double kMoveSteps = 8.0;  // the planner's corotational moves, in scene steps
constexpr int kColumns = 288;       // three batches of compliance columns

/// Mean CPU milliseconds of f over repeats calls.
template <typename F>
double meanMs(int repeats, F&& f) {
  const ng::CpuStopwatch clock(ng::CpuStopwatch::Scope::kProcess);
  for (int i = 0; i < repeats; ++i) {
    f();
  }
  return 1e3 * clock.seconds() / repeats;
}

}  // namespace

int main(int argc, char** argv) {
  constexpr const char* kUsage =
      "usage: corotational_update_cost SCENE [TETS] [DEPTH_FRACTION] [REPEATS]\n"
      "The CPU of a corotational update's parts on the state of an insertion into SCENE's first "
      "target (TETS: about this many tetrahedra, 0 the default mesh; DEPTH_FRACTION of the "
      "target's depth, default 0.7; REPEATS per part, default 20).\n";
  if (ng::report::helpRequested(argc, argv) || argc < 2) {
    std::fputs(kUsage, argc < 2 ? stderr : stdout);
    return argc < 2 ? 2 : 0;
  }
  const double tets = argc > 2 ? std::atof(argv[2]) : 0.0;
  const double fraction = argc > 3 ? std::atof(argv[3]) : 0.7;
  const int repeats = argc > 4 ? std::atoi(argv[4]) : 20;
  if (!(tets >= 0.0) || !(fraction >= 0.0 && fraction <= 1.0) || repeats < 1) {
    std::fprintf(stderr,
                 "corotational_update_cost: TETS >= 0, DEPTH_FRACTION in [0, 1] and "
                 "REPEATS >= 1\n%s",
                 kUsage);
    return 2;
  }
  try {
    const t3::TissueScene3d scene = t3::loadTissueScene3d(argv[1]);
    t3::TetMesh3 mesh =
        t3::meshTissue3d(scene, {}, tets > 0.0 ? t3::sizeScaleForTets(scene, tets) : 1.0);
    const int n_tets = mesh.elementCount();
    t3::TissueModel3 model(std::move(mesh), scene.materialTable(), true);
    const t3::Target3& target = scene.targets.front();
    t3::NeedleInsertion3 needle(model, scene.needle, scene.block_min_m.x(), target.position_m.x());
    const double step = kMoveSteps * scene.needle.insertion_velocity_m_s * scene.needle.step_s;
    const double entry_x = scene.block_min_m.x();
    const double depth = entry_x + fraction * (target.position_m.x() - entry_x);
    const ng::CpuStopwatch insertion(ng::CpuStopwatch::Scope::kProcess);
    int updates = 0;
    for (double s = entry_x - step; s < depth;) {
      s = std::min(s + step, depth);
      std::string why;
      if (!needle.moveTo(target.position_m.tail<2>(), s, &why)) {
        std::fprintf(stderr, "corotational_update_cost: the insertion was refused: %s\n",
                     why.c_str());
        return 1;
      }
      updates += needle.lastMove().corotation_updates;
    }
    const double insertion_s = insertion.seconds();
    const Eigen::VectorXd u = needle.displacementField();

    fem::CorotationalForces<3> forces(model.mesh(), scene.materialTable());
    Eigen::VectorXd g;
    const double pass_ms = meanMs(repeats, [&] { g = forces.correction(u); });
    Eigen::VectorXd x;
    const double solve_ms = meanMs(repeats, [&] { x = model.compliance().solve(g); });
    const double field_ms = meanMs(repeats, [&] { x = needle.displacementField(); });
    const double update_ms = meanMs(repeats, [&] { x = model.corotationDisplacement(u); });
    forces.warpedStiffness(u);  // the first call also builds the sparsity pattern
    fem::SparseMatrix warped;
    const double assembly_ms = meanMs(3, [&] { warped = forces.warpedStiffness(u); });
    // The pass against the warped stiffness's rotations, as between refactorisations.
    const double warped_pass_ms = meanMs(repeats, [&] { g = forces.correction(u); });
    const double refactor_ms = meanMs(1, [&] { model.compliance().refactor(warped); });
    std::vector<int> dofs;
    for (int i = 0; i < kColumns; ++i) {
      dofs.push_back(static_cast<int>((7919LL * i) % model.compliance().dofCount()));
    }
    const double columns_ms = meanMs(1, [&] { model.compliance().require(dofs); });
    std::printf(
        "%s: %d tetrahedra, insertion to %.1f mm by moves of %.1f mm: %.2f s CPU, %d updates\n"
        "element pass %.2f ms, solve %.2f ms, pass and solve %.2f ms, the needle's field %.2f ms "
        "(its cached columns); an update (the field, the pass and a solve) about %.1f ms\n"
        "factor %.0f entries\n"
        "warped stiffness assembly %.1f ms, refactorisation %.3f s, compliance column %.3f ms "
        "(%d in batches)\n"
        "element pass against the warped stiffness's rotations %.2f ms (%d of %d elements "
        "turned)\n",
        scene.name.c_str(), n_tets, 1e3 * depth, 1e3 * step, insertion_s, updates, pass_ms,
        solve_ms, update_ms, field_ms, field_ms + pass_ms + solve_ms,
        model.compliance().factorEntries(), assembly_ms, 1e-3 * refactor_ms,
        columns_ms / std::max(1, model.compliance().cachedColumns()),
        model.compliance().cachedColumns(), warped_pass_ms, forces.warpedElements(), n_tets);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "corotational_update_cost: %s\n", e.what());
    return 1;
  }
  return 0;
}
