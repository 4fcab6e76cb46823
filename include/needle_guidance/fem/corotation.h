// Corotational elements on a simplex mesh (dissertation 2.2.1; Mueller et al. 2002): the force
// of element e at displaced corners x = X + u is R K_e (R^T x - X), R the rotation of the polar
// decomposition of its deformation gradient, which vanishes for any rigid motion however large;
// the linear element's K_e u instead grows with the rotation (a turn by a strains it by
// ~a^2 / 2). CorotationalForces gives the difference g(u) = f_int(u) - K u, so that a solver
// factored for the linear K finds the corotational equilibrium K u = f - g(u) as a fixed point.
#pragma once

#include <Eigen/Core>
#include <vector>

#include "needle_guidance/fem/linear_elasticity.h"

namespace needle_guidance::fem {

/// The rotation of the polar decomposition F = R S: Newton's iteration R <- (R + R^-T) / 2 from F
/// (Higham 1986), a few small inverses for the near-rigid elements of tissue; the SVD
/// (polarRotation) for an inverted or nearly flat F, or if the iteration stalls.
template <int Dim>
Eigen::Matrix<double, Dim, Dim> fastPolarRotation(const Eigen::Matrix<double, Dim, Dim>& f);

template <int Dim>
class CorotationalForces {
public:
  /// Precomputes each element's shape gradients and linear stiffness (the mesh must stay alive
  /// and unchanged). Throws std::invalid_argument like assembleStiffness.
  CorotationalForces(const SimplexMesh<Dim>& mesh, const std::vector<Material>& materials,
                     double thickness_m = 1.0);
  /// g(u) = sum over elements of R K_e (R^T x - X) - K_e u at displacement u (Dim * node order)
  /// [N]. An element the displacement inverts (det F <= 0) takes the proper rotation nearest to
  /// F (the smallest singular direction flipped, as invertible FEM does); inverted counts them.
  Eigen::VectorXd correction(const Eigen::VectorXd& u, int* inverted = nullptr) const;

private:
  const SimplexMesh<Dim>* mesh_;
  std::vector<Eigen::Matrix<double, Dim + 1, Dim>> gradients_;
  std::vector<ElementMatrix<Dim>> stiffness_;
};

}  // namespace needle_guidance::fem
