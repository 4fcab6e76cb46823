// FEM accuracy: patch test, convergence order against a manufactured plane-strain solution,
// Newmark energy conservation in free vibration, explicit stability limit.
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <functional>
#include <iostream>
#include <random>

#include "needle_guidance/tissue/integrator.h"

namespace needle_guidance::tissue {
namespace {

constexpr unsigned kSeed = 777;

geometry::TriangleMesh gridMesh(int nx, int ny, double lx, double ly, double jitter, unsigned seed = kSeed) {
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
      if ((i + j) % 2 == 0) {
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
Manufactured sineField() {
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
[[maybe_unused]] Manufactured divergenceFreeField() {
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
  const auto mesh = gridMesh(n, n, 1.0, 1.0, 0.0);
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

TEST(FemAccuracy, PatchTestReproducesUniformStrainToRoundOff) {
  constexpr double kPatchRel = 1e-10;  // relative to max |u|
  for (ElementFormulation formulation : {ElementFormulation::kLinear, ElementFormulation::kAveragedVolumetric}) {
    const auto mesh = gridMesh(7, 6, 0.07, 0.06, 0.35);  // irregular interior
    FemOptions options;
    options.formulation = formulation;
    std::vector<ElementMaterial> mats;
    for (std::size_t t = 0; t < mesh.triangleCount(); ++t) mats.push_back(material(50e3, 0.45));
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
  for (int n : sizes) errors.push_back(manufacturedL2Error(sineField(), n, 1.0, 0.3, ElementFormulation::kLinear));
  for (std::size_t k = 1; k < sizes.size(); ++k) {
    const double order = std::log(errors[k - 1] / errors[k]) / std::log(2.0);
    std::cout << "L2 error h=1/" << sizes[k] << ": " << errors[k] << ", observed order " << order << "\n";
    EXPECT_GE(order, 1.7);
    EXPECT_LE(order, 2.3);
  }
}

TEST(FemAccuracy, NewmarkFreeVibrationConservesEnergy) {
  constexpr double kEnergyDriftRel = 1e-9;
  const auto mesh = gridMesh(10, 4, 0.1, 0.04, 0.2);
  const FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), material(60e3, 0.45)));
  std::vector<int> fixed;
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    if (mesh.nodes[i].x() < 1e-12) {
      fixed.push_back(dofX(static_cast<int>(i)));
      fixed.push_back(dofY(static_cast<int>(i)));
    }
  }
  auto integ = makeIntegrator(IntegratorKind::kNewmark, model, fixed);
  // Start at u = 0 (a = M^-1 (-K u) = 0, consistent) with a smooth bending velocity.
  Eigen::VectorXd v = Eigen::VectorXd::Zero(model.dofCount());
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    if (mesh.nodes[i].x() > 1e-12) v(dofY(static_cast<int>(i))) = 0.1 * std::pow(mesh.nodes[i].x() / 0.1, 2);
  }
  integ->setState(Eigen::VectorXd::Zero(model.dofCount()), v, Eigen::VectorXd::Zero(model.dofCount()));
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
  const auto mesh = gridMesh(10, 4, 0.1, 0.04, 0.2);
  const FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), material(60e3, 0.45)));
  std::vector<int> fixed;
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    if (mesh.nodes[i].x() < 1e-12) {
      fixed.push_back(dofX(static_cast<int>(i)));
      fixed.push_back(dofY(static_cast<int>(i)));
    }
  }
  auto integ = makeIntegrator(IntegratorKind::kExplicit, model, fixed);
  const double limit_s = integ->stableTimeStep();
  ASSERT_TRUE(std::isfinite(limit_s));
  ASSERT_GT(limit_s, 0.0);
  std::mt19937 rng(kSeed);
  std::normal_distribution<double> normal(0.0, 1e-3);
  Eigen::VectorXd u(model.dofCount());
  for (int i = 0; i < u.size(); ++i) u(i) = normal(rng);  // excites the highest modes
  for (int d : fixed) u(d) = 0.0;
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
