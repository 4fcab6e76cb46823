// Integrators: constraint reactions, changing prescribed sets and model changes (moveNode)
// against from-scratch solves. The last two exercise the cached factorisation machinery
// (row deletions/additions and low-rank updates of the factor).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>

#include "fem_test_support.h"
#include "needle_guidance/tissue/integrator.h"

namespace needle_guidance::tissue {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): test fixtures

constexpr double kForceTol_N = 1e-9;   // reactions of O(1) N forces
constexpr double kSolutionRel = 1e-9;  // relative to the solution's max norm
constexpr unsigned kSeed = 4242;
constexpr double kDt_s = 1e-3;

ElementMaterial tissue(double e_pa = 60e3, double nu = 0.45) {
  return material(e_pa, nu, 1.0, 0.002, 1050.0);
}

/// Left and bottom edges fixed.
std::vector<int> fixedEdges(const geometry::TriangleMesh& mesh) {
  return fixedDofsWhere(mesh, [](const Point2& p) { return p.x() < 1e-12 || p.y() < 1e-12; });
}

double relError(const Eigen::VectorXd& a, const Eigen::VectorXd& b) {
  return (a - b).lpNorm<Eigen::Infinity>() / std::max(b.lpNorm<Eigen::Infinity>(), 1e-300);
}

TEST(IntegratorReactions, ReactionEqualsAppliedForceOneAndTwoElements) {
  for (int n_elements : {1, 2}) {
    geometry::TriangleMesh mesh;
    mesh.nodes = {Point2(0, 0), Point2(0.01, 0), Point2(0.01, 0.01), Point2(0, 0.01)};
    mesh.triangles = {{0, 1, 2}};
    if (n_elements == 2)
      mesh.triangles.push_back({0, 2, 3});
    mesh.triangle_region.assign(mesh.triangles.size(), 0);
    mesh.region_names = {"tissue"};
    if (n_elements == 1)
      mesh.nodes.pop_back();
    const FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), tissue()));
    std::vector<int> fixed = {dofX(0), dofY(0), dofX(2)};
    if (n_elements == 2)
      fixed.push_back(dofX(3));
    for (IntegratorKind kind : {IntegratorKind::kQuasiStatic, IntegratorKind::kNewmark}) {
      auto integ = makeIntegrator(kind, model, fixed);
      // Apply a force at node 1, then prescribe the displacement it produced: the constraint
      // must supply exactly that force. Newmark at a huge step is quasi-static.
      const double dt_s = kind == IntegratorKind::kNewmark ? 1e6 : kDt_s;
      Eigen::VectorXd f = Eigen::VectorXd::Zero(model.dofCount());
      f(dofX(1)) = 0.7;
      f(dofY(1)) = -0.3;
      Eigen::VectorXd reactions;
      ASSERT_TRUE(integ->step(dt_s, f, {}, reactions));
      EXPECT_EQ(reactions.size(), 0);
      const Eigen::VectorXd u_force = integ->displacement();
      auto integ2 = makeIntegrator(kind, model, fixed);
      Prescribed p{{dofX(1), dofY(1)}, {u_force(dofX(1)), u_force(dofY(1))}};
      ASSERT_TRUE(integ2->step(dt_s, Eigen::VectorXd::Zero(model.dofCount()), p, reactions));
      ASSERT_EQ(reactions.size(), 2);
      EXPECT_NEAR(reactions(0), 0.7, kForceTol_N) << toString(kind);
      EXPECT_NEAR(reactions(1), -0.3, kForceTol_N) << toString(kind);
      EXPECT_LT(relError(integ2->displacement(), u_force), 1e-9);
    }
  }
}

