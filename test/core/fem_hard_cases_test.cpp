// FEM hard cases: volumetric locking at nu = 0.499 and its remedy, a 1e4 stiffness contrast,
// sliver elements, very large time steps, NaN inputs. Each works within a stated error or fails
// with a clear status; none produces NaN silently.
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

constexpr unsigned kSeed = 99;

TEST(FemHardCases, VolumetricLockingAtNu0499AndAveragedVolumetricRemedy) {
  constexpr int kN = 16;
  constexpr double kAveragedMaxRelL2 = 0.1;  // stated error of the remedy on this mesh
  const double linear_030 =
      manufacturedL2Error(divergenceFreeField(), kN, 1.0, 0.3, ElementFormulation::kLinear, false);
  const double linear_0499 = manufacturedL2Error(divergenceFreeField(), kN, 1.0, 0.499,
                                                 ElementFormulation::kLinear, false);
  const double avg_0499 = manufacturedL2Error(divergenceFreeField(), kN, 1.0, 0.499,
                                              ElementFormulation::kAveragedVolumetric, false);
  std::cout << "relative L2 error, 16x16: linear nu=0.3 " << linear_030 << ", linear nu=0.499 "
            << linear_0499 << ", averaged volumetric nu=0.499 " << avg_0499 << "\n";
  EXPECT_GT(linear_0499, 3.0 * linear_030);  // locking: the CST error explodes as nu -> 0.5
  EXPECT_LT(avg_0499, kAveragedMaxRelL2);
  EXPECT_LT(avg_0499, 0.5 * linear_0499);
}

TEST(FemHardCases, StiffnessContrast1e4MatchesSeriesSprings) {
  constexpr double kRel = 1e-8;
  const double l_m = 0.05, h_m = 0.02, e_soft = 10e3, e_stiff = 1e8, force_n = 0.5;
  const auto mesh = gridMesh(20, 4, 2 * l_m, h_m, 0.0, kSeed);
  std::vector<ElementMaterial> mats;
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    const auto& tri = mesh.triangles[t];
    const double cx =
        (mesh.nodes[tri[0]].x() + mesh.nodes[tri[1]].x() + mesh.nodes[tri[2]].x()) / 3;
    mats.push_back(material(cx < l_m ? e_soft : e_stiff, 0.0));  // nu = 0: exact 1-D bar
  }
  const FemModel model(mesh, mats);
  std::vector<int> fixed;
  Eigen::VectorXd f = Eigen::VectorXd::Zero(model.dofCount());
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    const Point2& x = mesh.nodes[i];
    if (x.x() < 1e-12)
      fixed.push_back(dofX(static_cast<int>(i)));
    if (x.x() < 1e-12 && x.y() < 1e-12)
      fixed.push_back(dofY(static_cast<int>(i)));
    if (x.x() > 2 * l_m - 1e-12) {
      const bool corner = x.y() < 1e-12 || x.y() > h_m - 1e-12;
      f(dofX(static_cast<int>(i))) = force_n / 4 * (corner ? 0.5 : 1.0);
    }
  }
  auto integ = makeIntegrator(IntegratorKind::kQuasiStatic, model, fixed);
  Eigen::VectorXd r;
  ASSERT_TRUE(integ->step(1.0, f, {}, r));
  const double area = h_m * 1.0;
  const double expected = force_n * l_m / (e_soft * area) + force_n * l_m / (e_stiff * area);
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    if (mesh.nodes[i].x() > 2 * l_m - 1e-12) {
      EXPECT_NEAR(integ->displacement()(dofX(static_cast<int>(i))), expected, kRel * expected);
    }
  }
  EXPECT_TRUE(integ->displacement().allFinite());
}

TEST(FemHardCases, SliverElementsSolveThePatchTest) {
  // Stated error with a sliver of area ratio ~2.5e-10: round-off amplified by the sliver's
  // conditioning (observed ~1.3e-7 relative), far below any physical tolerance.
  constexpr double kPatchRel = 1e-6;
  constexpr double kSliverGap_m = 1e-12;
  auto mesh = gridMesh(6, 6, 0.06, 0.06, 0.3, kSeed);
  // Collapse an interior node onto the opposite edge of one of its triangles (a gap of
  // kSliverGap_m): that triangle becomes a sliver; the others must stay positive.
  const int node = 3 * 7 + 3;
  const Point2 start = mesh.nodes[static_cast<std::size_t>(node)];
  double sliver_area = 0.0, regular_area = 1e300;
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t)
    regular_area = std::min(regular_area, mesh.triangleArea(t));
  for (std::size_t t = 0; t < mesh.triangleCount() && sliver_area == 0.0; ++t) {
    const auto& tri = mesh.triangles[t];
    const int k = tri[0] == node ? 0 : tri[1] == node ? 1 : tri[2] == node ? 2 : -1;
    if (k < 0)
      continue;
    const Point2 a = mesh.nodes[tri[(k + 1) % 3]], b = mesh.nodes[tri[(k + 2) % 3]];
    const Point2 e = (b - a).normalized();
    const Point2 foot = a + (start - a).dot(e) * e;
    mesh.nodes[node] = foot + kSliverGap_m * (start - foot).normalized();
    double min_area = 1e300;
    for (std::size_t s2 = 0; s2 < mesh.triangleCount(); ++s2)
      min_area = std::min(min_area, mesh.triangleArea(s2));
    if (min_area > 0.0) {
      sliver_area = mesh.triangleArea(t);
    } else {
      mesh.nodes[node] = start;
    }
  }
  ASSERT_GT(sliver_area, 0.0) << "no sliver could be built without inverting a triangle";
  ASSERT_LT(sliver_area, 1e-8 * regular_area) << "the constructed triangle is not a sliver";
  std::cout << "sliver area " << sliver_area << " m^2, smallest regular " << regular_area
            << " m^2\n";
  const FemModel model(mesh,
                       std::vector<ElementMaterial>(mesh.triangleCount(), material(50e3, 0.45)));
  Eigen::Matrix2d a;
  a << 1e-3, 2e-4, -3e-4, 5e-4;
  Prescribed p;
  for (int b : mesh.boundaryNodes()) {
    const Point2 u = a * mesh.nodes[b];
    p.dofs.insert(p.dofs.end(), {dofX(b), dofY(b)});
    p.values.insert(p.values.end(), {u.x(), u.y()});
  }
  auto integ = makeIntegrator(IntegratorKind::kQuasiStatic, model, {});
  Eigen::VectorXd r;
  const StepStatus status = integ->step(1.0, Eigen::VectorXd::Zero(model.dofCount()), p, r);
  ASSERT_TRUE(status) << status.toString();
  double max_err = 0.0;
  for (int i = 0; i < model.nodeCount(); ++i) {
    max_err =
        std::max(max_err, (integ->displacement().segment<2>(2 * i) - a * mesh.nodes[i]).norm());
  }
  EXPECT_LT(max_err, kPatchRel * 0.06 * a.norm());
}

