// Shared fixtures of the FEM gtests: structured meshes, materials and manufactured solutions.
#pragma once

#include <array>
#include <cmath>
#include <functional>
#include <random>
#include <vector>

#include "needle_guidance/tissue/integrator.h"

namespace needle_guidance::tissue::test_support {

/// nx x ny cells split into two triangles each; `alternate` flips the diagonal in a checkerboard
/// (which hides volumetric locking), otherwise every diagonal runs the same way.
inline geometry::TriangleMesh gridMesh(int nx, int ny, double lx, double ly, double jitter,
                                       unsigned seed, bool alternate = true) {
  geometry::TriangleMesh mesh;
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> uni(-1.0, 1.0);
  const double hx = lx / nx, hy = ly / ny;
  for (int j = 0; j <= ny; ++j) {
    for (int i = 0; i <= nx; ++i) {
      Point2 p(i * hx, j * hy);
      if (i > 0 && i < nx && j > 0 && j < ny)
        p += Point2(jitter * hx * uni(rng), jitter * hy * uni(rng));
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

/// Both DOFs of every node whose reference position satisfies `where`.
inline std::vector<int> fixedDofsWhere(const geometry::TriangleMesh& mesh,
                                       const std::function<bool(const Point2&)>& where) {
  std::vector<int> fixed;
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    if (where(mesh.nodes[i])) {
      fixed.push_back(dofX(static_cast<int>(i)));
      fixed.push_back(dofY(static_cast<int>(i)));
    }
  }
  return fixed;
}

/// A material with density rho [kg/m^3] and Rayleigh damping C = alpha M + beta K.
inline ElementMaterial material(double e_pa, double nu, double alpha_per_s = 0.0,
                                double beta_s = 0.0, double density_kg_m3 = 1000.0) {
  ElementMaterial m;
  m.young_modulus_Pa = e_pa;
  m.poisson_ratio = nu;
  m.density_kg_m3 = density_kg_m3;
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
inline Manufactured sineField() {
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
inline Manufactured divergenceFreeField() {
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
inline const std::array<std::array<double, 3>, 3> kQuadPoints = {
    {{2.0 / 3, 1.0 / 6, 1.0 / 6}, {1.0 / 6, 2.0 / 3, 1.0 / 6}, {1.0 / 6, 1.0 / 6, 2.0 / 3}}};

/// Solves the manufactured problem on an n x n grid of the unit square (boundary fixed) and
/// returns the relative L2 displacement error.
inline double manufacturedL2Error(const Manufactured& field, int n, double e_pa, double nu,
                                  ElementFormulation formulation, bool alternate = true) {
  const auto mesh = gridMesh(n, n, 1.0, 1.0, 0.0, /*seed=*/0, alternate);
  FemOptions options;
  options.formulation = formulation;
  const FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), material(e_pa, nu)),
                       options);
  const double mu = e_pa / (2 * (1 + nu));
  const double lambda = e_pa * nu / ((1 + nu) * (1 - 2 * nu));
  Eigen::VectorXd f = Eigen::VectorXd::Zero(model.dofCount());
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    const auto& tri = mesh.triangles[t];
    const double area = mesh.triangleArea(t);
    for (const auto& q : kQuadPoints) {
      const Point2 x =
          q[0] * mesh.nodes[tri[0]] + q[1] * mesh.nodes[tri[1]] + q[2] * mesh.nodes[tri[2]];
      const Point2 b = field.body_force(x, mu, lambda);
      for (int k = 0; k < 3; ++k)
        f.segment<2>(2 * tri[k]) += area / 3.0 * q[k] * b;
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
      const Point2 x =
          q[0] * mesh.nodes[tri[0]] + q[1] * mesh.nodes[tri[1]] + q[2] * mesh.nodes[tri[2]];
      Point2 uh = Point2::Zero();
      for (int k = 0; k < 3; ++k)
        uh += q[k] * Point2(u(2 * tri[k]), u(2 * tri[k] + 1));
      const Point2 ue = field.u(x);
      err2 += area / 3.0 * (uh - ue).squaredNorm();
      norm2 += area / 3.0 * ue.squaredNorm();
    }
  }
  return std::sqrt(err2 / norm2);
}

}  // namespace needle_guidance::tissue::test_support
