// Corotational element forces (corotation.h).
#include "needle_guidance/fem/corotation.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace needle_guidance::fem {

namespace {

/// The cofactor matrix of x, det(x) x^-T (Cramer's rule): with det x = sum_j x(0, j) c(0, j),
/// the inverse transpose for the price of one division.
template <int Dim>
inline Eigen::Matrix<double, Dim, Dim> cofactors(const Eigen::Matrix<double, Dim, Dim>& x) {
  Eigen::Matrix<double, Dim, Dim> c;
  if constexpr (Dim == 3) {
    c(0, 0) = x(1, 1) * x(2, 2) - x(1, 2) * x(2, 1);
    c(0, 1) = x(1, 2) * x(2, 0) - x(1, 0) * x(2, 2);
    c(0, 2) = x(1, 0) * x(2, 1) - x(1, 1) * x(2, 0);
    c(1, 0) = x(0, 2) * x(2, 1) - x(0, 1) * x(2, 2);
    c(1, 1) = x(0, 0) * x(2, 2) - x(0, 2) * x(2, 0);
    c(1, 2) = x(0, 1) * x(2, 0) - x(0, 0) * x(2, 1);
    c(2, 0) = x(0, 1) * x(1, 2) - x(0, 2) * x(1, 1);
    c(2, 1) = x(0, 2) * x(1, 0) - x(0, 0) * x(1, 2);
    c(2, 2) = x(0, 0) * x(1, 1) - x(0, 1) * x(1, 0);
  } else {
    c(0, 0) = x(1, 1);
    c(0, 1) = -x(1, 0);
    c(1, 0) = -x(0, 1);
    c(1, 1) = x(0, 0);
  }
  return c;
}

/// A deformation gradient with its cofactor matrix and determinant, which the volume ratio,
/// the inverted count and Newton's first step all use.
template <int Dim>
struct Deformation {
  using Matrix = Eigen::Matrix<double, Dim, Dim>;
  explicit Deformation(const Matrix& f_in)
      : f(f_in), cofactor(cofactors<Dim>(f_in)), det(f_in.row(0).dot(cofactor.row(0))) {}
  Matrix f;
  Matrix cofactor;  ///< det(F) F^-T
  double det;
};

/// fastPolarRotation of d.f.
template <int Dim>
[[gnu::always_inline]] inline Eigen::Matrix<double, Dim, Dim> newtonPolarRotation(
    const Deformation<Dim>& d) {
  using Matrix = Eigen::Matrix<double, Dim, Dim>;
  constexpr double kMinDet = 0.1;
  // Newton's iteration converges quadratically (the next error is about half the square of the
  // last change): a change below 1e-7 leaves an error below 1e-14, so the iteration stops there.
  constexpr double kConverged = 1e-7;
  constexpr int kMaxIterations = 12;
  if (!(d.det > kMinDet)) {
    return polarRotation<Dim>(d.f);
  }
  // R^-T = cof(R) / det R: one division per step. Every iterate keeps a positive determinant
  // (its singular values become (s + 1/s) / 2 >= 1).
  Matrix r = d.f;
  Matrix c = d.cofactor;
  double det = d.det;
  for (int i = 0; i < kMaxIterations; ++i) {
    if (i > 0) {
      c = cofactors<Dim>(r);
      det = r.row(0).dot(c.row(0));
    }
    const Matrix next = 0.5 * r + (0.5 / det) * c;
    if ((next - r).cwiseAbs().maxCoeff() < kConverged) {
      return next;
    }
    r = next;
  }
  return polarRotation<Dim>(d.f);
}

/// 0 at or below lo, 1 at or above hi, smooth (C1) in between.
inline double smoothStep(double x, double lo, double hi) {
  const double t = std::clamp((x - lo) / (hi - lo), 0.0, 1.0);
  return t * t * (3.0 - 2.0 * t);
}

/// |F^T F - I|^2 / 4 (Frobenius), the square of the Green strain, from the upper triangle of the
/// symmetric F^T F.
template <int Dim>
inline double greenStrainSquared(const Eigen::Matrix<double, Dim, Dim>& f) {
  double diagonal = 0.0;
  double off_diagonal = 0.0;
  for (int i = 0; i < Dim; ++i) {
    const double cii = f.col(i).squaredNorm() - 1.0;
    diagonal += cii * cii;
    for (int j = i + 1; j < Dim; ++j) {
      const double cij = f.col(i).dot(f.col(j));
      off_diagonal += cij * cij;
    }
  }
  return 0.25 * (diagonal + 2.0 * off_diagonal);
}

/// The rotation by the share t of r's angle about its axis (a faded element's, off the hot path).
template <int Dim>
[[gnu::noinline]] Eigen::Matrix<double, Dim, Dim> partialRotation(
    const Eigen::Matrix<double, Dim, Dim>& r, double t) {
  if constexpr (Dim == 3) {
    const Eigen::Quaterniond q(r);
    return Eigen::Quaterniond::Identity().slerp(t, q).toRotationMatrix();
  } else {
    return Eigen::Rotation2Dd(t * std::atan2(r(1, 0), r(0, 0))).toRotationMatrix();
  }
}

/// elementRotation of d.f; *polar (if given) says whether it is the whole polar rotation.
template <int Dim>
[[gnu::always_inline]] inline Eigen::Matrix<double, Dim, Dim> fadedRotation(
    const Deformation<Dim>& d, bool* polar = nullptr) {
  using Matrix = Eigen::Matrix<double, Dim, Dim>;
  if (polar) {
    *polar = false;
  }
  // The share of its polar rotation the element takes: all of it while it is sound (volume
  // ratio det F and Green strain within the small-strain range), none when crushed or strained
  // far beyond it, smooth in between.
  const double volume_share = smoothStep(d.det, kCrushedVolume, kSoundVolume);
  if (volume_share <= 0.0) {
    return Matrix::Identity();
  }
  // The Green strain's square first: its root only for an element beyond kSmallStrain.
  const double green_squared = greenStrainSquared<Dim>(d.f);
  const double t =
      green_squared <= kSmallStrain * kSmallStrain
          ? volume_share
          : volume_share * (1.0 - smoothStep(std::sqrt(green_squared), kSmallStrain, kLargeStrain));
  if (t <= 0.0) {
    return Matrix::Identity();
  }
  const Matrix r = newtonPolarRotation<Dim>(d);
  if (t < 1.0) {
    return partialRotation<Dim>(r, t);
  }
  if (polar) {
    *polar = true;
  }
  return r;
}

}  // namespace

