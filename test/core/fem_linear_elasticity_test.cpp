// fem::linear_elasticity and fem::CondensedCompliance: the Dim = 2 instantiation reproduces the
// plane-strain FemModel's stiffness; the Dim = 3 tetrahedron has the rigid-body null space and
// reproduces a uniform-strain patch; a clamped bar's condensed compliance matches the full
// solve and 1-D theory; degenerate elements are refused with their index.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <cstdlib>
#include <stdexcept>

#include "fem_test_support.h"
#include "needle_guidance/fem/condensed_compliance.h"
#include "needle_guidance/fem/linear_elasticity.h"
#include "needle_guidance/tissue/fem_model.h"

namespace needle_guidance::fem {
namespace {

constexpr double kRoundOffRel = 1e-12;  // relative, matrix and vector norms
constexpr double kSolveRel = 1e-9;      // relative, Cholesky solves
constexpr unsigned kSeed = 4242;

SimplexMesh<3> boxTets(int nx, int ny, int nz, double lx, double ly, double lz) {
  SimplexMesh<3> mesh;
  auto id = [&](int i, int j, int k) { return (k * (ny + 1) + j) * (nx + 1) + i; };
  for (int k = 0; k <= nz; ++k) {
    for (int j = 0; j <= ny; ++j) {
      for (int i = 0; i <= nx; ++i) {
        mesh.nodes.emplace_back(lx * i / nx, ly * j / ny, lz * k / nz);
      }
    }
  }
  // Six tetrahedra per cube around the main diagonal (Kuhn triangulation), all positive.
  const int perms[6][3] = {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}};
  for (int k = 0; k < nz; ++k) {
    for (int j = 0; j < ny; ++j) {
      for (int i = 0; i < nx; ++i) {
        for (const auto& p : perms) {
          int c[3] = {i, j, k};
          std::array<int, 4> tet{};
          tet[0] = id(c[0], c[1], c[2]);
          for (int s = 0; s < 3; ++s) {
            ++c[p[s]];
            tet[static_cast<std::size_t>(s + 1)] = id(c[0], c[1], c[2]);
          }
          if (signedMeasure<3>(Corners<3>{mesh.nodes[tet[0]], mesh.nodes[tet[1]],
                                          mesh.nodes[tet[2]], mesh.nodes[tet[3]]}) < 0.0) {
            std::swap(tet[2], tet[3]);
          }
          mesh.elements.push_back(tet);
          mesh.element_material.push_back(0);
        }
      }
    }
  }
  return mesh;
}

TEST(FemLinearElasticity, PlaneStrainMatchesTissueFemModel) {
  const auto tri = tissue::test_support::gridMesh(5, 4, 0.08, 0.06, 0.25, kSeed);
  const double thickness_m = 0.02;
  std::vector<tissue::ElementMaterial> old_materials;
  SimplexMesh<2> mesh;
  std::vector<Material> materials{{30e3, 0.45}, {90e3, 0.3}};
  for (const auto& p : tri.nodes) {
    mesh.nodes.push_back(p);
  }
  for (std::size_t t = 0; t < tri.triangleCount(); ++t) {
    const int m = tri.nodes[tri.triangles[t][0]].x() < 0.04 ? 0 : 1;
    mesh.elements.push_back(tri.triangles[t]);
    mesh.element_material.push_back(m);
    old_materials.push_back(
        tissue::test_support::material(materials[static_cast<std::size_t>(m)].young_modulus_Pa,
                                       materials[static_cast<std::size_t>(m)].poisson_ratio));
  }
  tissue::FemOptions options;
  options.thickness_m = thickness_m;
  const tissue::FemModel reference(tri, old_materials, options);
  const SparseMatrix k = assembleStiffness<2>(mesh, materials, thickness_m);
  const SparseMatrix diff = k - reference.stiffness();
  EXPECT_LT(diff.norm(), kRoundOffRel * reference.stiffness().norm());
}

TEST(FemLinearElasticity, TetrahedronRigidModesAndUniformStrain) {
  const Corners<3> c{Point<3>(0.0, 0.0, 0.0), Point<3>(0.01, 0.001, 0.0),
                     Point<3>(0.002, 0.012, 0.001), Point<3>(0.001, 0.002, 0.009)};
  const Material m{60e3, 0.45};
  const ElementMatrix<3> k = elementStiffness<3>(c, m);
  EXPECT_LT((k - k.transpose()).norm(), kRoundOffRel * k.norm());
  // Translations and infinitesimal rotations produce no force.
  for (int mode = 0; mode < 6; ++mode) {
    Eigen::Matrix<double, 12, 1> u;
    for (int a = 0; a < 4; ++a) {
      Eigen::Vector3d axis = Eigen::Vector3d::Zero();
      axis(mode % 3) = 1.0;
      u.segment<3>(3 * a) = mode < 3 ? axis : Eigen::Vector3d(axis.cross(c[a]));
    }
    EXPECT_LT((k * u).norm(), kRoundOffRel * k.norm() * u.norm()) << "mode " << mode;
  }
  // Uniaxial strain e_xx = 1e-3: energy density 1/2 (lambda + 2 mu) e^2 times the volume.
  Eigen::Matrix<double, 12, 1> u = Eigen::Matrix<double, 12, 1>::Zero();
  for (int a = 0; a < 4; ++a) {
    u(3 * a) = 1e-3 * c[a].x();
  }
  const auto d = elasticityMatrix<3>(m);
  const double expected = 0.5 * d(0, 0) * 1e-6 * signedMeasure<3>(c);
  EXPECT_NEAR(0.5 * u.dot(k * u), expected, kRoundOffRel * 1e3 * expected);
}

TEST(FemLinearElasticity, CondensedComplianceMatchesFullSolveAndBarTheory) {
  // Bar along x clamped at x = 0 (all DOFs), axial load at the far face.
  const double lx = 0.1, ly = 0.02, lz = 0.02;
  const SimplexMesh<3> mesh = boxTets(10, 2, 2, lx, ly, lz);
  const Material m{50e3, 0.0};  // nu = 0: no lateral coupling, 1-D theory exact for the mean
  const SparseMatrix k = assembleStiffness<3>(mesh, {m});
  std::vector<char> fixed(static_cast<std::size_t>(3 * mesh.nodeCount()), 0);
  Eigen::VectorXd f = Eigen::VectorXd::Zero(3 * mesh.nodeCount());
  std::vector<int> loaded;
  for (int i = 0; i < mesh.nodeCount(); ++i) {
    if (mesh.nodes[static_cast<std::size_t>(i)].x() < 1e-12) {
      for (int d = 0; d < 3; ++d) {
        fixed[static_cast<std::size_t>(3 * i + d)] = 1;
      }
    } else if (mesh.nodes[static_cast<std::size_t>(i)].x() > lx - 1e-12) {
      loaded.push_back(3 * i);
    }
  }
  // Consistent nodal loads of a uniform traction are not equal on a Kuhn mesh; use the exact
  // ones: the reaction of a uniform strain field on the far face.
  Eigen::VectorXd u_uniform(3 * mesh.nodeCount());
  u_uniform.setZero();
  const double strain = 1e-3;
  for (int i = 0; i < mesh.nodeCount(); ++i) {
    u_uniform(3 * i) = strain * mesh.nodes[static_cast<std::size_t>(i)].x();
  }
  const Eigen::VectorXd reaction = k * u_uniform;
  for (int dof : loaded) {
    f(dof) = reaction(dof);
  }
  CondensedCompliance g(k, fixed);
  const Eigen::VectorXd u = g.solve(f);
  EXPECT_LT((u - u_uniform).norm(), kSolveRel * u_uniform.norm());
  g.require(loaded);
  Eigen::VectorXd u_condensed = Eigen::VectorXd::Zero(u.size());
  for (int dof : loaded) {
    u_condensed += g.column(dof) * f(dof);
  }
  EXPECT_LT((u_condensed - u).norm(), kSolveRel * u.norm());
  EXPECT_NEAR(g.entry(loaded[0], loaded[1]), g.entry(loaded[1], loaded[0]),
              kSolveRel * std::abs(g.entry(loaded[0], loaded[0])));
  EXPECT_EQ(g.solvedColumns(), static_cast<long long>(loaded.size()));
}

/// Every DOF of the nodes on the face x = 0 held fixed.
std::vector<char> fixedAtEntryFace(const SimplexMesh<3>& mesh) {
  std::vector<char> fixed(static_cast<std::size_t>(3 * mesh.nodeCount()), 0);
  for (int i = 0; i < mesh.nodeCount(); ++i) {
    if (mesh.nodes[static_cast<std::size_t>(i)].x() < 1e-12) {
      for (int d = 0; d < 3; ++d) {
        fixed[static_cast<std::size_t>(3 * i + d)] = 1;
      }
    }
  }
  return fixed;
}

// A force on a few DOFs: the field from their cached columns is the solve's (to the single
// precision the columns are read in), and without every column cached, or with more DOFs than a
// solve reads, the solve answers.
TEST(FemLinearElasticity, SupportedSolveFromCachedColumnsEqualsTheSolve) {
  const SimplexMesh<3> mesh = boxTets(16, 6, 6, 0.08, 0.03, 0.03);
  const SparseMatrix k = assembleStiffness<3>(mesh, {Material{20e3, 0.45}});
  CondensedCompliance g(k, fixedAtEntryFace(mesh));
  ASSERT_GT(g.factorEntries(), 0.0);
  // Three nodes inside the block, as a needle's tissue points load them.
  std::vector<int> support;
  for (int node : {mesh.nodeCount() / 2, mesh.nodeCount() / 2 + 1, mesh.nodeCount() / 3}) {
    for (int d = 0; d < 3; ++d) {
      support.push_back(3 * node + d);
    }
  }
  std::srand(kSeed);
  Eigen::VectorXd f = Eigen::VectorXd::Zero(3 * mesh.nodeCount());
  for (int dof : support) {
    f(dof) = Eigen::VectorXd::Random(1)(0);  // N
  }
  const Eigen::VectorXd u = g.solve(f);
  // Not cached yet: the solve.
  EXPECT_LT((g.solveSupported(f, support) - u).norm(), kRoundOffRel * u.norm());
  g.require(support);
  ASSERT_LT(static_cast<double>(support.size()) * g.dofCount(), 2.0 * g.factorEntries());
  const Eigen::VectorXd from_columns = g.solveSupported(f, support);
  constexpr double kSingleRel = 1e-6;  // relative, columns read in single precision
  EXPECT_LT((from_columns - u).norm(), kSingleRel * u.norm());
  EXPECT_GT((from_columns - u).norm(), 0.0);  // they are: the field is not the solve's bit for bit
  EXPECT_EQ(g.solvedColumns(), static_cast<long long>(support.size()));
}

// The single-precision solve (the corotational warp's) on a soft block with a stiff inclusion
// (a stiffness ratio of 100, as a calcification in a gland): the double solve's answer to the
// precision the warp's tolerances need, though not bit for bit; a wrong size is refused.
TEST(FemLinearElasticity, SinglePrecisionSolveEqualsTheSolve) {
  constexpr double kSingleSolveRel = 1e-5;  // relative (measured 4e-7)
  const SimplexMesh<3> mesh = boxTets(16, 6, 6, 0.08, 0.03, 0.03);
  std::vector<Material> materials = {Material{10e3, 0.45}, Material{1e6, 0.45}};
  SimplexMesh<3> graded = mesh;
  graded.element_material.assign(static_cast<std::size_t>(graded.elementCount()), 0);
  for (int e = 0; e < graded.elementCount(); e += 7) {
    graded.element_material[static_cast<std::size_t>(e)] = 1;
  }
  const SparseMatrix k = assembleStiffness<3>(graded, materials);
  const std::vector<char> fixed = fixedAtEntryFace(mesh);
  CondensedCompliance g(k, fixed);
  std::srand(kSeed);
  const Eigen::VectorXd f = 1e-3 * Eigen::VectorXd::Random(3 * mesh.nodeCount());  // N
  const Eigen::VectorXd u = g.solve(f);
  const Eigen::VectorXd single = g.solveSinglePrecision(f);
  EXPECT_LT((single - u).lpNorm<Eigen::Infinity>(), kSingleSolveRel * u.lpNorm<Eigen::Infinity>());
  EXPECT_GT((single - u).norm(), 0.0);
  for (int i = 0; i < mesh.nodeCount(); ++i) {
    if (fixed[static_cast<std::size_t>(3 * i)]) {
      EXPECT_EQ(single.segment<3>(3 * i), Eigen::Vector3d::Zero().eval());
    }
  }
  EXPECT_GT(g.memoryBytes(), g.factorBytes());  // the single-precision copy is held
  EXPECT_THROW(g.solveSinglePrecision(Eigen::VectorXd::Zero(5)), std::invalid_argument);
}

TEST(FemLinearElasticity, RefusesDegenerateElementAndFreeBody) {
  SimplexMesh<3> mesh = boxTets(2, 1, 1, 0.02, 0.01, 0.01);
  const Material m{50e3, 0.3};
  // Flatten one tetrahedron: its fourth node onto the plane of the other three.
  mesh.nodes.push_back(mesh.nodes[static_cast<std::size_t>(mesh.elements[3][0])]);
  mesh.elements[3][3] = mesh.nodeCount() - 1;
  try {
    assembleStiffness<3>(mesh, {m});
    FAIL() << "a zero-volume element was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("element 3"), std::string::npos) << e.what();
  }
  const SimplexMesh<3> ok = boxTets(2, 1, 1, 0.02, 0.01, 0.01);
  const SparseMatrix k = assembleStiffness<3>(ok, {m});
  EXPECT_THROW(CondensedCompliance(k, std::vector<char>(static_cast<std::size_t>(k.rows()), 0)),
               std::invalid_argument);
  EXPECT_THROW(assembleStiffness<3>(ok, {Material{-1.0, 0.3}}), std::invalid_argument);
}

// A tetrahedron turned rigidly by up to 90 degrees: the linear element answers with forces that
// grow with the angle (at 90 degrees more than those of a real 10 % stretch), the corotational
// element with none; a stretch then turned gives the stretch's own forces, turned.
TEST(FemLinearElasticity, CorotatedTetrahedronHasNoForceUnderLargeRotation) {
  const Material material{10e3, 0.45};
  const Corners<3> ref{Point<3>(0.0, 0.0, 0.0), Point<3>(0.01, 0.001, 0.0),
                       Point<3>(0.002, 0.012, 0.001), Point<3>(0.001, 0.002, 0.009)};
  const ElementMatrix<3> ke = elementStiffness<3>(ref, material);
  auto flatten = [](const Corners<3>& c) {
    Eigen::Matrix<double, 12, 1> v;
    for (int a = 0; a < 4; ++a) {
      v.segment<3>(3 * a) = c[static_cast<std::size_t>(a)];
    }
    return v;
  };
  auto transformed = [&](const Eigen::Matrix3d& m) {
    Corners<3> out = ref;
    for (auto& p : out) {
      p = m * p;
    }
    return out;
  };
  const Eigen::Vector3d axis = Eigen::Vector3d(1.0, 2.0, 0.5).normalized();
  const Eigen::Matrix3d stretch = Eigen::Vector3d(1.1, 1.0, 1.0).asDiagonal();
  const double stretch_force = (ke * (flatten(transformed(stretch)) - flatten(ref))).norm();
  double previous_linear = 0.0;
  for (int deg = 15; deg <= 90; deg += 15) {
    const Eigen::Matrix3d r = Eigen::AngleAxisd(deg * M_PI / 180.0, axis).toRotationMatrix();
    const Corners<3> turned = transformed(r);
    const double linear = (ke * (flatten(turned) - flatten(ref))).norm();
    const CorotatedElement<3> co = corotatedElement<3>(ref, turned, material);
    EXPECT_GT(linear, previous_linear) << deg << " deg: linear force grows with the angle";
    previous_linear = linear;
    EXPECT_LT(co.force.norm(), kRoundOffRel * 1e3 * stretch_force) << deg << " deg";
    EXPECT_LT((co.rotation - r).norm(), kSolveRel) << deg << " deg";
    const CorotatedElement<3> both = corotatedElement<3>(ref, transformed(r * stretch), material);
    Eigen::Matrix<double, 12, 1> expected = ke * (flatten(transformed(stretch)) - flatten(ref));
    for (int a = 0; a < 4; ++a) {
      expected.segment<3>(3 * a) = r * expected.segment<3>(3 * a).eval();
    }
    EXPECT_LT((both.force - expected).norm(), kSolveRel * stretch_force) << deg << " deg";
  }
  EXPECT_GT(previous_linear, stretch_force) << "linear: spurious force at 90 deg";
}

}  // namespace
}  // namespace needle_guidance::fem

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
