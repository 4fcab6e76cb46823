// Corotational element forces (corotation.h).
#include "needle_guidance/fem/corotation.h"

#include <Eigen/LU>
#include <stdexcept>
#include <string>

namespace needle_guidance::fem {

template <int Dim>
Eigen::Matrix<double, Dim, Dim> fastPolarRotation(const Eigen::Matrix<double, Dim, Dim>& f) {
  constexpr double kMinDet = 0.1;
  constexpr double kConverged = 1e-13;
  constexpr int kMaxIterations = 12;
  if (!(f.determinant() > kMinDet)) {
    return polarRotation<Dim>(f);
  }
  Eigen::Matrix<double, Dim, Dim> r = f;
  for (int i = 0; i < kMaxIterations; ++i) {
    const Eigen::Matrix<double, Dim, Dim> next = 0.5 * (r + r.inverse().transpose());
    if ((next - r).cwiseAbs().maxCoeff() < kConverged) {
      return next;
    }
    r = next;
  }
  return polarRotation<Dim>(f);
}

template <int Dim>
CorotationalForces<Dim>::CorotationalForces(const SimplexMesh<Dim>& mesh,
                                            const std::vector<Material>& materials,
                                            double thickness_m)
    : mesh_(&mesh) {
  gradients_.reserve(mesh.elements.size());
  stiffness_.reserve(mesh.elements.size());
  for (int e = 0; e < mesh.elementCount(); ++e) {
    const int mat = mesh.element_material[static_cast<std::size_t>(e)];
    if (mat < 0 || mat >= static_cast<int>(materials.size())) {
      throw std::invalid_argument("CorotationalForces: element " + std::to_string(e) +
                                  ": material index " + std::to_string(mat) + " out of range");
    }
    const Corners<Dim> c = corners<Dim>(mesh, e);
    gradients_.push_back(shapeGradients<Dim>(c));
    stiffness_.push_back(
        elementStiffness<Dim>(c, materials[static_cast<std::size_t>(mat)], thickness_m));
  }
}

template <int Dim>
Eigen::VectorXd CorotationalForces<Dim>::correction(const Eigen::VectorXd& u, int* inverted) const {
  // An element whose deformation gradient is symmetric to this has no rotation: its corotated
  // force equals the linear one (to this relative size), so it adds nothing to g.
  constexpr double kNoRotation = 1e-12;
  constexpr int kDofs = kElementDofs<Dim>;
  using Local = Eigen::Matrix<double, kDofs, 1>;
  using Matrix = Eigen::Matrix<double, Dim, Dim>;
  Eigen::VectorXd g = Eigen::VectorXd::Zero(u.size());
  int flipped = 0;
  for (int e = 0; e < mesh_->elementCount(); ++e) {
    const auto& nodes = mesh_->elements[static_cast<std::size_t>(e)];
    const auto& grad = gradients_[static_cast<std::size_t>(e)];
    Matrix f = Matrix::Identity();
    Local ue, xe;
    for (int a = 0; a <= Dim; ++a) {
      ue.template segment<Dim>(Dim * a) = u.template segment<Dim>(Dim * nodes[a]);
      xe.template segment<Dim>(Dim * a) = mesh_->nodes[static_cast<std::size_t>(nodes[a])];
      f += ue.template segment<Dim>(Dim * a) * grad.row(a);
    }
    if ((f - f.transpose()).cwiseAbs().maxCoeff() < kNoRotation) {
      continue;
    }
    flipped += f.determinant() > 0.0 ? 0 : 1;
    const Matrix r = fastPolarRotation<Dim>(f);
    // R K_e (R^T x - X) - K_e u with x = X + u.
    Local local;
    for (int a = 0; a <= Dim; ++a) {
      local.template segment<Dim>(Dim * a) =
          r.transpose() * (xe.template segment<Dim>(Dim * a) + ue.template segment<Dim>(Dim * a)) -
          xe.template segment<Dim>(Dim * a);
    }
    const ElementMatrix<Dim>& ke = stiffness_[static_cast<std::size_t>(e)];
    const Local kl = ke * local, ku = ke * ue;
    for (int a = 0; a <= Dim; ++a) {
      g.template segment<Dim>(Dim * nodes[a]) +=
          r * kl.template segment<Dim>(Dim * a) - ku.template segment<Dim>(Dim * a);
    }
  }
  if (inverted) {
    *inverted = flipped;
  }
  return g;
}

template Eigen::Matrix<double, 2, 2> fastPolarRotation<2>(const Eigen::Matrix<double, 2, 2>&);
template Eigen::Matrix<double, 3, 3> fastPolarRotation<3>(const Eigen::Matrix<double, 3, 3>&);
template class CorotationalForces<2>;
template class CorotationalForces<3>;

}  // namespace needle_guidance::fem
