// FEM hard cases: volumetric locking at nu = 0.499 and its remedy, a 1e4 stiffness contrast,
// sliver elements, very large time steps, NaN inputs. Each works within a stated error or fails
// with a clear status; none produces NaN silently.
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <functional>
#include <iostream>
#include <random>

#include "needle_guidance/tissue/integrator.h"

namespace needle_guidance::tissue {
namespace {

constexpr unsigned kSeed = 99;

/// nx x ny cells split into two triangles each; `alternate` flips the diagonal in a checkerboard
/// (which hides volumetric locking), otherwise every diagonal runs the same way.
geometry::TriangleMesh gridMesh(int nx, int ny, double lx, double ly, double jitter, unsigned seed = kSeed,
                                bool alternate = true) {
  geometry::TriangleMesh mesh;
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> uni(-1.0, 1.0);
  const double hx = lx / nx, hy = ly / ny;
  for (int j = 0; j <= ny; ++j) {
    for (int i = 0; i <= nx; ++i) {
      Point2 p(i * hx, j * hy);
      if (i > 0 && i < nx && j > 0 && j < ny) p += Point2(jitter * hx * uni(rng), jitter * hy * uni(rng));
      mesh.nodes.push_back(p);
    }
  }
  auto id = [&](int i, int j) { return j * (nx + 1) + i; };
  for (int j = 0; j < ny; ++j) {
    for (int i = 0; i < nx; ++i) {
      const int a = id(i, j), b = id(i + 1, j), c = id(i + 1, j + 1), d = id(i, j + 1);
      if (!alternate || (i + j) % 2 == 0) {
        mesh.triangles.push_back({a, b, c});
        mesh.triangles.push_back({a, c, d});
      } else {
        mesh.triangles.push_back({a, b, d});
        mesh.triangles.push_back({b, c, d});
      }
      mesh.triangle_region.push_back(0);
      mesh.triangle_region.push_back(0);
    }
  }
  mesh.region_names = {"tissue"};
  return mesh;
}

ElementMaterial material(double e_pa, double nu, double alpha_per_s = 0.0, double beta_s = 0.0) {
  ElementMaterial m;
  m.young_modulus_Pa = e_pa;
  m.poisson_ratio = nu;
  m.density_kg_m3 = 1000.0;
  m.rayleigh_alpha_per_s = alpha_per_s;
  m.rayleigh_beta_s = beta_s;
  return m;
}

/// A manufactured displacement field on the unit square, zero on the boundary, and the body
/// force b = -div sigma(u) for plane strain with shear modulus mu and Lame lambda.
struct Manufactured {
  std::function<Point2(const Point2&)> u;
  std::function<Point2(const Point2&, double mu, double lambda)> body_force;
};

/// u = (sin(pi x) sin(pi y), sin(pi x) sin(pi y)); b = -(mu lap u + (lambda + mu) grad div u).
[[maybe_unused]] Manufactured sineField() {
  Manufactured m;
  m.u = [](const Point2& p) {
    const double s = std::sin(M_PI * p.x()) * std::sin(M_PI * p.y());
    return Point2(s, s);
  };
  m.body_force = [](const Point2& p, double mu, double lambda) {
    const double sx = std::sin(M_PI * p.x()), sy = std::sin(M_PI * p.y());
    const double cx = std::cos(M_PI * p.x()), cy = std::cos(M_PI * p.y());
    const double lap = -2.0 * M_PI * M_PI * sx * sy;
    const double gd = M_PI * M_PI * (cx * cy - sx * sy);  // both components of grad div u
    return Point2(-(mu * lap + (lambda + mu) * gd), -(mu * lap + (lambda + mu) * gd));
  };
  return m;
}

/// Divergence-free u = curl(sin^2(pi x) sin^2(pi y)): b = -mu lap u, independent of lambda, so
/// the exact solution stays bounded as nu -> 0.5 (a locking test).
Manufactured divergenceFreeField() {
  Manufactured m;
  m.u = [](const Point2& p) {
    const double x = p.x(), y = p.y();
    return Point2(M_PI * std::pow(std::sin(M_PI * x), 2) * std::sin(2 * M_PI * y),
                  -M_PI * std::sin(2 * M_PI * x) * std::pow(std::sin(M_PI * y), 2));
  };
  m.body_force = [](const Point2& p, double mu, double /*lambda*/) {
    const double x = p.x(), y = p.y();
    const double pi3 = M_PI * M_PI * M_PI;
    const double lap_x = 2 * pi3 * std::sin(2 * M_PI * y) * (2 * std::cos(2 * M_PI * x) - 1);
    const double lap_y = -2 * pi3 * std::sin(2 * M_PI * x) * (2 * std::cos(2 * M_PI * y) - 1);
    return Point2(-mu * lap_x, -mu * lap_y);
  };
  return m;
}

/// Degree-2 triangle quadrature: barycentric points (2/3, 1/6, 1/6) and permutations, weight 1/3.
const std::array<std::array<double, 3>, 3> kQuadPoints = {
    {{2.0 / 3, 1.0 / 6, 1.0 / 6}, {1.0 / 6, 2.0 / 3, 1.0 / 6}, {1.0 / 6, 1.0 / 6, 2.0 / 3}}};

/// Solves the manufactured problem on an n x n grid of the unit square (boundary fixed) and
/// returns the relative L2 displacement error.
double manufacturedL2Error(const Manufactured& field, int n, double e_pa, double nu, ElementFormulation formulation) {
  const auto mesh = gridMesh(n, n, 1.0, 1.0, 0.0, kSeed, /*alternate=*/false);
  FemOptions options;
  options.formulation = formulation;
  const FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), material(e_pa, nu)), options);
  const double mu = e_pa / (2 * (1 + nu));
  const double lambda = e_pa * nu / ((1 + nu) * (1 - 2 * nu));
  Eigen::VectorXd f = Eigen::VectorXd::Zero(model.dofCount());
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    const auto& tri = mesh.triangles[t];
    const double area = mesh.triangleArea(t);
    for (const auto& q : kQuadPoints) {
      const Point2 x = q[0] * mesh.nodes[tri[0]] + q[1] * mesh.nodes[tri[1]] + q[2] * mesh.nodes[tri[2]];
      const Point2 b = field.body_force(x, mu, lambda);
      for (int k = 0; k < 3; ++k) f.segment<2>(2 * tri[k]) += area / 3.0 * q[k] * b;
    }
  }
  std::vector<int> fixed;
  for (int node : mesh.boundaryNodes()) {
    fixed.push_back(dofX(node));
    fixed.push_back(dofY(node));
  }
  auto integ = makeIntegrator(IntegratorKind::kQuasiStatic, model, fixed);
  Eigen::VectorXd r;
  EXPECT_TRUE(integ->step(1.0, f, {}, r));
  const Eigen::VectorXd& u = integ->displacement();
  double err2 = 0.0, norm2 = 0.0;
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    const auto& tri = mesh.triangles[t];
    const double area = mesh.triangleArea(t);
    for (const auto& q : kQuadPoints) {
      const Point2 x = q[0] * mesh.nodes[tri[0]] + q[1] * mesh.nodes[tri[1]] + q[2] * mesh.nodes[tri[2]];
      Point2 uh = Point2::Zero();
      for (int k = 0; k < 3; ++k) uh += q[k] * Point2(u(2 * tri[k]), u(2 * tri[k] + 1));
      const Point2 ue = field.u(x);
      err2 += area / 3.0 * (uh - ue).squaredNorm();
      norm2 += area / 3.0 * ue.squaredNorm();
    }
  }
  return std::sqrt(err2 / norm2);
}

