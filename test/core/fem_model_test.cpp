// FemModel: element stiffness symmetry, rigid-body null space, mass totals, in-place moveNode
// against a from-scratch assembly, refusals (inverting moves, invalid materials, inverted input),
// corotational rigid rotation, element energies.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <functional>
#include <random>
#include <stdexcept>

#include "fem_test_support.h"
#include "needle_guidance/tissue/fem_model.h"

namespace needle_guidance::tissue {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): test fixtures

constexpr double kRoundOffRel = 1e-12;   // relative, matrix norms
constexpr double kNullSpaceRel = 1e-12;  // |K r| / (|K| |r|)
constexpr double kMassTol_kg = 1e-12;    // absolute on masses of O(1e-3 .. 1) kg
constexpr unsigned kSeed = 12345;

ElementMaterial tissue(double e_pa = 60e3, double nu = 0.45) {
  return material(e_pa, nu, 2.0, 0.01, 1050.0);
}

/// Two materials: left half soft, right half stiff.
std::vector<ElementMaterial> mixedMaterials(const geometry::TriangleMesh& mesh) {
  std::vector<ElementMaterial> mats;
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    const auto& tri = mesh.triangles[t];
    const double cx =
        (mesh.nodes[tri[0]].x() + mesh.nodes[tri[1]].x() + mesh.nodes[tri[2]].x()) / 3.0;
    mats.push_back(cx < 0.05 ? tissue(30e3, 0.45) : tissue(90e3, 0.3));
  }
  return mats;
}

double relDiff(const SparseMatrix& a, const SparseMatrix& b) {
  return SparseMatrix(a - b).norm() / std::max(a.norm(), 1e-300);
}

class FemModelTest : public ::testing::TestWithParam<ElementFormulation> {
protected:
  FemOptions options() const {
    FemOptions o;
    o.formulation = GetParam();
    o.thickness_m = 0.02;
    return o;
  }
};

TEST_P(FemModelTest, StiffnessMassDampingSymmetric) {
  const auto mesh = gridMesh(6, 5, 0.1, 0.08, 0.25, kSeed);
  const FemModel model(mesh, mixedMaterials(mesh), options());
  for (const SparseMatrix* m : {&model.stiffness(), &model.mass(), &model.damping()}) {
    EXPECT_LT(SparseMatrix(*m - SparseMatrix(m->transpose())).norm(), kRoundOffRel * m->norm());
  }
}

TEST_P(FemModelTest, RigidBodyModesInNullSpace) {
  const auto mesh = gridMesh(7, 6, 0.1, 0.08, 0.3, kSeed);
  const FemModel model(mesh, mixedMaterials(mesh), options());
  const int n = model.nodeCount();
  Eigen::VectorXd tx = Eigen::VectorXd::Zero(2 * n), ty = tx, rot = tx;
  for (int i = 0; i < n; ++i) {
    tx(dofX(i)) = 1.0;
    ty(dofY(i)) = 1.0;
    rot(dofX(i)) = -mesh.nodes[i].y();  // infinitesimal rotation about the origin
    rot(dofY(i)) = mesh.nodes[i].x();
  }
  const double k_norm = model.stiffness().norm();
  for (const Eigen::VectorXd* r : {&tx, &ty, &rot}) {
    EXPECT_LT((model.stiffness() * *r).norm(), kNullSpaceRel * k_norm * r->norm());
  }
  // A non-rigid field is not in the null space.
  Eigen::VectorXd stretch = Eigen::VectorXd::Zero(2 * n);
  for (int i = 0; i < n; ++i)
    stretch(dofX(i)) = mesh.nodes[i].x();
  EXPECT_GT((model.stiffness() * stretch).norm(), 1e-3 * k_norm * stretch.norm());
}

TEST_P(FemModelTest, MassTotalsAndLumping) {
  const auto mesh = gridMesh(5, 4, 0.1, 0.08, 0.2, kSeed);
  const auto mats = mixedMaterials(mesh);
  const FemModel model(mesh, mats, options());
  double expected_kg = 0.0;
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    expected_kg += mats[t].density_kg_m3 * mesh.triangleArea(t) * options().thickness_m;
  }
  Eigen::VectorXd ones_x = Eigen::VectorXd::Zero(model.dofCount());
  for (int i = 0; i < model.nodeCount(); ++i)
    ones_x(dofX(i)) = 1.0;
  EXPECT_NEAR(ones_x.dot(model.mass() * ones_x), expected_kg, kMassTol_kg);
  double lumped_x = 0.0, lumped_y = 0.0;
  for (int i = 0; i < model.nodeCount(); ++i) {
    lumped_x += model.lumpedMass()(dofX(i));
    lumped_y += model.lumpedMass()(dofY(i));
  }
  EXPECT_NEAR(lumped_x, expected_kg, kMassTol_kg);
  EXPECT_NEAR(lumped_y, expected_kg, kMassTol_kg);
  // Lumped mass = row sums of the consistent mass.
  const Eigen::VectorXd row_sums = model.mass() * Eigen::VectorXd::Ones(model.dofCount());
  EXPECT_LT((row_sums - model.lumpedMass()).lpNorm<Eigen::Infinity>(), kMassTol_kg);
}

