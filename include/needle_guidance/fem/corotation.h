// Corotational elements on a simplex mesh (dissertation 2.2.1; Mueller et al. 2002): the force
// of element e at displaced corners x = X + u is R K_e (R^T x - X), R the rotation of the polar
// decomposition of its deformation gradient, which vanishes for any rigid motion however large;
// the linear element's K_e u instead grows with the rotation (a turn by a strains it by
// ~a^2 / 2). CorotationalForces gives the difference g(u) = f_int(u) - K_0 u to a reference
// stiffness K_0, so that a solver factored for K_0 finds the corotational equilibrium
// K_0 u = f - g(u) as a fixed point. K_0 is the linear K, or the warped stiffness
// K_R = sum_e R_e K_e R_e^T at the rotations of a recent displacement (Mueller et al. 2002):
// the fixed point then contracts with the rotations' change since that displacement rather
// than with the rotations themselves.
#pragma once

#include <Eigen/Core>
#include <array>
#include <vector>

#include "needle_guidance/fem/linear_elasticity.h"

namespace needle_guidance::fem {

/// The rotation of the polar decomposition F = R S: Newton's iteration R <- (R + R^-T) / 2 from F
/// (Higham 1986), R^-T = cof(R) / det R, three steps for most elements of tissue; the SVD
/// (polarRotation) for an inverted or nearly flat F, or if the iteration stalls.
template <int Dim>
Eigen::Matrix<double, Dim, Dim> fastPolarRotation(const Eigen::Matrix<double, Dim, Dim>& f);

/// Volume ratios (det F) of a crushed element: at or below kCrushedVolume (inverted included) an
/// element takes no rotation (the linear element), at or above kSoundVolume its polar rotation,
/// in between a smoothly rising fraction of it.
constexpr double kCrushedVolume = 0.1;
constexpr double kSoundVolume = 0.3;
/// Green strains |F^T F - I| / 2 (Frobenius) bounding the small-strain range: up to
/// kSmallStrain an element takes its polar rotation, from kLargeStrain none, smoothly between.
constexpr double kSmallStrain = 0.3;
constexpr double kLargeStrain = 1.0;

/// The rotation of an element of deformation gradient F: its polar rotation while the element
/// is in the corotational model's small-strain range (volume ratio at least kSoundVolume, Green
/// strain at most kSmallStrain). Beyond it (next to a needle tip pushing deep into soft
/// tissue) the rotation fades smoothly to none, the linear element: a crushed element's polar
/// rotation turns fast as its singular values approach zero and jumps as it inverts (which
/// singular direction takes the reflection), and a strongly strained one carries stresses whose
/// turning the warped stiffness leaves out; with either the fixed point cycles. The linear
/// element still resists the crushing with its full stiffness.
template <int Dim>
Eigen::Matrix<double, Dim, Dim> elementRotation(const Eigen::Matrix<double, Dim, Dim>& f);

template <int Dim>
class CorotationalForces {
public:
  /// Precomputes each element's shape gradients and linear stiffness (the mesh must stay alive
  /// and unchanged). Throws std::invalid_argument like assembleStiffness.
  CorotationalForces(const SimplexMesh<Dim>& mesh, const std::vector<Material>& materials,
                     double thickness_m = 1.0);
  /// g(u) = sum over elements of R K_e (R^T x - X) - R_0 K_e R_0^T u at displacement u (Dim *
  /// node order) [N], R_0 the element's reference rotation (identity until warpedStiffness).
  /// Each element takes elementRotation(F): an element crushed to below kSoundVolume of its
  /// volume fades to no rotation; inverted counts the inverted ones (det F <= 0).
  /// max_turn_rad: the largest angle between an element's rotation and its reference rotation.
  Eigen::VectorXd correction(const Eigen::VectorXd& u, int* inverted = nullptr,
                             double* max_turn_rad = nullptr) const;
  /// The warped stiffness K_R = sum_e R_e K_e R_e^T at displacement u (the same sparsity pattern
  /// as assembleStiffness); the rotations R_e become the reference rotations of correction.
  SparseMatrix warpedStiffness(const Eigen::VectorXd& u);
  /// Elements whose reference rotation is not the identity.
  int warpedElements() const { return warped_elements_; }

private:
  using Rotation = Eigen::Matrix<double, Dim, Dim>;
  /// Deformation gradient of element e at u.
  Rotation gradient(int e, const Eigen::VectorXd& u) const;

  /// What the element pass reads of an element, side by side (two cache lines in 3-D): its
  /// corners' first DOFs, its shape gradients and its Lame parameters times its measure, so
  /// that the linear force K_e d is measure_mu (H + H^T) + measure_lambda tr(H) I times grad_a
  /// on corner a (linearStress times |e| t).
  struct PassElement {
    std::array<int, Dim + 1> dof;                       ///< Dim * node of each corner
    std::array<std::array<double, Dim>, Dim + 1> grad;  ///< shape gradient of each corner [1/m]
    double measure_mu = 0.0;                            ///< |e| t mu [N m] (|e| t a volume)
    double measure_lambda = 0.0;                        ///< |e| t lambda [N m]
  };

  const SimplexMesh<Dim>* mesh_;
  std::vector<Material> materials_;
  double thickness_m_;
  std::vector<PassElement> elements_;
  std::vector<Rotation> reference_;  ///< per element; empty: every reference is the identity
  std::vector<char> warped_;         ///< per element: reference rotation differs from identity
  int warped_elements_ = 0;
  SparseMatrix warped_k_;   ///< the last warped stiffness (its pattern is re-used)
  std::vector<int> slots_;  ///< per element and entry of K_e: its index in warped_k_'s values
};

}  // namespace needle_guidance::fem
