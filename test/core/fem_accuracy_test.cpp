// FEM accuracy: patch test, convergence order against a manufactured plane-strain solution,
// Newmark energy conservation in free vibration, explicit stability limit.
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <functional>
#include <iostream>
#include <random>

#include "fem_test_support.h"
#include "needle_guidance/tissue/integrator.h"

namespace needle_guidance::tissue {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): test fixtures

constexpr unsigned kSeed = 777;

TEST(FemAccuracy, PatchTestReproducesUniformStrainToRoundOff) {
  constexpr double kPatchRel = 1e-10;  // relative to max |u|
  for (ElementFormulation formulation :
       {ElementFormulation::kLinear, ElementFormulation::kAveragedVolumetric}) {
    const auto mesh = gridMesh(7, 6, 0.07, 0.06, 0.35, kSeed);  // irregular interior
    FemOptions options;
    options.formulation = formulation;
    std::vector<ElementMaterial> mats;
    for (std::size_t t = 0; t < mesh.triangleCount(); ++t)
      mats.push_back(material(50e3, 0.45));
    const FemModel model(mesh, mats, options);
    // u = A X + c, a uniform strain plus rigid motion.
    Eigen::Matrix2d a;
    a << 1e-3, -4e-4, 7e-4, -2e-3;
    const Point2 c(1e-4, -3e-4);
    Prescribed p;
    for (int node : mesh.boundaryNodes()) {
      const Point2 u = a * mesh.nodes[node] + c;
      p.dofs.push_back(dofX(node));
      p.values.push_back(u.x());
      p.dofs.push_back(dofY(node));
      p.values.push_back(u.y());
    }
    auto integ = makeIntegrator(IntegratorKind::kQuasiStatic, model, {});
    Eigen::VectorXd r;
    ASSERT_TRUE(integ->step(1.0, Eigen::VectorXd::Zero(model.dofCount()), p, r));
    double max_err = 0.0, max_u = 0.0;
    for (int i = 0; i < model.nodeCount(); ++i) {
      const Point2 exact = a * mesh.nodes[i] + c;
      max_err = std::max(max_err, (integ->displacement().segment<2>(2 * i) - exact).norm());
      max_u = std::max(max_u, exact.norm());
    }
    EXPECT_LT(max_err, kPatchRel * max_u);
  }
}

TEST(FemAccuracy, StaticConvergenceOrderIsTwo) {
  const std::vector<int> sizes = {8, 16, 32, 64};
  std::vector<double> errors;
  for (int n : sizes)
    errors.push_back(manufacturedL2Error(sineField(), n, 1.0, 0.3, ElementFormulation::kLinear));
  for (std::size_t k = 1; k < sizes.size(); ++k) {
    const double order = std::log(errors[k - 1] / errors[k]) / std::log(2.0);
    std::cout << "L2 error h=1/" << sizes[k] << ": " << errors[k] << ", observed order " << order
              << "\n";
    EXPECT_GE(order, 1.7);
    EXPECT_LE(order, 2.3);
  }
}

TEST(FemAccuracy, NewmarkFreeVibrationConservesEnergy) {
  constexpr double kEnergyDriftRel = 1e-9;
  const auto mesh = gridMesh(10, 4, 0.1, 0.04, 0.2, kSeed);
  const FemModel model(mesh,
                       std::vector<ElementMaterial>(mesh.triangleCount(), material(60e3, 0.45)));
  const std::vector<int> fixed =
      fixedDofsWhere(mesh, [](const Point2& p) { return p.x() < 1e-12; });
  auto integ = makeIntegrator(IntegratorKind::kNewmark, model, fixed);
  // Start at u = 0 (a = M^-1 (-K u) = 0, consistent) with a smooth bending velocity.
  Eigen::VectorXd v = Eigen::VectorXd::Zero(model.dofCount());
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    if (mesh.nodes[i].x() > 1e-12)
      v(dofY(static_cast<int>(i))) = 0.1 * std::pow(mesh.nodes[i].x() / 0.1, 2);
  }
  integ->setState(Eigen::VectorXd::Zero(model.dofCount()), v,
                  Eigen::VectorXd::Zero(model.dofCount()));
  const double e0 = integ->energy();
  const Eigen::VectorXd zero = Eigen::VectorXd::Zero(model.dofCount());
  double max_drift = 0.0, max_u = 0.0;
  Eigen::VectorXd r;
  for (int s = 0; s < 5000; ++s) {  // first bending period ~ 20 ms: ~100 periods at 0.4 ms
    ASSERT_TRUE(integ->step(4e-4, zero, {}, r));
    max_drift = std::max(max_drift, std::abs(integ->energy() - e0) / e0);
    max_u = std::max(max_u, integ->displacement().lpNorm<Eigen::Infinity>());
  }
  std::cout << "Newmark energy drift over 5000 steps: " << max_drift << "\n";
  EXPECT_LT(max_drift, kEnergyDriftRel);
  EXPECT_GT(max_u, 1e-4);  // it really vibrated
}

TEST(FemAccuracy, ExplicitStableBelowLimitAndRefusedAbove) {
  const auto mesh = gridMesh(10, 4, 0.1, 0.04, 0.2, kSeed);
  const FemModel model(mesh,
                       std::vector<ElementMaterial>(mesh.triangleCount(), material(60e3, 0.45)));
  const std::vector<int> fixed =
      fixedDofsWhere(mesh, [](const Point2& p) { return p.x() < 1e-12; });
  auto integ = makeIntegrator(IntegratorKind::kExplicit, model, fixed);
  const double limit_s = integ->stableTimeStep();
  ASSERT_TRUE(std::isfinite(limit_s));
  ASSERT_GT(limit_s, 0.0);
  std::mt19937 rng(kSeed);
  std::normal_distribution<double> normal(0.0, 1e-3);
  Eigen::VectorXd u(model.dofCount());
  for (int i = 0; i < u.size(); ++i)
    u(i) = normal(rng);  // excites the highest modes
  for (int d : fixed)
    u(d) = 0.0;
  const Eigen::VectorXd zero = Eigen::VectorXd::Zero(model.dofCount());
  integ->setState(u, zero, zero);
  const double e0 = integ->energy();
  Eigen::VectorXd r;
  double e_max = e0;
  for (int s = 0; s < 20000; ++s) {
    ASSERT_TRUE(integ->step(0.9 * limit_s, zero, {}, r));
    e_max = std::max(e_max, integ->energy());
  }
  EXPECT_LT(e_max, 2.0 * e0);  // bounded (central differences conserve a modified energy)
  // Above explicit_safety (0.9) x limit: refused, state unchanged, message names the limit.
  const Eigen::VectorXd u_before = integ->displacement();
  const StepStatus status = integ->step(1.01 * limit_s, zero, {}, r);
  EXPECT_FALSE(status);
  EXPECT_NE(status.toString().find("stability limit"), std::string::npos) << status.toString();
  EXPECT_EQ(integ->displacement(), u_before);
}

}  // namespace
}  // namespace needle_guidance::tissue

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