TEST_P(FemModelTest, MoveNodeMatchesFromScratchAssembly) {
  auto mesh = gridMesh(8, 6, 0.1, 0.08, 0.25, kSeed);
  const auto mats = mixedMaterials(mesh);
  FemModel model(mesh, mats, options());
  // Several moves of different interior nodes, like the needle tip advancing.
  const std::vector<std::pair<int, Point2>> moves = {{3 * 9 + 4, Point2(0.004, 0.001)},
                                                     {3 * 9 + 5, Point2(-0.002, 0.003)},
                                                     {3 * 9 + 4, Point2(0.002, -0.002)}};
  for (const auto& [node, delta] : moves) {
    const Point2 p_new = mesh.nodes[node] + delta;
    ASSERT_TRUE(model.canMoveNode(node, p_new, 0.0));
    const std::vector<int> changed = model.moveNode(node, p_new);
    mesh.nodes[node] = p_new;
    EXPECT_NE(std::find(changed.begin(), changed.end(), dofX(node)), changed.end());
    EXPECT_NE(std::find(changed.begin(), changed.end(), dofY(node)), changed.end());
  }
  const FemModel fresh(mesh, mats, options());
  EXPECT_LT(relDiff(model.stiffness(), fresh.stiffness()), kRoundOffRel);
  EXPECT_LT(relDiff(model.mass(), fresh.mass()), kRoundOffRel);
  EXPECT_LT(relDiff(model.damping(), fresh.damping()), kRoundOffRel);
  EXPECT_LT((model.lumpedMass() - fresh.lumpedMass()).norm(),
            kRoundOffRel * fresh.lumpedMass().norm());
  EXPECT_EQ(model.stiffness().nonZeros(), fresh.stiffness().nonZeros());
  for (int i = 0; i < model.nodeCount(); ++i)
    EXPECT_EQ(model.mesh().nodes[i], mesh.nodes[i]);
}

TEST_P(FemModelTest, MoveNodeThatWouldInvertThrowsAndLeavesModelUnchanged) {
  const auto mesh = gridMesh(4, 4, 0.1, 0.1, 0.0, kSeed);
  FemModel model(mesh, mixedMaterials(mesh), options());
  const SparseMatrix k_before = model.stiffness();
  const int node = 2 * 5 + 2;              // centre node (0.05, 0.05)
  const Point2 across(0.05 + 0.03, 0.05);  // beyond the neighbouring node at x = 0.075
  EXPECT_FALSE(model.canMoveNode(node, across, 0.0));
  try {
    model.moveNode(node, across);
    FAIL() << "moveNode did not throw";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("element"), std::string::npos) << e.what();
  }
  EXPECT_EQ(relDiff(model.stiffness(), k_before), 0.0);
  EXPECT_EQ(model.mesh().nodes[node], mesh.nodes[node]);
  EXPECT_THROW(model.moveNode(node, Point2(std::nan(""), 0.0)), std::invalid_argument);
  EXPECT_THROW(model.moveNode(-1, Point2(0.0, 0.0)), std::invalid_argument);
}

INSTANTIATE_TEST_SUITE_P(Formulations, FemModelTest,
                         ::testing::Values(ElementFormulation::kLinear,
                                           ElementFormulation::kAveragedVolumetric));

void expectThrowNaming(const geometry::TriangleMesh& mesh, const std::vector<ElementMaterial>& mats,
                       const std::string& needle) {
  try {
    FemModel model(mesh, mats);
    FAIL() << "no throw, expected a message with '" << needle << "'";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
  }
}

TEST(FemModelInvalid, InvalidMaterialsThrowNamingTheElement) {
  const auto mesh = gridMesh(3, 3, 0.03, 0.03, 0.0, kSeed);
  const std::vector<std::function<void(ElementMaterial&)>> breakers = {
      [](ElementMaterial& m) { m.young_modulus_Pa = 0.0; },
      [](ElementMaterial& m) { m.young_modulus_Pa = -1.0; },
      [](ElementMaterial& m) { m.poisson_ratio = 0.5; },
      [](ElementMaterial& m) { m.poisson_ratio = -1.0; },
      [](ElementMaterial& m) { m.density_kg_m3 = 0.0; },
      [](ElementMaterial& m) { m.young_modulus_Pa = std::nan(""); },
      [](ElementMaterial& m) { m.poisson_ratio = std::nan(""); },
      [](ElementMaterial& m) { m.density_kg_m3 = std::nan(""); },
      [](ElementMaterial& m) { m.rayleigh_beta_s = std::nan(""); },
  };
  for (const auto& breaker : breakers) {
    std::vector<ElementMaterial> mats(mesh.triangleCount(), tissue());
    breaker(mats[7]);
    expectThrowNaming(mesh, mats, "element 7");
  }
  expectThrowNaming(mesh, std::vector<ElementMaterial>(3, tissue()), "materials");
}

