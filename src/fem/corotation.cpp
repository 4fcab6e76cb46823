// Corotational element forces (corotation.h).
#include "needle_guidance/fem/corotation.h"

#include <Eigen/Geometry>
#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace needle_guidance::fem {

template <int Dim>
Eigen::Matrix<double, Dim, Dim> fastPolarRotation(const Eigen::Matrix<double, Dim, Dim>& f) {
  constexpr double kMinDet = 0.1;
  // Newton's iteration converges quadratically (the next error is about half the square of the
  // last change): a change below 1e-7 leaves an error below 1e-14, so the iteration stops there.
  constexpr double kConverged = 1e-7;
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

namespace {

/// 0 at or below lo, 1 at or above hi, smooth (C1) in between.
double smoothStep(double x, double lo, double hi) {
  const double t = std::clamp((x - lo) / (hi - lo), 0.0, 1.0);
  return t * t * (3.0 - 2.0 * t);
}

}  // namespace

template <int Dim>
Eigen::Matrix<double, Dim, Dim> elementRotation(const Eigen::Matrix<double, Dim, Dim>& f) {
  using Matrix = Eigen::Matrix<double, Dim, Dim>;
  // The share of its polar rotation the element takes: all of it while it is sound (volume
  // ratio det F and Green strain within the small-strain range), none when crushed or strained
  // far beyond it, smooth in between.
  const double green = 0.5 * (f.transpose() * f - Matrix::Identity()).norm();
  const double t = smoothStep(f.determinant(), kCrushedVolume, kSoundVolume) *
                   (1.0 - smoothStep(green, kSmallStrain, kLargeStrain));
  if (t <= 0.0) {
    return Matrix::Identity();
  }
  const Matrix r = fastPolarRotation<Dim>(f);
  if (t >= 1.0) {
    return r;
  }
  if constexpr (Dim == 3) {
    const Eigen::Quaterniond q(r);
    return Eigen::Quaterniond::Identity().slerp(t, q).toRotationMatrix();
  } else {
    return Eigen::Rotation2Dd(t * std::atan2(r(1, 0), r(0, 0))).toRotationMatrix();
  }
}

template <int Dim>
CorotationalForces<Dim>::CorotationalForces(const SimplexMesh<Dim>& mesh,
                                            const std::vector<Material>& materials,
                                            double thickness_m)
    : mesh_(&mesh), materials_(materials), thickness_m_(thickness_m) {
  gradients_.reserve(mesh.elements.size());
  elasticity_.reserve(mesh.elements.size());
  for (int e = 0; e < mesh.elementCount(); ++e) {
    const Material& material = elementMaterial<Dim>(mesh, materials, e, "CorotationalForces");
    const Corners<Dim> c = corners<Dim>(mesh, e);
    gradients_.push_back(shapeGradients<Dim>(c));
    elasticity_.push_back(
        {std::abs(signedMeasure<Dim>(c)) * thickness_m, lameParameters(material)});
  }
}

namespace {

/// Cosine of the angle of a rotation (decreasing in the angle: the largest angle is found
/// by the least cosine, one arc cosine per pass).
template <int Dim>
double rotationCosine(const Eigen::Matrix<double, Dim, Dim>& r) {
  return std::clamp(0.5 * (r.trace() - (Dim - 2)), -1.0, 1.0);
}

/// R_b K R_b^T for the block-diagonal R_b with r on each corner's block.
template <int Dim>
ElementMatrix<Dim> rotated(const ElementMatrix<Dim>& k, const Eigen::Matrix<double, Dim, Dim>& r) {
  ElementMatrix<Dim> out;
  for (int a = 0; a <= Dim; ++a) {
    for (int b = 0; b <= Dim; ++b) {
      out.template block<Dim, Dim>(Dim * a, Dim * b) =
          r * k.template block<Dim, Dim>(Dim * a, Dim * b) * r.transpose();
    }
  }
  return out;
}

}  // namespace

template <int Dim>
typename CorotationalForces<Dim>::Rotation CorotationalForces<Dim>::gradient(
    int e, const Eigen::VectorXd& u) const {
  const auto& nodes = mesh_->elements[static_cast<std::size_t>(e)];
  const auto& grad = gradients_[static_cast<std::size_t>(e)];
  Rotation f = Rotation::Identity();
  for (int a = 0; a <= Dim; ++a) {
    f += u.template segment<Dim>(Dim * nodes[a]) * grad.row(a);
  }
  return f;
}

template <int Dim>
Eigen::VectorXd CorotationalForces<Dim>::correction(const Eigen::VectorXd& u, int* inverted,
                                                    double* max_turn_rad) const {
  // An element whose deformation gradient is symmetric to this has no rotation: with the
  // identity as reference its corotated force equals the linear one (to this relative size), so
  // it adds nothing to g.
  constexpr double kNoRotation = 1e-12;
  const Rotation identity = Rotation::Identity();
  Eigen::VectorXd g = Eigen::VectorXd::Zero(u.size());
  int flipped = 0;
  double least_cosine = 1.0;
  for (int e = 0; e < mesh_->elementCount(); ++e) {
    const std::size_t ei = static_cast<std::size_t>(e);
    const bool warped = !warped_.empty() && warped_[ei];
    const Rotation f = gradient(e, u);
    if (!warped && (f - f.transpose()).cwiseAbs().maxCoeff() < kNoRotation) {
      continue;
    }
    flipped += f.determinant() > 0.0 ? 0 : 1;
    const Rotation r = elementRotation<Dim>(f);
    const Rotation r0 = warped ? reference_[ei] : identity;
    least_cosine = std::min(least_cosine, rotationCosine<Dim>(r0.transpose() * r));
    // R K_e (R^T x - X) - R_0 K_e R_0^T u with x = X + u. K_e d is |e| sigma(H) grad_a on
    // corner a (linearStress), H the gradient of the corner displacements d: R^T F - I for
    // d = R^T x - X, R_0^T (F - I) for d = R_0^T u. Nine stress entries per element instead of
    // two products with the 12 x 12 K_e.
    const ElementElasticity& el = elasticity_[ei];
    const Rotation p =
        el.measure_m * (r * linearStress<Dim>(r.transpose() * f - identity, el.lame) -
                        r0 * linearStress<Dim>(r0.transpose() * (f - identity), el.lame));
    const auto& nodes = mesh_->elements[ei];
    const auto& grad = gradients_[ei];
    for (int a = 0; a <= Dim; ++a) {
      g.template segment<Dim>(Dim * nodes[a]) += p * grad.row(a).transpose();
    }
  }
  if (inverted) {
    *inverted = flipped;
  }
  if (max_turn_rad) {
    *max_turn_rad = std::acos(least_cosine);
  }
  return g;
}

template <int Dim>
SparseMatrix CorotationalForces<Dim>::warpedStiffness(const Eigen::VectorXd& u) {
  constexpr int kDofs = kElementDofs<Dim>;
  constexpr int kEntries = kDofs * kDofs;
  const std::size_t n = mesh_->elements.size();
  if (slots_.empty()) {
    // The pattern of assembleStiffness, once; later calls only overwrite the values.
    std::vector<Eigen::Triplet<double>> triplets;
    triplets.reserve(n * kEntries);
    for (const auto& nodes : mesh_->elements) {
      for (int a = 0; a < kDofs; ++a) {
        for (int b = 0; b < kDofs; ++b) {
          triplets.emplace_back(Dim * nodes[a / Dim] + a % Dim, Dim * nodes[b / Dim] + b % Dim,
                                1.0);
        }
      }
    }
    warped_k_.resize(Dim * mesh_->nodeCount(), Dim * mesh_->nodeCount());
    warped_k_.setFromTriplets(triplets.begin(), triplets.end());
    slots_.resize(n * kEntries);
    for (std::size_t t = 0; t < triplets.size(); ++t) {
      const int col = triplets[t].col();
      const int* first = warped_k_.innerIndexPtr() + warped_k_.outerIndexPtr()[col];
      const int* last = warped_k_.innerIndexPtr() + warped_k_.outerIndexPtr()[col + 1];
      slots_[t] = static_cast<int>(std::lower_bound(first, last, triplets[t].row()) -
                                   warped_k_.innerIndexPtr());
    }
  }
  reference_.assign(n, Rotation::Identity());
  warped_.assign(n, 0);
  warped_elements_ = 0;
  std::fill(warped_k_.valuePtr(), warped_k_.valuePtr() + warped_k_.nonZeros(), 0.0);
  for (int e = 0; e < mesh_->elementCount(); ++e) {
    const std::size_t ei = static_cast<std::size_t>(e);
    const Rotation r = elementRotation<Dim>(gradient(e, u));
    if (r != Rotation::Identity()) {
      reference_[ei] = r;
      warped_[ei] = 1;
      ++warped_elements_;
    }
    const Material& material = elementMaterial<Dim>(*mesh_, materials_, e, "CorotationalForces");
    const ElementMatrix<Dim> k = rotated<Dim>(
        elementStiffness<Dim>(corners<Dim>(*mesh_, e), material, thickness_m_), reference_[ei]);
    const int* slot = slots_.data() + ei * kEntries;
    for (int a = 0; a < kDofs; ++a) {
      for (int b = 0; b < kDofs; ++b) {
        warped_k_.valuePtr()[slot[a * kDofs + b]] += k(a, b);
      }
    }
  }
  return warped_k_;
}

template Eigen::Matrix<double, 2, 2> fastPolarRotation<2>(const Eigen::Matrix<double, 2, 2>&);
template Eigen::Matrix<double, 3, 3> fastPolarRotation<3>(const Eigen::Matrix<double, 3, 3>&);
template Eigen::Matrix<double, 2, 2> elementRotation<2>(const Eigen::Matrix<double, 2, 2>&);
template Eigen::Matrix<double, 3, 3> elementRotation<3>(const Eigen::Matrix<double, 3, 3>&);
template class CorotationalForces<2>;
template class CorotationalForces<3>;

}  // namespace needle_guidance::fem