TEST(FemHardCases, VolumetricLockingAtNu0499AndAveragedVolumetricRemedy) {
  constexpr int kN = 16;
  constexpr double kAveragedMaxRelL2 = 0.1;  // stated error of the remedy on this mesh
  const double linear_030 = manufacturedL2Error(divergenceFreeField(), kN, 1.0, 0.3, ElementFormulation::kLinear);
  const double linear_0499 = manufacturedL2Error(divergenceFreeField(), kN, 1.0, 0.499, ElementFormulation::kLinear);
  const double avg_0499 =
      manufacturedL2Error(divergenceFreeField(), kN, 1.0, 0.499, ElementFormulation::kAveragedVolumetric);
  std::cout << "relative L2 error, 16x16: linear nu=0.3 " << linear_030 << ", linear nu=0.499 " << linear_0499
            << ", averaged volumetric nu=0.499 " << avg_0499 << "\n";
  EXPECT_GT(linear_0499, 3.0 * linear_030);  // locking: the CST error explodes as nu -> 0.5
  EXPECT_LT(avg_0499, kAveragedMaxRelL2);
  EXPECT_LT(avg_0499, 0.5 * linear_0499);
}

TEST(FemHardCases, StiffnessContrast1e4MatchesSeriesSprings) {
  constexpr double kRel = 1e-8;
  const double l_m = 0.05, h_m = 0.02, e_soft = 10e3, e_stiff = 1e8, force_n = 0.5;
  const auto mesh = gridMesh(20, 4, 2 * l_m, h_m, 0.0);
  std::vector<ElementMaterial> mats;
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    const auto& tri = mesh.triangles[t];
    const double cx = (mesh.nodes[tri[0]].x() + mesh.nodes[tri[1]].x() + mesh.nodes[tri[2]].x()) / 3;
    mats.push_back(material(cx < l_m ? e_soft : e_stiff, 0.0));  // nu = 0: exact 1-D bar
  }
  const FemModel model(mesh, mats);
  std::vector<int> fixed;
  Eigen::VectorXd f = Eigen::VectorXd::Zero(model.dofCount());
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    const Point2& x = mesh.nodes[i];
    if (x.x() < 1e-12) fixed.push_back(dofX(static_cast<int>(i)));
    if (x.x() < 1e-12 && x.y() < 1e-12) fixed.push_back(dofY(static_cast<int>(i)));
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
  auto mesh = gridMesh(6, 6, 0.06, 0.06, 0.3);
  // Collapse an interior node onto the opposite edge of one of its triangles (a gap of
  // kSliverGap_m): that triangle becomes a sliver; the others must stay positive.
  const int node = 3 * 7 + 3;
  const Point2 start = mesh.nodes[static_cast<std::size_t>(node)];
  double sliver_area = 0.0, regular_area = 1e300;
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) regular_area = std::min(regular_area, mesh.triangleArea(t));
  for (std::size_t t = 0; t < mesh.triangleCount() && sliver_area == 0.0; ++t) {
    const auto& tri = mesh.triangles[t];
    const int k = tri[0] == node ? 0 : tri[1] == node ? 1 : tri[2] == node ? 2 : -1;
    if (k < 0) continue;
    const Point2 a = mesh.nodes[tri[(k + 1) % 3]], b = mesh.nodes[tri[(k + 2) % 3]];
    const Point2 e = (b - a).normalized();
    const Point2 foot = a + (start - a).dot(e) * e;
    mesh.nodes[node] = foot + kSliverGap_m * (start - foot).normalized();
    double min_area = 1e300;
    for (std::size_t s2 = 0; s2 < mesh.triangleCount(); ++s2) min_area = std::min(min_area, mesh.triangleArea(s2));
    if (min_area > 0.0) {
      sliver_area = mesh.triangleArea(t);
    } else {
      mesh.nodes[node] = start;
    }
  }
  ASSERT_GT(sliver_area, 0.0) << "no sliver could be built without inverting a triangle";
  ASSERT_LT(sliver_area, 1e-8 * regular_area) << "the constructed triangle is not a sliver";
  std::cout << "sliver area " << sliver_area << " m^2, smallest regular " << regular_area << " m^2\n";
  const FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), material(50e3, 0.45)));
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
    max_err = std::max(max_err, (integ->displacement().segment<2>(2 * i) - a * mesh.nodes[i]).norm());
  }
  EXPECT_LT(max_err, kPatchRel * 0.06 * a.norm());
}

