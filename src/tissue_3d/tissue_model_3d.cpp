// TissueModel3: stiffness assembly, the factored compliance and a uniform-grid element locator
// (needle_insertion_3d.h).
#include <algorithm>
#include <cmath>
#include <ctime>
#include <stdexcept>

#include "needle_guidance/tissue_3d/needle_insertion_3d.h"

namespace needle_guidance::tissue_3d {

/// Elements bucketed by their bounding boxes on a uniform grid of about one element per cell.
struct TissueModel3::Grid {
  Vector3 lo, cell;
  Eigen::Vector3i n;
  std::vector<std::vector<int>> buckets;
  int index(const Eigen::Vector3i& c) const { return (c.z() * n.y() + c.y()) * n.x() + c.x(); }
  Eigen::Vector3i cellOf(const Vector3& p) const {
    Eigen::Vector3i c;
    for (int k = 0; k < 3; ++k) {
      c(k) = std::clamp(static_cast<int>(std::floor((p(k) - lo(k)) / cell(k))), 0, n(k) - 1);
    }
    return c;
  }
};

namespace {

/// The rotation of the polar decomposition F = R S: Newton's iteration R <- (R + R^-T) / 2
/// from F (Higham 1986), quadratic and a few 3 x 3 inverses for the near-rigid elements of
/// tissue; the SVD (fem::polarRotation) for an inverted or nearly flat F, or if it stalls.
Eigen::Matrix3d polarRotation3(const Eigen::Matrix3d& f) {
  constexpr double kMinDet = 0.1;
  constexpr double kConverged = 1e-13;
  constexpr int kMaxIterations = 12;
  if (!(f.determinant() > kMinDet)) {
    return fem::polarRotation<3>(f);
  }
  Eigen::Matrix3d r = f;
  for (int i = 0; i < kMaxIterations; ++i) {
    const Eigen::Matrix3d next = 0.5 * (r + r.inverse().transpose());
    if ((next - r).cwiseAbs().maxCoeff() < kConverged) {
      return next;
    }
    r = next;
  }
  return fem::polarRotation<3>(f);
}

}  // namespace

TissueModel3::TissueModel3(TetMesh3 mesh, const std::vector<fem::Material>& materials,
                           bool corotational)
    : mesh_(std::move(mesh)), corotational_(corotational) {
  const std::clock_t start = std::clock();
  const fem::SparseMatrix k = fem::assembleStiffness<3>(mesh_, materials);
  if (corotational_) {
    gradients_.reserve(mesh_.elements.size());
    element_stiffness_.reserve(mesh_.elements.size());
    for (int e = 0; e < mesh_.elementCount(); ++e) {
      const fem::Corners<3> c = fem::corners<3>(mesh_, e);
      gradients_.push_back(fem::shapeGradients<3>(c));
      element_stiffness_.push_back(
          fem::elementStiffness<3>(c, materials[static_cast<std::size_t>(
                                          mesh_.element_material[static_cast<std::size_t>(e)])]));
    }
  }
  std::vector<char> fixed(static_cast<std::size_t>(3 * mesh_.nodeCount()), 0);
  for (int i = 0; i < mesh_.nodeCount(); ++i) {
    if (mesh_.node_fixed[static_cast<std::size_t>(i)]) {
      for (int d = 0; d < 3; ++d) {
        fixed[static_cast<std::size_t>(3 * i + d)] = 1;
      }
    }
  }
  compliance_ = std::make_unique<fem::CondensedCompliance>(k, fixed);
  assembly_cpu_s_ = static_cast<double>(std::clock() - start) / CLOCKS_PER_SEC;

  grid_ = std::make_unique<Grid>();
  Vector3 lo = mesh_.nodes[0], hi = mesh_.nodes[0];
  for (const auto& p : mesh_.nodes) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  const double per_cell = std::cbrt((hi - lo).prod() / std::max(1, mesh_.elementCount()));
  grid_->lo = lo;
  for (int k = 0; k < 3; ++k) {
    grid_->n(k) = std::max(1, static_cast<int>((hi(k) - lo(k)) / (2.0 * per_cell)));
    grid_->cell(k) = (hi(k) - lo(k)) / grid_->n(k);
  }
  grid_->buckets.resize(static_cast<std::size_t>(grid_->n.prod()));
  for (int e = 0; e < mesh_.elementCount(); ++e) {
    const fem::Corners<3> c = fem::corners<3>(mesh_, e);
    Vector3 a = c[0], b = c[0];
    for (const auto& p : c) {
      a = a.cwiseMin(p);
      b = b.cwiseMax(p);
    }
    const Eigen::Vector3i ca = grid_->cellOf(a), cb = grid_->cellOf(b);
    for (int z = ca.z(); z <= cb.z(); ++z) {
      for (int y = ca.y(); y <= cb.y(); ++y) {
        for (int x = ca.x(); x <= cb.x(); ++x) {
          grid_->buckets[static_cast<std::size_t>(grid_->index({x, y, z}))].push_back(e);
        }
      }
    }
  }
}

TissueModel3::~TissueModel3() = default;

Eigen::VectorXd TissueModel3::corotationDisplacement(const Eigen::VectorXd& u) const {
  // An element whose deformation gradient is symmetric to this has no rotation: its corotated
  // force equals the linear one (to this relative size), so it adds nothing to g.
  constexpr double kNoRotation = 1e-12;
  if (!corotational_) {
    return {};
  }
  const std::clock_t start = std::clock();
  Eigen::VectorXd g = Eigen::VectorXd::Zero(3 * mesh_.nodeCount());
  int inverted = 0;
  using Vector12 = Eigen::Matrix<double, 12, 1>;
  for (int e = 0; e < mesh_.elementCount(); ++e) {
    const auto& nodes = mesh_.elements[static_cast<std::size_t>(e)];
    const Eigen::Matrix<double, 4, 3>& grad = gradients_[static_cast<std::size_t>(e)];
    Eigen::Matrix3d f = Eigen::Matrix3d::Identity();
    Vector12 ue, xe_ref;
    for (int a = 0; a < 4; ++a) {
      ue.segment<3>(3 * a) = u.segment<3>(3 * nodes[a]);
      xe_ref.segment<3>(3 * a) = mesh_.nodes[static_cast<std::size_t>(nodes[a])];
      f += ue.segment<3>(3 * a) * grad.row(a);
    }
    if ((f - f.transpose()).cwiseAbs().maxCoeff() < kNoRotation) {
      continue;
    }
    // An element the point-like tip load inverts (det F <= 0; the linear field does that next
    // to the tip on fine meshes) takes the proper rotation nearest to F: polarRotation flips
    // the smallest singular direction (as invertible FEM does), so its force stays finite.
    inverted += f.determinant() > 0.0 ? 0 : 1;
    const Eigen::Matrix3d r = polarRotation3(f);
    // R K_e (R^T x - X) - K_e u with x = X + u.
    Vector12 local;
    for (int a = 0; a < 4; ++a) {
      local.segment<3>(3 * a) = r.transpose() * (xe_ref.segment<3>(3 * a) + ue.segment<3>(3 * a)) -
                                xe_ref.segment<3>(3 * a);
    }
    const fem::ElementMatrix<3>& ke = element_stiffness_[static_cast<std::size_t>(e)];
    const Vector12 kl = ke * local, ku = ke * ue;
    for (int a = 0; a < 4; ++a) {
      g.segment<3>(3 * nodes[a]) += r * kl.segment<3>(3 * a) - ku.segment<3>(3 * a);
    }
  }
  inverted_elements_ = inverted;
  Eigen::VectorXd v = -compliance_->solve(g);
  corotation_cpu_s_ += static_cast<double>(std::clock() - start) / CLOCKS_PER_SEC;
  if (!v.allFinite()) {
    throw std::runtime_error("TissueModel3: the corotational displacement is not finite");
  }
  return v;
}

std::optional<EmbeddedPoint> TissueModel3::locate(const Vector3& p) const {
  constexpr double kInsideTol = 1e-9;  // barycentric, round-off on shared faces
  const auto& bucket = grid_->buckets[static_cast<std::size_t>(grid_->index(grid_->cellOf(p)))];
  EmbeddedPoint best;
  double best_min = -1e300;
  for (int e : bucket) {
    const Eigen::Vector4d w = fem::barycentric<3>(fem::corners<3>(mesh_, e), p);
    if (w.minCoeff() > best_min) {
      best_min = w.minCoeff();
      best.element = e;
      best.weights = w;
    }
  }
  if (best.element < 0 || best_min < -kInsideTol) {
    return std::nullopt;
  }
  best.reference_m = p;
  return best;
}

}  // namespace needle_guidance::tissue_3d