template <int Dim>
Eigen::Matrix<double, Dim, Dim> fastPolarRotation(const Eigen::Matrix<double, Dim, Dim>& f) {
  return newtonPolarRotation<Dim>(Deformation<Dim>(f));
}

template <int Dim>
Eigen::Matrix<double, Dim, Dim> elementRotation(const Eigen::Matrix<double, Dim, Dim>& f) {
  return fadedRotation<Dim>(Deformation<Dim>(f));
}

template <int Dim>
CorotationalForces<Dim>::CorotationalForces(const SimplexMesh<Dim>& mesh,
                                            const std::vector<Material>& materials,
                                            double thickness_m)
    : mesh_(&mesh), materials_(materials), thickness_m_(thickness_m) {
  elements_.reserve(mesh.elements.size());
  for (int e = 0; e < mesh.elementCount(); ++e) {
    const Material& material = elementMaterial<Dim>(mesh, materials, e, "CorotationalForces");
    const Corners<Dim> c = corners<Dim>(mesh, e);
    const Eigen::Matrix<double, Dim + 1, Dim> grad = shapeGradients<Dim>(c);
    const double measure_m = std::abs(signedMeasure<Dim>(c)) * thickness_m;
    const LameParameters lame = lameParameters(material);
    PassElement el;
    for (int a = 0; a <= Dim; ++a) {
      el.dof[a] = Dim * mesh.elements[static_cast<std::size_t>(e)][a];
      for (int j = 0; j < Dim; ++j) {
        el.grad[a][j] = grad(a, j);
      }
    }
    el.measure_mu = measure_m * lame.mu_Pa;
    el.measure_lambda = measure_m * lame.lambda_Pa;
    elements_.push_back(el);
  }
}