TEST(FemHardCases, VeryLargeTimeStepsNewmarkStableExplicitRefuses) {
  const auto mesh = gridMesh(8, 4, 0.08, 0.04, 0.2, kSeed);
  const FemModel model(
      mesh, std::vector<ElementMaterial>(mesh.triangleCount(), material(60e3, 0.45, 2.0, 0.01)));
  std::vector<int> fixed;
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    if (mesh.nodes[i].x() < 1e-12)
      fixed.insert(fixed.end(), {dofX(static_cast<int>(i)), dofY(static_cast<int>(i))});
  }
  Eigen::VectorXd f = Eigen::VectorXd::Zero(model.dofCount());
  f(model.dofCount() - 1) = -0.1;  // tip load
  auto stat = makeIntegrator(IntegratorKind::kQuasiStatic, model, fixed);
  Eigen::VectorXd r;
  ASSERT_TRUE(stat->step(1.0, f, {}, r));
  auto newmark = makeIntegrator(IntegratorKind::kNewmark, model, fixed);
  double err = 0.0;
  for (int s = 0; s < 200; ++s) {
    ASSERT_TRUE(newmark->step(10.0, f, {}, r));
    ASSERT_TRUE(newmark->displacement().allFinite());
    err = (newmark->displacement() - stat->displacement()).norm() / stat->displacement().norm();
  }
  std::cout << "Newmark dt = 10 s, 200 steps: relative distance to the static solution " << err
            << "\n";
  EXPECT_LT(
      err,
      1e-2);  // trapezoidal rule is A- but not L-stable: high modes decay only via Rayleigh damping
  auto expl = makeIntegrator(IntegratorKind::kExplicit, model, fixed);
  const StepStatus status = expl->step(10.0, f, {}, r);
  EXPECT_FALSE(status);
  EXPECT_NE(status.toString().find("stability limit"), std::string::npos);
  EXPECT_EQ(expl->displacement().norm(), 0.0);
}

TEST(FemHardCases, NaNInputsRefusedStateUnchanged) {
  const auto mesh = gridMesh(4, 4, 0.04, 0.04, 0.1, kSeed);
  const FemModel model(mesh,
                       std::vector<ElementMaterial>(mesh.triangleCount(), material(60e3, 0.45)));
  const std::vector<int> fixed = {0, 1, 2, 3};
  for (IntegratorKind kind :
       {IntegratorKind::kQuasiStatic, IntegratorKind::kNewmark, IntegratorKind::kExplicit}) {
    auto integ = makeIntegrator(kind, model, fixed);
    const double dt = kind == IntegratorKind::kExplicit ? 0.5 * integ->stableTimeStep() : 1e-3;
    Eigen::VectorXd f = Eigen::VectorXd::Zero(model.dofCount());
    f(10) = 0.1;
    Eigen::VectorXd r;
    ASSERT_TRUE(integ->step(dt, f, {{12}, {1e-4}}, r));
    const Eigen::VectorXd u = integ->displacement(), v = integ->velocity();
    Eigen::VectorXd f_nan = f;
    f_nan(5) = std::nan("");
    EXPECT_FALSE(integ->step(dt, f_nan, {}, r)) << toString(kind);
    EXPECT_FALSE(integ->step(dt, f, {{12}, {std::nan("")}}, r)) << toString(kind);
    EXPECT_FALSE(integ->step(std::nan(""), f, {}, r)) << toString(kind);
    if (kind != IntegratorKind::kQuasiStatic) {
      EXPECT_FALSE(integ->step(-1.0, f, {}, r)) << toString(kind);
    }
    EXPECT_EQ(integ->displacement(), u);
    EXPECT_EQ(integ->velocity(), v);
  }
}

}  // namespace
}  // namespace needle_guidance::tissue

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
