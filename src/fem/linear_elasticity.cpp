// Linear elasticity on simplices for Dim = 2 (plane strain) and Dim = 3 (linear_elasticity.h).
#include "needle_guidance/fem/linear_elasticity.h"

#include <Eigen/LU>
#include <Eigen/SVD>
#include <cmath>
#include <stdexcept>
#include <string>

#include "needle_guidance/format.h"

namespace needle_guidance::fem {
namespace {

template <int Dim>
Eigen::Matrix<double, Dim, Dim> edgeMatrix(const Corners<Dim>& c) {
  Eigen::Matrix<double, Dim, Dim> j;
  for (int k = 0; k < Dim; ++k) {
    j.col(k) = c[static_cast<std::size_t>(k + 1)] - c[0];
  }
  return j;
}

constexpr double factorial(int n) {
  return n <= 1 ? 1.0 : n * factorial(n - 1);
}

}  // namespace

void validateMaterial(const Material& m, const char* where) {
  if (!std::isfinite(m.young_modulus_Pa) || m.young_modulus_Pa <= 0.0) {
    throw std::invalid_argument(std::string(where) + ": Young's modulus " +
                                formatNumber(m.young_modulus_Pa, 6) + " Pa must be finite and > 0");
  }
  if (!std::isfinite(m.poisson_ratio) || m.poisson_ratio <= -1.0 || m.poisson_ratio >= 0.5) {
    throw std::invalid_argument(std::string(where) + ": Poisson ratio " +
                                formatNumber(m.poisson_ratio, 6) + " must be in (-1, 0.5)");
  }
}

template <int Dim>
double signedMeasure(const Corners<Dim>& c) {
  return edgeMatrix<Dim>(c).determinant() / factorial(Dim);
}

template <int Dim>
Eigen::Matrix<double, Dim + 1, Dim> shapeGradients(const Corners<Dim>& c) {
  const Eigen::Matrix<double, Dim, Dim> inv = edgeMatrix<Dim>(c).inverse();
  Eigen::Matrix<double, Dim + 1, Dim> g;
  g.template bottomRows<Dim>() = inv;  // grad lambda_k = row k-1 of J^-1
  g.row(0) = -inv.colwise().sum();
  return g;
}

template <int Dim>
Eigen::Matrix<double, Dim + 1, 1> barycentric(const Corners<Dim>& c, const Point<Dim>& p) {
  Eigen::Matrix<double, Dim + 1, 1> w;
  w.template tail<Dim>() = edgeMatrix<Dim>(c).partialPivLu().solve(p - c[0]);
  w(0) = 1.0 - w.template tail<Dim>().sum();
  return w;
}

LameParameters lameParameters(const Material& m) {
  const double nu = m.poisson_ratio;
  return {m.young_modulus_Pa * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
          m.young_modulus_Pa / (2.0 * (1.0 + nu))};
}

template <int Dim>
Eigen::Matrix<double, kStrainComponents<Dim>, kStrainComponents<Dim>> elasticityMatrix(
    const Material& m) {
  const LameParameters lame = lameParameters(m);
  const double lambda = lame.lambda_Pa;
  const double mu = lame.mu_Pa;
  Eigen::Matrix<double, kStrainComponents<Dim>, kStrainComponents<Dim>> d;
  d.setZero();
  d.template topLeftCorner<Dim, Dim>().setConstant(lambda);
  for (int i = 0; i < Dim; ++i) {
    d(i, i) += 2.0 * mu;
  }
  for (int i = Dim; i < kStrainComponents<Dim>; ++i) {
    d(i, i) = mu;
  }
  return d;
}

template <int Dim>
ElementMatrix<Dim> elementStiffness(const Corners<Dim>& c, const Material& material,
                                    double thickness_m) {
  const Eigen::Matrix<double, Dim + 1, Dim> g = shapeGradients<Dim>(c);
  // Shear pairs in Voigt order: (x, y) in 2-D; (x, y), (y, z), (z, x) in 3-D.
  constexpr int kPairs = kStrainComponents<Dim> - Dim;
  constexpr std::array<std::array<int, 2>, 3> kShear{{{0, 1}, {1, 2}, {2, 0}}};
  Eigen::Matrix<double, kStrainComponents<Dim>, kElementDofs<Dim>> b;
  b.setZero();
  for (int a = 0; a <= Dim; ++a) {
    for (int i = 0; i < Dim; ++i) {
      b(i, Dim * a + i) = g(a, i);
    }
    for (int s = 0; s < kPairs; ++s) {
      const int i = kShear[static_cast<std::size_t>(s)][0];
      const int j = kShear[static_cast<std::size_t>(s)][1];
      b(Dim + s, Dim * a + i) = g(a, j);
      b(Dim + s, Dim * a + j) = g(a, i);
    }
  }
  const double measure = std::abs(signedMeasure<Dim>(c)) * thickness_m;
  return measure * b.transpose() * elasticityMatrix<Dim>(material) * b;
}

template <int Dim>
Eigen::Matrix<double, Dim, Dim> polarRotation(const Eigen::Matrix<double, Dim, Dim>& f) {
  const Eigen::JacobiSVD<Eigen::Matrix<double, Dim, Dim>> svd(
      f, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix<double, Dim, Dim> u = svd.matrixU();
  const Eigen::Matrix<double, Dim, Dim> v = svd.matrixV();
  if ((u * v.transpose()).determinant() < 0.0) {
    u.col(Dim - 1) *= -1.0;  // the smallest singular value takes the reflection
  }
  return u * v.transpose();
}

template <int Dim>
CorotatedElement<Dim> corotatedElement(const Corners<Dim>& reference, const Corners<Dim>& displaced,
                                       const Material& material, double thickness_m) {
  const Eigen::Matrix<double, Dim + 1, Dim> g = shapeGradients<Dim>(reference);
  Eigen::Matrix<double, Dim, Dim> f = Eigen::Matrix<double, Dim, Dim>::Zero();
  Point<Dim> x_mean = Point<Dim>::Zero(), X_mean = Point<Dim>::Zero();
  for (int a = 0; a <= Dim; ++a) {
    f += displaced[static_cast<std::size_t>(a)] * g.row(a);
    x_mean += displaced[static_cast<std::size_t>(a)] / double(Dim + 1);
    X_mean += reference[static_cast<std::size_t>(a)] / double(Dim + 1);
  }
  CorotatedElement<Dim> out;
  out.rotation = polarRotation<Dim>(f);
  const ElementMatrix<Dim> ke = elementStiffness<Dim>(reference, material, thickness_m);
  ElementMatrix<Dim> rb = ElementMatrix<Dim>::Zero();
  Eigen::Matrix<double, kElementDofs<Dim>, 1> d;
  for (int a = 0; a <= Dim; ++a) {
    const auto k = static_cast<std::size_t>(a);
    rb.template block<Dim, Dim>(Dim * a, Dim * a) = out.rotation;
    d.template segment<Dim>(Dim * a) =
        out.rotation.transpose() * (displaced[k] - x_mean) - (reference[k] - X_mean);
  }
  out.force = rb * (ke * d);
  out.tangent = rb * ke * rb.transpose();
  return out;
}

template <int Dim>
Corners<Dim> corners(const SimplexMesh<Dim>& mesh, int element) {
  Corners<Dim> c;
  const auto& nodes = mesh.elements[static_cast<std::size_t>(element)];
  for (int k = 0; k <= Dim; ++k) {
    c[static_cast<std::size_t>(k)] = mesh.nodes[static_cast<std::size_t>(nodes[k])];
  }
  return c;
}

template <int Dim>
const Material& elementMaterial(const SimplexMesh<Dim>& mesh,
                                const std::vector<Material>& materials, int e, const char* who) {
  const std::size_t ei = static_cast<std::size_t>(e);
  const int mat = ei < mesh.element_material.size() ? mesh.element_material[ei] : -1;
  if (mat < 0 || mat >= static_cast<int>(materials.size())) {
    throw std::invalid_argument(std::string(who) + ": element " + std::to_string(e) +
                                ": material index " + std::to_string(mat) + " out of range (" +
                                std::to_string(materials.size()) + " materials)");
  }
  return materials[static_cast<std::size_t>(mat)];
}

template <int Dim>
SparseMatrix assembleStiffness(const SimplexMesh<Dim>& mesh, const std::vector<Material>& materials,
                               double thickness_m, double min_measure) {
  if (mesh.element_material.size() != mesh.elements.size()) {
    throw std::invalid_argument(
        "assembleStiffness: " + std::to_string(mesh.element_material.size()) +
        " material indices for " + std::to_string(mesh.elements.size()) + " elements");
  }
  for (std::size_t i = 0; i < materials.size(); ++i) {
    validateMaterial(materials[i], ("material " + std::to_string(i)).c_str());
  }
  const int n = Dim * mesh.nodeCount();
  std::vector<Eigen::Triplet<double>> triplets;
  triplets.reserve(mesh.elements.size() * kElementDofs<Dim> * kElementDofs<Dim>);
  for (int e = 0; e < mesh.elementCount(); ++e) {
    const Material& material = elementMaterial<Dim>(mesh, materials, e, "assembleStiffness");
    const Corners<Dim> c = corners<Dim>(mesh, e);
    const double measure = signedMeasure<Dim>(c);
    if (!(measure > min_measure)) {
      throw std::invalid_argument("assembleStiffness: element " + std::to_string(e) +
                                  " has signed measure " + formatNumber(measure, 6) + " m^" +
                                  std::to_string(Dim) + " (<= " + formatNumber(min_measure, 6) +
                                  "): inverted or degenerate");
    }
    const ElementMatrix<Dim> k = elementStiffness<Dim>(c, material, thickness_m);
    const auto& nodes = mesh.elements[static_cast<std::size_t>(e)];
    for (int a = 0; a < kElementDofs<Dim>; ++a) {
      const int ga = Dim * nodes[a / Dim] + a % Dim;
      for (int b = 0; b < kElementDofs<Dim>; ++b) {
        triplets.emplace_back(ga, Dim * nodes[b / Dim] + b % Dim, k(a, b));
      }
    }
  }
  SparseMatrix kg(n, n);
  kg.setFromTriplets(triplets.begin(), triplets.end());
  return kg;
}

#define NG_FEM_INSTANTIATE(D)                                                                      \
  template double signedMeasure<D>(const Corners<D>&);                                             \
  template Eigen::Matrix<double, D + 1, D> shapeGradients<D>(const Corners<D>&);                   \
  template Eigen::Matrix<double, D + 1, 1> barycentric<D>(const Corners<D>&, const Point<D>&);     \
  template Eigen::Matrix<double, kStrainComponents<D>, kStrainComponents<D>> elasticityMatrix<D>(  \
      const Material&);                                                                            \
  template ElementMatrix<D> elementStiffness<D>(const Corners<D>&, const Material&, double);       \
  template Corners<D> corners<D>(const SimplexMesh<D>&, int);                                      \
  template const Material& elementMaterial<D>(const SimplexMesh<D>&, const std::vector<Material>&, \
                                              int, const char*);                                   \
  template Eigen::Matrix<double, D, D> polarRotation<D>(const Eigen::Matrix<double, D, D>&);       \
  template CorotatedElement<D> corotatedElement<D>(const Corners<D>&, const Corners<D>&,           \
                                                   const Material&, double);                       \
  template SparseMatrix assembleStiffness<D>(const SimplexMesh<D>&, const std::vector<Material>&,  \
                                             double, double);
NG_FEM_INSTANTIATE(2)
NG_FEM_INSTANTIATE(3)
#undef NG_FEM_INSTANTIATE

}  // namespace needle_guidance::fem