namespace {

/// Cosine of the angle of the rotation r0^T r, from tr(r0^T r) = sum_ij r0_ij r_ij (decreasing
/// in the angle: the largest angle is found by the least cosine, one arc cosine per pass).
template <int Dim>
inline double relativeRotationCosine(const Eigen::Matrix<double, Dim, Dim>& r0,
                                     const Eigen::Matrix<double, Dim, Dim>& r) {
  return std::clamp(0.5 * (r0.cwiseProduct(r).sum() - (Dim - 2)), -1.0, 1.0);
}

/// Deformation gradient F = I + sum_a u_a grad_a^T of an element (PassElement) at u.
template <int Dim, typename Element>
inline Eigen::Matrix<double, Dim, Dim> deformationGradient(const Element& el, const double* u) {
  Eigen::Matrix<double, Dim, Dim> f = Eigen::Matrix<double, Dim, Dim>::Identity();
  for (int a = 0; a <= Dim; ++a) {
    const double* ua = u + el.dof[a];
    for (int j = 0; j < Dim; ++j) {
      for (int i = 0; i < Dim; ++i) {
        f(i, j) += ua[i] * el.grad[a][j];
      }
    }
  }
  return f;
}

/// |e| t sigma(H) of an element (PassElement) for the displacement gradient H (linearStress).
template <int Dim, typename Element>
inline Eigen::Matrix<double, Dim, Dim> elementStress(const Element& el,
                                                     const Eigen::Matrix<double, Dim, Dim>& h) {
  Eigen::Matrix<double, Dim, Dim> s = el.measure_mu * (h + h.transpose());
  s.diagonal().array() += el.measure_lambda * h.trace();
  return s;
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
  return deformationGradient<Dim>(elements_[static_cast<std::size_t>(e)], u.data());
}

template <int Dim>
Eigen::VectorXd CorotationalForces<Dim>::correction(const Eigen::VectorXd& u, int* inverted,
                                                    double* max_turn_rad) const {
  // An element whose deformation gradient is symmetric to this has no rotation: with the
  // identity as reference its corotated force equals the linear one (to this relative size), so
  // it adds nothing to g.
  constexpr double kNoRotation = 1e-12;
  Eigen::VectorXd g = Eigen::VectorXd::Zero(u.size());
  double* const gd = g.data();
  const double* const ud = u.data();
  const bool any_warped = !warped_.empty();
  int flipped = 0;
  double least_cosine = 1.0;
  const std::size_t n = elements_.size();
  for (std::size_t ei = 0; ei < n; ++ei) {
    const PassElement& el = elements_[ei];
    const bool warped = any_warped && warped_[ei];
    const Rotation f = deformationGradient<Dim>(el, ud);
    if (!warped && (f - f.transpose()).cwiseAbs().maxCoeff() < kNoRotation) {
      continue;
    }
    const Deformation<Dim> deformation(f);
    flipped += deformation.det > 0.0 ? 0 : 1;
    bool polar = false;
    const Rotation r = fadedRotation<Dim>(deformation, &polar);
    // R K_e (R^T x - X) - R_0 K_e R_0^T u with x = X + u. K_e d is |e| sigma(H) grad_a on
    // corner a (linearStress), H the gradient of the corner displacements d: R^T F - I for
    // d = R^T x - X, R_0^T (F - I) for d = R_0^T u. Nine stress entries per element instead of
    // two products with the 12 x 12 K_e; with the identity as reference the second term is
    // sigma(F - I) itself.
    Rotation p;
    if (polar) {
      // R^T F - I = S - I is symmetric for the polar rotation R of F = R S, and R S = F: the
      // rotated stress is 2 |e| mu (F - R) + |e| lambda tr(S - I) R.
      const double trace_h = r.cwiseProduct(f).sum() - Dim;
      p = (2.0 * el.measure_mu) * (f - r) + (el.measure_lambda * trace_h) * r;
    } else {
      Rotation h;
      h.noalias() = r.transpose() * f;
      h.diagonal().array() -= 1.0;
      p.noalias() = r * elementStress<Dim>(el, h);
    }
    Rotation h0 = f;
    h0.diagonal().array() -= 1.0;
    if (warped) {
      const Rotation& r0 = reference_[ei];
      least_cosine = std::min(least_cosine, relativeRotationCosine<Dim>(r0, r));
      const Rotation h0_turned = r0.transpose() * h0;
      p.noalias() -= r0 * elementStress<Dim>(el, h0_turned);
    } else {
      least_cosine = std::min(least_cosine, relativeRotationCosine<Dim>(Rotation::Identity(), r));
      p -= elementStress<Dim>(el, h0);
    }
    for (int a = 0; a <= Dim; ++a) {
      double* ga = gd + el.dof[a];
      for (int i = 0; i < Dim; ++i) {
        double sum = 0.0;
        for (int j = 0; j < Dim; ++j) {
          sum += p(i, j) * el.grad[a][j];
        }
        ga[i] += sum;
      }
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