/// Drives `integ` through a sequence of steps with a changing prescribed set (a tip node moving
/// along +x, shaft y-constraints added and later removed) and compares every step with a fresh
/// integrator started from the same state.
void compareWithFresh(IntegratorKind kind, ElementFormulation formulation, bool move_nodes) {
  auto mesh = gridMesh(12, 10, 0.12, 0.1, 0.2, kSeed);
  FemOptions options;
  options.formulation = formulation;
  FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), tissue()), options);
  const std::vector<int> fixed = fixedEdges(mesh);
  auto integ = makeIntegrator(kind, model, fixed);
  const int row = 5;  // needle along y = 0.05
  auto node = [&](int i) { return row * 13 + i; };
  Eigen::VectorXd f = Eigen::VectorXd::Zero(model.dofCount());
  f(dofY(node(3))) = 0.05;  // some external load
  std::vector<int> shaft;
  for (int s = 0; s < 40; ++s) {
    const int tip_i = 11 - std::min(s / 4, 8);  // tip moves leftwards through the nodes
    if (s % 4 == 0 && s > 0 && s / 4 <= 8)
      shaft.push_back(node(tip_i + 1));
    if (s == 30)
      shaft.erase(shaft.begin(), shaft.begin() + 2);  // retraction releases nodes
    const int tip = node(tip_i);
    if (move_nodes && s % 3 == 1) {
      // Cutting: move the tip node a little in the reference mesh.
      const Point2 p = model.mesh().nodes[tip] + Point2(-0.0005, 0.0001 * ((s % 2) ? 1 : -1));
      ASSERT_TRUE(model.canMoveNode(tip, p, 0.0));
      integ->modelChanged(model.moveNode(tip, p));
    }
    Prescribed p;
    p.dofs = {dofX(tip), dofY(tip)};
    p.values = {-0.0002 * s, 0.0};
    for (int sn : shaft) {
      p.dofs.push_back(dofY(sn));
      p.values.push_back(0.0);
    }
    auto fresh = makeIntegrator(kind, model, fixed);
    fresh->setState(integ->displacement(), integ->velocity(), integ->acceleration());
    Eigen::VectorXd r1, r2;
    ASSERT_TRUE(integ->step(kDt_s, f, p, r1));
    ASSERT_TRUE(fresh->step(kDt_s, f, p, r2));
    EXPECT_LT(relError(integ->displacement(), fresh->displacement()), kSolutionRel) << "step " << s;
    EXPECT_LT(relError(integ->acceleration(), fresh->acceleration()), kSolutionRel) << "step " << s;
    EXPECT_LT(relError(r1, r2), kSolutionRel) << "step " << s;
    ASSERT_TRUE(integ->displacement().allFinite());
  }
  // The long-lived integrator modified its factorisation instead of refactorising every step.
  const auto counters = integ->solverCounters();
  EXPECT_LE(counters.factorizations, 2);
  EXPECT_GT(counters.row_deletions, 0);
  EXPECT_GT(counters.row_additions, 0);
  if (move_nodes) {
    EXPECT_GT(counters.rank_updates, 0);
  }
}

TEST(IntegratorIncremental, ChangingPrescribedSetMatchesFreshSolveQuasiStatic) {
  compareWithFresh(IntegratorKind::kQuasiStatic, ElementFormulation::kLinear, false);
}
TEST(IntegratorIncremental, ChangingPrescribedSetMatchesFreshSolveNewmark) {
  compareWithFresh(IntegratorKind::kNewmark, ElementFormulation::kLinear, false);
}
TEST(IntegratorIncremental, ModelChangedAfterMoveNodeMatchesFreshQuasiStatic) {
  compareWithFresh(IntegratorKind::kQuasiStatic, ElementFormulation::kLinear, true);
}
TEST(IntegratorIncremental, ModelChangedAfterMoveNodeMatchesFreshNewmark) {
  compareWithFresh(IntegratorKind::kNewmark, ElementFormulation::kLinear, true);
}
TEST(IntegratorIncremental, ModelChangedAfterMoveNodeMatchesFreshAveragedVolumetric) {
  compareWithFresh(IntegratorKind::kQuasiStatic, ElementFormulation::kAveragedVolumetric, true);
  compareWithFresh(IntegratorKind::kNewmark, ElementFormulation::kAveragedVolumetric, true);
}

