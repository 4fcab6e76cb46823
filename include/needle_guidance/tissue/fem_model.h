// Plane-strain linear-elastic FEM on a triangle mesh (dissertation 2.1.4, 2.2.2): element
// matrices, global sparse assembly, and reference-mesh node moves for needle cutting (2.3.4).
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <array>
#include <memory>
#include <vector>

#include "needle_guidance/geometry/triangle_mesh.h"

namespace needle_guidance::tissue {

using geometry::Point2;
using SparseMatrix = Eigen::SparseMatrix<double>;  // column-major

/// Material of one element, SI.
struct ElementMaterial {
  double young_modulus_Pa = 0.0;      ///< > 0
  double poisson_ratio = 0.0;         ///< (-1, 0.5)
  double density_kg_m3 = 1000.0;      ///< > 0
  double rayleigh_alpha_per_s = 0.0;  ///< C = alpha M + beta K
  double rayleigh_beta_s = 0.0;
};

/// Element formulation. kLinear is the constant-strain triangle (CST). kAveragedVolumetric
/// is the locking remedy for nearly incompressible tissue (nu -> 0.5): the volumetric part of
/// the strain is averaged over node patches (average nodal pressure / nodal B-bar), so linear
/// triangles do not lock.
enum class ElementFormulation { kLinear, kAveragedVolumetric };

struct FemOptions {
  ElementFormulation formulation = ElementFormulation::kLinear;
  double thickness_m = 1.0;  ///< out-of-plane thickness: forces are per this thickness [m]
};

/// DOF numbering: node i has DOFs 2i (x) and 2i+1 (y).
inline int dofX(int node) {
  return 2 * node;
}
inline int dofY(int node) {
  return 2 * node + 1;
}

/// The FEM model of a tissue slice: the reference mesh G (node positions may be moved, 2.3.4),
/// per-element materials, and the assembled stiffness K, consistent mass M, lumped mass and
/// Rayleigh damping C = alpha M + beta K (per element, then assembled).
/// Throws std::invalid_argument (naming the element or node) for an invalid material, an
/// inverted or degenerate element (signed area <= 0), or a non-finite coordinate.
class FemModel {
public:
  /// @param[in] mesh reference mesh (counter-clockwise triangles) [m]
  /// @param[in] element_materials one per triangle
  FemModel(geometry::TriangleMesh mesh, std::vector<ElementMaterial> element_materials,
           const FemOptions& options = {});
  /// Deep copies: moving a node of the copy leaves the original unchanged.
  FemModel(const FemModel& other);
  FemModel& operator=(const FemModel& other);
  FemModel(FemModel&&) = default;
  FemModel& operator=(FemModel&&) = default;
  ~FemModel();

  const geometry::TriangleMesh& mesh() const { return mesh_; }
  int nodeCount() const;
  int dofCount() const { return 2 * nodeCount(); }
  const std::vector<ElementMaterial>& materials() const { return materials_; }
  const FemOptions& options() const { return options_; }

  const SparseMatrix& stiffness() const { return K_; }             ///< K [N/m]
  const SparseMatrix& mass() const { return M_; }                  ///< consistent M [kg]
  const SparseMatrix& damping() const { return C_; }               ///< C [N s/m]
  const Eigen::VectorXd& lumpedMass() const { return m_lumped_; }  ///< per DOF [kg]

  /// Triangles that use `node`.
  const std::vector<int>& trianglesOfNode(int node) const;

  /// Would moving `node` to p_new (reference frame) keep every adjacent triangle's signed area
  /// above min_area_m2? (Figure 2.9's degenerate case is when it would not.)
  bool canMoveNode(int node, const Point2& p_new, double min_area_m2) const;

  /// Moves a node of the reference mesh (cutting, 2.3.4) and updates K, M, C and the lumped
  /// mass in place for the affected triangles only (the sparsity pattern never changes).
  /// Returns the DOFs whose rows/columns changed. Throws std::invalid_argument and leaves the
  /// model unchanged if an adjacent triangle would get signed area <= 0.
  std::vector<int> moveNode(int node, const Point2& p_new);

  /// Element strain energy density x area, per triangle, for displacement u [J per m thickness].
  Eigen::VectorXd elementStrainEnergy(const Eigen::VectorXd& u) const;
  /// Von Mises stress per triangle (plane strain) for displacement u [Pa].
  Eigen::VectorXd elementVonMises(const Eigen::VectorXd& u) const;

  // ---- added by the FEM core (additive) ----
  // K, M and C share one sparsity pattern (same outer/inner index arrays) that never changes.

  /// Corotational (warped-stiffness) linearisation at displacement u (Mueller et al. 2002,
  /// "Stable real-time deformations"): per-element rotation R_e from the polar decomposition of
  /// the 2x2 deformation gradient (per-node patch rotation for the averaged volumetric blocks).
  /// Fills K_R = sum R K_e R^T [N/m], C_R = sum (alpha M_e + beta R K_e R^T) [N s/m] (same
  /// pattern as K) and the offset force f0 [N] such that the elastic force is K_R u - f0.
  /// Throws std::invalid_argument if u has the wrong size.
  void assembleCorotational(const Eigen::VectorXd& u, SparseMatrix& K_R, SparseMatrix& C_R,
                            Eigen::VectorXd& f0) const;
  /// Corotational elastic force sum R_e K_e (R_e^T x_e - X_e) at displacement u [N].
  Eigen::VectorXd corotationalForce(const Eigen::VectorXd& u) const;
  /// Corotational strain energy sum 1/2 d_e^T K_e d_e, d_e = R_e^T x_e - X_e [J per thickness
  /// thickness_m]; zero for any rigid motion. Linear energy is 1/2 u^T K u.
  double corotationalStrainEnergy(const Eigen::VectorXd& u) const;

private:
  // implementation detail, free to change
  geometry::TriangleMesh mesh_;
  std::vector<ElementMaterial> materials_;
  FemOptions options_;
  SparseMatrix K_, M_, C_;
  Eigen::VectorXd m_lumped_;
  std::vector<std::vector<int>> node_triangles_;
  struct Impl;
  std::shared_ptr<Impl> impl_;
};

}  // namespace needle_guidance::tissue