TEST(FemModelInvalid, InvertedInputTriangleThrowsNamingTheElement) {
  auto mesh = gridMesh(3, 3, 0.03, 0.03, 0.0, kSeed);
  std::swap(mesh.triangles[5][1], mesh.triangles[5][2]);  // clockwise
  expectThrowNaming(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), tissue()),
                    "element 5");
  auto degenerate = gridMesh(3, 3, 0.03, 0.03, 0.0, kSeed);
  degenerate.nodes[5] = degenerate.nodes[4];  // collapses triangles using nodes 4 and 5
  expectThrowNaming(degenerate, std::vector<ElementMaterial>(degenerate.triangleCount(), tissue()),
                    "element");
  auto non_finite = gridMesh(3, 3, 0.03, 0.03, 0.0, kSeed);
  non_finite.nodes[2].x() = std::nan("");
  expectThrowNaming(non_finite, std::vector<ElementMaterial>(non_finite.triangleCount(), tissue()),
                    "node 2");
}

TEST(FemModelCorotational, RigidRotationHasZeroForceAndEnergy) {
  constexpr double kForceRel = 1e-10;  // |f_int| relative to |K| |u|
  for (ElementFormulation formulation :
       {ElementFormulation::kLinear, ElementFormulation::kAveragedVolumetric}) {
    const auto mesh = gridMesh(6, 5, 0.1, 0.08, 0.25, kSeed);
    FemOptions options;
    options.formulation = formulation;
    const FemModel model(mesh, mixedMaterials(mesh), options);
    // Rigid rotation by 90 degrees about (0.03, 0.02) plus a translation.
    const Eigen::Rotation2Dd rotation(M_PI / 2.0);
    const Point2 center(0.03, 0.02);
    Eigen::VectorXd u(model.dofCount());
    for (int i = 0; i < model.nodeCount(); ++i) {
      const Point2 x = center + rotation * (mesh.nodes[i] - center) + Point2(0.01, -0.005);
      u.segment<2>(2 * i) = x - mesh.nodes[i];
    }
    const double scale = model.stiffness().norm() * u.norm();
    EXPECT_LT(model.corotationalForce(u).norm(), kForceRel * scale);
    const double linear_energy_J = 0.5 * u.dot(model.stiffness() * u);
    const double corotational_energy_J = model.corotationalStrainEnergy(u);
    EXPECT_GT(linear_energy_J, 1.0);  // spurious strain energy of linear FEM
    EXPECT_LT(std::abs(corotational_energy_J), 1e-12 * linear_energy_J);
    // For small displacements the corotational force equals K u.
    Eigen::VectorXd small = 1e-9 * Eigen::VectorXd::LinSpaced(model.dofCount(), -1.0, 1.0);
    EXPECT_LT((model.corotationalForce(small) - model.stiffness() * small).norm(),
              1e-6 * (model.stiffness() * small).norm());
    SparseMatrix k_r, c_r;
    Eigen::VectorXd f0;
    model.assembleCorotational(u, k_r, c_r, f0);
    EXPECT_LT((k_r * u - f0).norm(), kForceRel * scale);
  }
}

TEST(FemModelEnergy, ElementEnergiesSumToTotalAndVonMisesOfUniaxialStrain) {
  constexpr double kEnergyRel = 1e-12;
  for (ElementFormulation formulation :
       {ElementFormulation::kLinear, ElementFormulation::kAveragedVolumetric}) {
    const auto mesh = gridMesh(5, 4, 0.1, 0.08, 0.2, kSeed);
    FemOptions options;
    options.formulation = formulation;
    options.thickness_m = 0.5;
    const ElementMaterial mat = tissue(50e3, 0.3);
    const FemModel model(mesh, std::vector<ElementMaterial>(mesh.triangleCount(), mat), options);
    std::mt19937 rng(kSeed);
    std::normal_distribution<double> normal(0.0, 1e-3);
    Eigen::VectorXd u(model.dofCount());
    for (int i = 0; i < u.size(); ++i)
      u(i) = normal(rng);
    const double total = 0.5 * u.dot(model.stiffness() * u) / options.thickness_m;
    EXPECT_NEAR(model.elementStrainEnergy(u).sum(), total, kEnergyRel * total);
    // Uniaxial strain e_xx = 1e-3 (plane strain): s_xx = (lambda + 2 mu) e, s_yy = s_zz = lambda e,
    // von Mises = |s_xx - s_yy| = 2 mu e.
    const double strain = 1e-3;
    Eigen::VectorXd uni = Eigen::VectorXd::Zero(model.dofCount());
    for (int i = 0; i < model.nodeCount(); ++i)
      uni(dofX(i)) = strain * mesh.nodes[i].x();
    const double mu = mat.young_modulus_Pa / (2.0 * (1.0 + mat.poisson_ratio));
    const Eigen::VectorXd vm = model.elementVonMises(uni);
    EXPECT_LT((vm.array() - 2.0 * mu * strain).abs().maxCoeff(), 1e-9 * 2.0 * mu * strain);
  }
}

}  // namespace
}  // namespace needle_guidance::tissue

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
