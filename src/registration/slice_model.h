// Private to the registration module: the biomechanical model of a probe-out slice (3.2.2) --
// conforming mesh, soft-class per element, Dirichlet/fixed/force node sets, unit-modulus
// stiffness per class -- and a solver for K(E) u = f with the rectum-wall displacements
// prescribed and the bone fixed. Shared by the registration and the case generator.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <array>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/geometry/triangle_mesh.h"
#include "needle_guidance/registration/deformable_registration.h"
#include "needle_guidance/registration/segmentation.h"

namespace needle_guidance::registration::detail {

using SparseMatrix = Eigen::SparseMatrix<double>;
using Moduli = std::array<double, kSoftClassCount>;

/// The meshed probe-out slice.
struct SliceModel {
  geometry::TriangleMesh mesh;      ///< rectum lumen and bladder cavity removed
  std::vector<int> triangle_class;  ///< SoftClass per triangle; -1 for bone
  std::vector<int> fixed_nodes;     ///< bone nodes (sorted)
  std::vector<int> rectum_nodes;    ///< rectum-wall nodes (Dirichlet, 3.3.2), by angle
  std::vector<int> bladder_nodes;   ///< bladder-wall nodes (sorted)
  std::vector<std::array<int, 2>> bladder_wall_edges;  ///< wall edges, cavity on the left
  std::vector<std::vector<int>> prostate_loops;        ///< CG u PZ boundary, region on the left
  Point2 rectum_centre = Point2::Zero();
  std::array<SparseMatrix, kSoftClassCount> unit_stiffness;  ///< K per class at E = 1 Pa [N/m]
};

/// Meshes the slice with about target_nodes nodes (3.3.2) and assembles the unit stiffness
/// matrices (tissue::FemModel, plane strain, averaged volumetric, poisson). Throws
/// std::invalid_argument (meshDomain's message) when the geometry cannot be meshed.
SliceModel buildSliceModel(const SliceSegmentation& seg, int target_nodes, double poisson);

/// Deformed loop positions: reference loop nodes + displacement (full DOF vector).
Loops deformedLoops(const SliceModel& model, const Eigen::VectorXd& u);

/// Solves K(E) u = f on the free DOFs with u = u_d on the rectum wall and 0 on bone.
class SliceSolver {
public:
  /// @param[in] rectum_displacement per model.rectum_nodes entry [m]
  /// @param[in] force_nodes nodes with unknown forces (set L); DOFs 2k, 2k+1 per node
  SliceSolver(const SliceModel& model, const std::vector<Point2>& rectum_displacement,
              std::vector<int> force_nodes);

  /// Factorises K(E) (no-op if E is unchanged). False if the factorisation fails.
  bool setModuli(const Moduli& modulus_Pa);
  const Moduli& moduli() const { return moduli_; }

  /// Displacement without external forces, u0 (all DOFs) [m].
  const Eigen::VectorXd& u0() const { return u0_; }
  /// Displacement due to the forces alone, K_ff^-1 f (zero on prescribed DOFs) [m].
  Eigen::VectorXd forceResponse(const Eigen::VectorXd& force_N) const;
  /// Columns K_ff^-1 e_k for every force DOF k (all DOFs x force DOFs) [m/N].
  Eigen::MatrixXd greensFunctions() const;
  /// Solves K_ff x = b_f for a full-size right-hand side (prescribed rows ignored); zero on
  /// prescribed DOFs.
  Eigen::VectorXd solveFree(const Eigen::VectorXd& b_full) const;
  /// K(E) u for a full DOF vector [N].
  Eigen::VectorXd multiplyK(const Eigen::VectorXd& u) const;
  /// E_c K_c u: the share of K(E) u from soft class c [N].
  Eigen::VectorXd classMultiply(int soft_class, const Eigen::VectorXd& u) const {
    return moduli_[static_cast<std::size_t>(soft_class)] *
           (model_.unit_stiffness[static_cast<std::size_t>(soft_class)] * u);
  }
  /// Total strain energy 1/2 u^T K u = sum of element strain energies [J per m thickness].
  double strainEnergy(const Eigen::VectorXd& u) const { return 0.5 * u.dot(multiplyK(u)); }

  int forceDofCount() const { return static_cast<int>(force_dofs_.size()); }
  const std::vector<int>& forceDofs() const { return force_dofs_; }
  const std::vector<int>& forceNodes() const { return force_nodes_; }
  int dofCount() const { return n_dof_; }
  long factorizations() const { return factorizations_; }

private:
  const SliceModel& model_;
  int n_dof_ = 0;
  std::vector<int> free_index_;  // per DOF: index among free DOFs, or -1
  std::vector<int> free_dofs_;
  std::vector<int> force_nodes_;
  std::vector<int> force_dofs_;
  Eigen::VectorXd u_prescribed_;  // full: rectum displacement, zero elsewhere
  SparseMatrix k_ff_;
  std::vector<int> ff_position_;  // per nnz of the full pattern: position in k_ff_ values, or -1
  Eigen::SimplicialLDLT<SparseMatrix> ldlt_;
  Moduli moduli_{};
  bool factorized_ = false;
  Eigen::VectorXd u0_;
  long factorizations_ = 0;
};

}  // namespace needle_guidance::registration::detail