TEST(IntegratorCorotational, RigidRotationOfTheBoundaryGivesZeroStrainEnergy) {
  // Every boundary node prescribed to a 90-degree rigid rotation: the corotational solution is
  // the rigid rotation (zero strain energy); linear FEM reproduces the linear field (R - I) X
  // (patch test) and reports a large spurious strain energy.
  const auto mesh = gridMesh(6, 6, 0.06, 0.06, 0.2, kSeed);
  const FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), tissue()));
  Prescribed p;
  for (int node : mesh.boundaryNodes()) {
    const Point2 x(-mesh.nodes[node].y(), mesh.nodes[node].x());  // rotation by +90 deg about 0
    const Point2 u = x - mesh.nodes[node];
    p.dofs.push_back(dofX(node));
    p.values.push_back(u.x());
    p.dofs.push_back(dofY(node));
    p.values.push_back(u.y());
  }
  IntegratorOptions corot;
  corot.corotational = true;
  auto linear = makeIntegrator(IntegratorKind::kQuasiStatic, model, {});
  auto rotating = makeIntegrator(IntegratorKind::kQuasiStatic, model, {}, corot);
  Eigen::VectorXd r;
  const Eigen::VectorXd zero = Eigen::VectorXd::Zero(model.dofCount());
  ASSERT_TRUE(linear->step(kDt_s, zero, p, r));
  const double reaction_linear_N = r.norm();
  ASSERT_TRUE(rotating->step(kDt_s, zero, p, r));
  EXPECT_GT(linear->energy(), 10.0);
  EXPECT_LT(rotating->energy(), 1e-12 * linear->energy());
  EXPECT_LT(r.norm(), 1e-9 * reaction_linear_N);
  for (int i = 0; i < model.nodeCount(); ++i) {
    const Point2 x(-mesh.nodes[i].y(), mesh.nodes[i].x());
    EXPECT_LT((rotating->displacement().segment<2>(2 * i) - (x - mesh.nodes[i])).norm(), 1e-12);
  }
  // Newmark and explicit with the corotational option: a body at rest in a rotated
  // configuration stays at rest (no spurious elastic force).
  for (IntegratorKind kind : {IntegratorKind::kNewmark, IntegratorKind::kExplicit}) {
    auto dyn = makeIntegrator(kind, model, {}, corot);
    dyn->setState(rotating->displacement(), zero, zero);
    const double dt_s = kind == IntegratorKind::kExplicit ? 0.5 * dyn->stableTimeStep() : kDt_s;
    for (int s = 0; s < 5; ++s)
      ASSERT_TRUE(dyn->step(dt_s, zero, {}, r)) << toString(kind);
    EXPECT_LT(relError(dyn->displacement(), rotating->displacement()), 1e-9) << toString(kind);
  }
}

TEST(IntegratorInput, BrokenPreconditionsThrow) {
  const auto mesh = gridMesh(3, 3, 0.03, 0.03, 0.0, kSeed);
  const FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), tissue()));
  EXPECT_THROW(makeIntegrator(IntegratorKind::kNewmark, model, {-1}), std::invalid_argument);
  EXPECT_THROW(makeIntegrator(IntegratorKind::kNewmark, model, {model.dofCount()}),
               std::invalid_argument);
  auto integ = makeIntegrator(IntegratorKind::kQuasiStatic, model, {0, 1});
  Eigen::VectorXd r;
  EXPECT_THROW(integ->step(kDt_s, Eigen::VectorXd::Zero(3), {}, r), std::invalid_argument);
  EXPECT_THROW(integ->step(kDt_s, Eigen::VectorXd::Zero(model.dofCount()), {{0}, {0.0}}, r),
               std::invalid_argument);
  EXPECT_THROW(integ->step(kDt_s, Eigen::VectorXd::Zero(model.dofCount()), {{4, 4}, {0.0, 0.0}}, r),
               std::invalid_argument);
  EXPECT_THROW(
      integ->setState(Eigen::VectorXd::Zero(2), Eigen::VectorXd::Zero(2), Eigen::VectorXd::Zero(2)),
      std::invalid_argument);
  EXPECT_STREQ(toString(IntegratorKind::kNewmark), "newmark");
}

}  // namespace
}  // namespace needle_guidance::tissue

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
