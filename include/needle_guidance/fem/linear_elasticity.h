// Linear elasticity on simplices, one implementation for 2-D and 3-D (dissertation 2.2.1-2.2.2):
// Dim = 2 is the plane-strain constant-strain triangle, Dim = 3 the linear (constant-strain)
// tetrahedron. Element stiffness K_e = t |e| B^T D B (t: thickness in 2-D, 1 in 3-D), global
// assembly into an Eigen sparse matrix, node i owning DOFs Dim*i .. Dim*i + Dim - 1.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <array>
#include <vector>

namespace needle_guidance::fem {

using SparseMatrix = Eigen::SparseMatrix<double>;  // column-major

/// Isotropic linear-elastic material [SI].
struct Material {
  double young_modulus_Pa = 0.0;  ///< > 0
  double poisson_ratio = 0.0;     ///< (-1, 0.5)
};

/// Throws std::invalid_argument naming `where` if the material is not finite and in range.
void validateMaterial(const Material& material, const char* where);

template <int Dim>
using Point = Eigen::Matrix<double, Dim, 1>;

/// A simplex mesh: triangles (Dim 2, counter-clockwise) or tetrahedra (Dim 3, positive volume).
template <int Dim>
struct SimplexMesh {
  std::vector<Point<Dim>> nodes;                   ///< [m]
  std::vector<std::array<int, Dim + 1>> elements;  ///< node indices
  std::vector<int> element_material;               ///< index into a material table, per element
  int nodeCount() const { return static_cast<int>(nodes.size()); }
  int elementCount() const { return static_cast<int>(elements.size()); }
};

template <int Dim>
constexpr int kElementDofs = Dim*(Dim + 1);
template <int Dim>
constexpr int kStrainComponents = Dim*(Dim + 1) / 2;
template <int Dim>
using ElementMatrix = Eigen::Matrix<double, kElementDofs<Dim>, kElementDofs<Dim>>;
template <int Dim>
using Corners = std::array<Point<Dim>, Dim + 1>;

/// Signed area (Dim 2) or volume (Dim 3) of a simplex [m^Dim].
template <int Dim>
double signedMeasure(const Corners<Dim>& corners);

/// Gradients of the linear shape functions, one row per corner [1/m]. The simplex must have a
/// non-zero measure (the caller checks).
template <int Dim>
Eigen::Matrix<double, Dim + 1, Dim> shapeGradients(const Corners<Dim>& corners);

/// Barycentric coordinates of p in the simplex (sum 1; all >= 0 inside).
template <int Dim>
Eigen::Matrix<double, Dim + 1, 1> barycentric(const Corners<Dim>& corners, const Point<Dim>& p);

/// Lame parameters of an isotropic material [Pa].
struct LameParameters {
  double lambda_Pa = 0.0;
  double mu_Pa = 0.0;  ///< shear modulus
};
LameParameters lameParameters(const Material& material);

/// Linear (Cauchy) stress of the displacement gradient H: lambda tr(e) I + 2 mu e with the small
/// strain e = (H + H^T) / 2 [Pa]; the stress elasticityMatrix gives for the same strain (plane
/// strain in 2-D). A constant-strain element's force K_e d is then |e| t sigma grad_a on corner
/// a, H = sum_b d_b grad_b^T.
template <int Dim>
Eigen::Matrix<double, Dim, Dim> linearStress(const Eigen::Matrix<double, Dim, Dim>& h,
                                             const LameParameters& lame) {
  const Eigen::Matrix<double, Dim, Dim> strain = 0.5 * (h + h.transpose());
  Eigen::Matrix<double, Dim, Dim> stress = 2.0 * lame.mu_Pa * strain;
  stress.diagonal().array() += lame.lambda_Pa * strain.trace();
  return stress;
}

/// Elasticity matrix in Voigt form with engineering shear: plane strain (Dim 2, order xx yy xy)
/// or 3-D (order xx yy zz xy yz zx) [Pa].
template <int Dim>
Eigen::Matrix<double, kStrainComponents<Dim>, kStrainComponents<Dim>> elasticityMatrix(
    const Material& material);

/// Element stiffness t |e| B^T D B for the DOF order (x0, y0[, z0], x1, ...) [N/m].
/// thickness_m scales 2-D elements (out-of-plane thickness) and must be 1 in 3-D.
template <int Dim>
ElementMatrix<Dim> elementStiffness(const Corners<Dim>& corners, const Material& material,
                                    double thickness_m = 1.0);

/// The rotation R of the polar decomposition F = R S (det R = +1), through the SVD.
template <int Dim>
Eigen::Matrix<double, Dim, Dim> polarRotation(const Eigen::Matrix<double, Dim, Dim>& f);

/// A corotational element at displaced corners x = X + u: the element's rotation R (polar
/// rotation of its deformation gradient), the internal force R K_e (R^T x - X) about the
/// centroid (zero for any rigid motion, however large the rotation) and the tangent R K_e R^T,
/// with K_e = elementStiffness(X). The linear element's force K_e u instead grows with the
/// rotation: a rigid turn by angle a strains it by ~a^2 / 2, so large rotations need this one.
template <int Dim>
struct CorotatedElement {
  Eigen::Matrix<double, Dim, Dim> rotation;
  Eigen::Matrix<double, kElementDofs<Dim>, 1> force;  ///< internal force [N]
  ElementMatrix<Dim> tangent;                         ///< [N/m]
};
template <int Dim>
CorotatedElement<Dim> corotatedElement(const Corners<Dim>& reference, const Corners<Dim>& displaced,
                                       const Material& material, double thickness_m = 1.0);

/// Corners of element e.
template <int Dim>
Corners<Dim> corners(const SimplexMesh<Dim>& mesh, int element);

/// The material of element e: materials[mesh.element_material[e]]. Throws std::invalid_argument
/// naming `who` and the element if the index is missing or out of range.
template <int Dim>
const Material& elementMaterial(const SimplexMesh<Dim>& mesh,
                                const std::vector<Material>& materials, int e, const char* who);

/// Global stiffness K (Dim * nodeCount square, symmetric) [N/m]. Throws std::invalid_argument
/// naming the element for a measure <= min_measure (inverted or near-degenerate), a material
/// index out of range or an invalid material.
template <int Dim>
SparseMatrix assembleStiffness(const SimplexMesh<Dim>& mesh, const std::vector<Material>& materials,
                               double thickness_m = 1.0, double min_measure = 0.0);

}  // namespace needle_guidance::fem