TEST(FemHardCases, VeryLargeTimeStepsNewmarkStableExplicitRefuses) {
  const auto mesh = gridMesh(8, 4, 0.08, 0.04, 0.2);
  const FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), material(60e3, 0.45, 2.0, 0.01)));
  std::vector<int> fixed;
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    if (mesh.nodes[i].x() < 1e-12) fixed.insert(fixed.end(), {dofX(static_cast<int>(i)), dofY(static_cast<int>(i))});
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
  std::cout << "Newmark dt = 10 s, 200 steps: relative distance to the static solution " << err << "\n";
  EXPECT_LT(err, 1e-2);  // trapezoidal rule is A- but not L-stable: high modes decay only via Rayleigh damping
  auto expl = makeIntegrator(IntegratorKind::kExplicit, model, fixed);
  const StepStatus status = expl->step(10.0, f, {}, r);
  EXPECT_FALSE(status);
  EXPECT_NE(status.toString().find("stability limit"), std::string::npos);
  EXPECT_EQ(expl->displacement().norm(), 0.0);
}

TEST(FemHardCases, NaNInputsRefusedStateUnchanged) {
  const auto mesh = gridMesh(4, 4, 0.04, 0.04, 0.1);
  const FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), material(60e3, 0.45)));
  const std::vector<int> fixed = {0, 1, 2, 3};
  for (IntegratorKind kind : {IntegratorKind::kQuasiStatic, IntegratorKind::kNewmark, IntegratorKind::kExplicit}) {
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
