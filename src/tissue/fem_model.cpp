// Plane-strain linear-elastic FEM on linear triangles (dissertation 2.1.4, 2.2.2) and reference
// mesh node moves for needle cutting (2.3.4).
//
// The global matrices are sums of small dense "blocks": one per triangle (6 DOFs: stiffness,
// consistent mass, Rayleigh damping) and, for ElementFormulation::kAveragedVolumetric, one per
// node (the node's patch DOFs: the averaged volumetric stiffness). K, M and C share one sparsity
// pattern, built once from the union of the block patterns; moveNode recomputes the changed
// blocks and re-sums exactly the affected entries, so the pattern never changes.
#include "needle_guidance/tissue/fem_model.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <string>

#include "needle_guidance/format.h"

namespace needle_guidance::tissue {
namespace {

using Matrix6 = Eigen::Matrix<double, 6, 6>;
using Matrix36 = Eigen::Matrix<double, 3, 6>;
using Vector6 = Eigen::Matrix<double, 6, 1>;

std::string fmt(double value) {
  return formatNumber(value, 9);
}

/// Geometry of a constant-strain triangle: signed area and the strain-displacement matrix B
/// (Voigt [exx, eyy, gamma_xy], engineering shear) for the DOF order (x0, y0, x1, y1, x2, y2).
struct CstGeometry {
  double area_m2 = 0.0;
  Matrix36 B = Matrix36::Zero();
  /// Row vector mapping element DOFs to the in-plane volumetric strain exx + eyy.
  Vector6 div = Vector6::Zero();
};

double signedArea(const Point2& a, const Point2& b, const Point2& c) {
  return 0.5 * ((b.x() - a.x()) * (c.y() - a.y()) - (c.x() - a.x()) * (b.y() - a.y()));
}

CstGeometry cstGeometry(const Point2& p0, const Point2& p1, const Point2& p2) {
  CstGeometry g;
  g.area_m2 = signedArea(p0, p1, p2);
  const std::array<const Point2*, 3> p{&p0, &p1, &p2};
  const double inv_2a = 1.0 / (2.0 * g.area_m2);
  for (int i = 0; i < 3; ++i) {
    const Point2& pj = *p[(i + 1) % 3];
    const Point2& pk = *p[(i + 2) % 3];
    const double b = (pj.y() - pk.y()) * inv_2a;  // dN_i/dx
    const double c = (pk.x() - pj.x()) * inv_2a;  // dN_i/dy
    g.B(0, 2 * i) = b;
    g.B(1, 2 * i + 1) = c;
    g.B(2, 2 * i) = c;
    g.B(2, 2 * i + 1) = b;
    g.div(2 * i) = b;
    g.div(2 * i + 1) = c;
  }
  return g;
}

double lameLambda(const ElementMaterial& m) {
  return m.young_modulus_Pa * m.poisson_ratio /
         ((1.0 + m.poisson_ratio) * (1.0 - 2.0 * m.poisson_ratio));
}
double shearModulus(const ElementMaterial& m) {
  return m.young_modulus_Pa / (2.0 * (1.0 + m.poisson_ratio));
}
/// 3-D bulk modulus; with e_zz = 0 (plane strain) the 3-D volumetric strain is exx + eyy.
double bulkModulus(const ElementMaterial& m) {
  return lameLambda(m) + 2.0 * shearModulus(m) / 3.0;
}

/// Plane-strain elasticity matrix (Voigt, engineering shear): lambda m m^T + mu diag(2, 2, 1).
Eigen::Matrix3d planeStrainD(const ElementMaterial& m) {
  const double lambda = lameLambda(m);
  const double mu = shearModulus(m);
  Eigen::Matrix3d d;
  d << lambda + 2.0 * mu, lambda, 0.0, lambda, lambda + 2.0 * mu, 0.0, 0.0, 0.0, mu;
  return d;
}

/// Deviatoric part of the plane-strain elasticity: D = D_dev + kappa m m^T with the 3-D split
/// W = mu e_dev : e_dev + kappa / 2 theta^2 (e_zz = 0, theta = exx + eyy).
Eigen::Matrix3d planeStrainDeviatoricD(const ElementMaterial& m) {
  const double mu = shearModulus(m);
  Eigen::Matrix3d d;
  d << 4.0 / 3.0 * mu, -2.0 / 3.0 * mu, 0.0, -2.0 / 3.0 * mu, 4.0 / 3.0 * mu, 0.0, 0.0, 0.0, mu;
  return d;
}

void validateMaterial(const ElementMaterial& m, std::size_t t) {
  auto fail = [&](const std::string& what) {
    throw std::invalid_argument("FemModel: element " + std::to_string(t) + ": " + what);
  };
  if (!std::isfinite(m.young_modulus_Pa) || m.young_modulus_Pa <= 0.0) {
    fail("Young's modulus " + fmt(m.young_modulus_Pa) + " Pa must be finite and > 0");
  }
  if (!std::isfinite(m.poisson_ratio) || m.poisson_ratio <= -1.0 || m.poisson_ratio >= 0.5) {
    fail("Poisson ratio " + fmt(m.poisson_ratio) + " must be in (-1, 0.5)");
  }
  if (!std::isfinite(m.density_kg_m3) || m.density_kg_m3 <= 0.0) {
    fail("density " + fmt(m.density_kg_m3) + " kg/m^3 must be finite and > 0");
  }
  if (!std::isfinite(m.rayleigh_alpha_per_s) || m.rayleigh_alpha_per_s < 0.0) {
    fail("Rayleigh alpha " + fmt(m.rayleigh_alpha_per_s) + " 1/s must be finite and >= 0");
  }
  if (!std::isfinite(m.rayleigh_beta_s) || m.rayleigh_beta_s < 0.0) {
    fail("Rayleigh beta " + fmt(m.rayleigh_beta_s) + " s must be finite and >= 0");
  }
}

}  // namespace

struct FemModel::Impl {
  // Element blocks (one per triangle, DOFs 2*node, 2*node+1 of its three nodes).
  std::vector<Matrix6> element_k;  ///< stiffness (deviatoric part for averaged) [N/m]
  std::vector<Matrix6> element_m;  ///< consistent mass [kg]
  std::vector<std::array<int, 36>> element_entry;  ///< value index in the shared pattern
  // Nodal volumetric blocks (kAveragedVolumetric only), one per node over its patch DOFs.
  std::vector<std::vector<int>> patch_nodes;  ///< node itself and its 1-ring, sorted
  std::vector<Eigen::VectorXd> nodal_g;       ///< d theta_a / d u_patch [1/m]
  std::vector<double> nodal_coef;             ///< thickness * V_a * kappa_a [N m]
  std::vector<double> nodal_kappa;            ///< patch-averaged bulk modulus [Pa]
  std::vector<double> nodal_beta;             ///< patch-averaged Rayleigh beta [s]
  std::vector<std::vector<int>> nodal_entry;  ///< value index in the shared pattern
  std::vector<char> dof_mark;                 ///< scratch marker, size dofCount

  /// Recomputes the element blocks of `triangles` and the nodal blocks of `nodes`.
  static void recomputeBlocks(FemModel& model, const std::vector<int>& triangles,
                              const std::vector<int>& nodes);
  /// Re-sums K, M, C entries (i, j) with i, j both in `dofs` from all blocks, and the lumped
  /// mass of their nodes.
  static void resumEntries(FemModel& model, const std::vector<int>& dofs);
  /// Visits every stiffness block in the corotational frame at displacement u:
  /// visit(dofs, entries, K_rot, M_or_null, alpha, beta, f_int) with K_rot = R K_b R^T and the
  /// block's elastic force f_int = R K_b (R^T x - X).
  template <typename Visit>
  static void visitCorotational(const FemModel& model, const Eigen::VectorXd& u, Visit&& visit);
};

namespace {

/// Index of entry (row, col) in a compressed column-major matrix, or -1.
int entryIndex(const SparseMatrix& a, int row, int col) {
  const int* inner = a.innerIndexPtr();
  const int begin = a.outerIndexPtr()[col];
  const int end = a.outerIndexPtr()[col + 1];
  const int* it = std::lower_bound(inner + begin, inner + end, row);
  if (it == inner + end || *it != row)
    return -1;
  return static_cast<int>(it - inner);
}

}  // namespace

FemModel::FemModel(const FemModel& other)
    : mesh_(other.mesh_),
      materials_(other.materials_),
      options_(other.options_),
      K_(other.K_),
      M_(other.M_),
      C_(other.C_),
      m_lumped_(other.m_lumped_),
      node_triangles_(other.node_triangles_),
      impl_(std::make_shared<Impl>(*other.impl_)) {}

FemModel& FemModel::operator=(const FemModel& other) {
  if (this != &other) {
    FemModel copy(other);
    *this = std::move(copy);
  }
  return *this;
}

FemModel::~FemModel() = default;

FemModel::FemModel(geometry::TriangleMesh mesh, std::vector<ElementMaterial> element_materials,
                   const FemOptions& options)
    : mesh_(std::move(mesh)),
      materials_(std::move(element_materials)),
      options_(options),
      impl_(std::make_shared<Impl>()) {
  const std::size_t n_tri = mesh_.triangles.size();
  const int n_nodes = static_cast<int>(mesh_.nodes.size());
  if (!std::isfinite(options_.thickness_m) || options_.thickness_m <= 0.0) {
    throw std::invalid_argument("FemModel: thickness " + fmt(options_.thickness_m) +
                                " m must be finite and > 0");
  }
  if (materials_.size() != n_tri) {
    throw std::invalid_argument("FemModel: " + std::to_string(materials_.size()) +
                                " materials for " + std::to_string(n_tri) + " triangles");
  }
  if (n_tri == 0)
    throw std::invalid_argument("FemModel: the mesh has no triangles");
  for (int i = 0; i < n_nodes; ++i) {
    if (!mesh_.nodes[i].allFinite()) {
      throw std::invalid_argument("FemModel: node " + std::to_string(i) +
                                  " has a non-finite coordinate");
    }
  }
  node_triangles_.assign(n_nodes, {});
  for (std::size_t t = 0; t < n_tri; ++t) {
    validateMaterial(materials_[t], t);
    const auto& tri = mesh_.triangles[t];
    for (int k = 0; k < 3; ++k) {
      if (tri[k] < 0 || tri[k] >= n_nodes) {
        throw std::invalid_argument("FemModel: element " + std::to_string(t) + " uses node " +
                                    std::to_string(tri[k]) + " out of range [0, " +
                                    std::to_string(n_nodes) + ")");
      }
    }
    if (tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2]) {
      throw std::invalid_argument("FemModel: element " + std::to_string(t) + " repeats a node");
    }
    const double area = signedArea(mesh_.nodes[tri[0]], mesh_.nodes[tri[1]], mesh_.nodes[tri[2]]);
    if (!(area > 0.0)) {
      throw std::invalid_argument("FemModel: element " + std::to_string(t) +
                                  " is inverted or degenerate (signed area " + fmt(area) +
                                  " m^2 <= 0)");
    }
    for (int k = 0; k < 3; ++k)
      node_triangles_[tri[k]].push_back(static_cast<int>(t));
  }

  Impl& im = *impl_;
  im.element_k.resize(n_tri);
  im.element_m.resize(n_tri);
  im.element_entry.resize(n_tri);
  im.dof_mark.assign(dofCount(), 0);
  const bool averaged = options_.formulation == ElementFormulation::kAveragedVolumetric;
  if (averaged) {
    im.patch_nodes.resize(n_nodes);
    for (int a = 0; a < n_nodes; ++a) {
      std::vector<int>& patch = im.patch_nodes[a];
      patch.push_back(a);
      for (int t : node_triangles_[a])
        patch.insert(patch.end(), mesh_.triangles[t].begin(), mesh_.triangles[t].end());
      std::sort(patch.begin(), patch.end());
      patch.erase(std::unique(patch.begin(), patch.end()), patch.end());
    }
    im.nodal_g.resize(n_nodes);
    im.nodal_coef.assign(n_nodes, 0.0);
    im.nodal_kappa.assign(n_nodes, 0.0);
    im.nodal_beta.assign(n_nodes, 0.0);
    im.nodal_entry.resize(n_nodes);
  }

  // Shared sparsity pattern: union of all block patterns.
  std::vector<Eigen::Triplet<double>> pattern;
  pattern.reserve(36 * n_tri);
  for (std::size_t t = 0; t < n_tri; ++t) {
    const auto& tri = mesh_.triangles[t];
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b)
        for (int i = 0; i < 2; ++i)
          for (int j = 0; j < 2; ++j)
            pattern.emplace_back(2 * tri[a] + i, 2 * tri[b] + j, 0.0);
  }
  if (averaged) {
    for (int a = 0; a < n_nodes; ++a) {
      for (int p : im.patch_nodes[a])
        for (int q : im.patch_nodes[a])
          for (int i = 0; i < 2; ++i)
            for (int j = 0; j < 2; ++j)
              pattern.emplace_back(2 * p + i, 2 * q + j, 0.0);
    }
  }
  K_.resize(dofCount(), dofCount());
  K_.setFromTriplets(pattern.begin(), pattern.end());
  K_.makeCompressed();
  pattern.clear();
  pattern.shrink_to_fit();
  for (std::size_t t = 0; t < n_tri; ++t) {
    const auto& tri = mesh_.triangles[t];
    for (int r = 0; r < 6; ++r)
      for (int c = 0; c < 6; ++c)
        im.element_entry[t][6 * c + r] =
            entryIndex(K_, 2 * tri[r / 2] + r % 2, 2 * tri[c / 2] + c % 2);
  }
  if (averaged) {
    for (int a = 0; a < n_nodes; ++a) {
      const auto& patch = im.patch_nodes[a];
      const int nd = 2 * static_cast<int>(patch.size());
      im.nodal_entry[a].resize(static_cast<std::size_t>(nd) * nd);
      for (int r = 0; r < nd; ++r)
        for (int c = 0; c < nd; ++c)
          im.nodal_entry[a][static_cast<std::size_t>(c) * nd + r] =
              entryIndex(K_, 2 * patch[r / 2] + r % 2, 2 * patch[c / 2] + c % 2);
    }
  }
  M_ = K_;
  C_ = K_;
  m_lumped_ = Eigen::VectorXd::Zero(dofCount());

  std::vector<int> all_tris(n_tri);
  for (std::size_t t = 0; t < n_tri; ++t)
    all_tris[t] = static_cast<int>(t);
  std::vector<int> all_nodes(n_nodes);
  for (int a = 0; a < n_nodes; ++a)
    all_nodes[a] = a;
  Impl::recomputeBlocks(*this, all_tris, all_nodes);
  std::vector<int> all_dofs(dofCount());
  for (int d = 0; d < dofCount(); ++d)
    all_dofs[d] = d;
  Impl::resumEntries(*this, all_dofs);
}

int FemModel::nodeCount() const {
  return static_cast<int>(mesh_.nodes.size());
}

const std::vector<int>& FemModel::trianglesOfNode(int node) const {
  if (node < 0 || node >= nodeCount()) {
    throw std::invalid_argument("FemModel::trianglesOfNode: node " + std::to_string(node) +
                                " out of range");
  }
  return node_triangles_[node];
}

void FemModel::Impl::recomputeBlocks(FemModel& model, const std::vector<int>& triangles,
                                     const std::vector<int>& nodes) {
  Impl& im = *model.impl_;
  const auto& mesh_ = model.mesh_;
  const auto& materials_ = model.materials_;
  const auto& options_ = model.options_;
  const auto& node_triangles_ = model.node_triangles_;
  const double t_m = options_.thickness_m;
  const bool averaged = options_.formulation == ElementFormulation::kAveragedVolumetric;
  for (int t : triangles) {
    const auto& tri = mesh_.triangles[t];
    const ElementMaterial& mat = materials_[t];
    const CstGeometry g =
        cstGeometry(mesh_.nodes[tri[0]], mesh_.nodes[tri[1]], mesh_.nodes[tri[2]]);
    const Eigen::Matrix3d d = averaged ? planeStrainDeviatoricD(mat) : planeStrainD(mat);
    im.element_k[t] = (t_m * g.area_m2) * g.B.transpose() * d * g.B;
    // Consistent mass of the linear triangle: rho A t / 12 [2 1 1; 1 2 1; 1 1 2] per direction.
    const double m12 = mat.density_kg_m3 * g.area_m2 * t_m / 12.0;
    Matrix6& me = im.element_m[t];
    me.setZero();
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b)
        for (int i = 0; i < 2; ++i)
          me(2 * a + i, 2 * b + i) = (a == b ? 2.0 : 1.0) * m12;
  }
  if (!averaged)
    return;
  // Average nodal volumetric strain (Bonet & Burton 1998, "A simple average nodal pressure
  // tetrahedral element for incompressible and nearly incompressible dynamic explicit
  // applications", Commun. Numer. Meth. Engng 14; equivalently the volumetric part of Dohrmann et
  // al. 2000, node-based uniform strain): theta_a = sum_e (A_e/3) theta_e / V_a with
  // V_a = sum_e A_e / 3, and volumetric energy sum_a t V_a kappa_a theta_a^2 / 2. One pressure
  // per node instead of per element removes the over-constraint that locks linear triangles.
  for (int a : nodes) {
    const auto& patch = im.patch_nodes[a];
    Eigen::VectorXd gvec = Eigen::VectorXd::Zero(2 * static_cast<Eigen::Index>(patch.size()));
    double volume = 0.0, kappa_v = 0.0, kappa_beta_v = 0.0;
    for (int t : node_triangles_[a]) {
      const auto& tri = mesh_.triangles[t];
      const CstGeometry g =
          cstGeometry(mesh_.nodes[tri[0]], mesh_.nodes[tri[1]], mesh_.nodes[tri[2]]);
      const double w = g.area_m2 / 3.0;
      const double kappa = bulkModulus(materials_[t]);
      volume += w;
      kappa_v += w * kappa;
      kappa_beta_v += w * kappa * materials_[t].rayleigh_beta_s;
      for (int k = 0; k < 3; ++k) {
        const int local =
            static_cast<int>(std::lower_bound(patch.begin(), patch.end(), tri[k]) - patch.begin());
        gvec(2 * local) += w * g.div(2 * k);
        gvec(2 * local + 1) += w * g.div(2 * k + 1);
      }
    }
    im.nodal_g[a] = gvec / volume;
    im.nodal_kappa[a] = kappa_v / volume;
    im.nodal_coef[a] = t_m * kappa_v;  // t V_a kappa_a
    im.nodal_beta[a] = kappa_beta_v / kappa_v;
  }
}

void FemModel::Impl::resumEntries(FemModel& model, const std::vector<int>& dofs) {
  Impl& im = *model.impl_;
  const auto& mesh_ = model.mesh_;
  const auto& materials_ = model.materials_;
  const auto& options_ = model.options_;
  const auto& node_triangles_ = model.node_triangles_;
  auto& K_ = model.K_;
  auto& M_ = model.M_;
  auto& C_ = model.C_;
  auto& m_lumped_ = model.m_lumped_;
  std::vector<char>& mark = im.dof_mark;
  for (int d : dofs)
    mark[d] = 1;
  double* k = K_.valuePtr();
  double* m = M_.valuePtr();
  double* c = C_.valuePtr();
  const int* inner = K_.innerIndexPtr();
  const int* outer = K_.outerIndexPtr();
  for (int col : dofs) {
    for (int idx = outer[col]; idx < outer[col + 1]; ++idx) {
      if (mark[inner[idx]])
        k[idx] = m[idx] = c[idx] = 0.0;
    }
  }
  // Blocks touching an affected DOF: triangles of the affected nodes and, for the averaged
  // formulation, the nodal blocks of the affected nodes' patches (patch membership is symmetric).
  std::vector<int> nodes;
  nodes.reserve(dofs.size());
  for (int d : dofs)
    nodes.push_back(d / 2);
  std::sort(nodes.begin(), nodes.end());
  nodes.erase(std::unique(nodes.begin(), nodes.end()), nodes.end());
  std::vector<int> tris;
  for (int a : nodes)
    tris.insert(tris.end(), node_triangles_[a].begin(), node_triangles_[a].end());
  std::sort(tris.begin(), tris.end());
  tris.erase(std::unique(tris.begin(), tris.end()), tris.end());
  const bool full = static_cast<int>(dofs.size()) == model.dofCount();
  for (int t : tris) {
    const auto& tri = mesh_.triangles[t];
    const ElementMaterial& mat = materials_[t];
    const Matrix6& ke = im.element_k[t];
    const Matrix6& me = im.element_m[t];
    const auto& entry = im.element_entry[t];
    for (int cc = 0; cc < 6; ++cc) {
      if (!full && !mark[2 * tri[cc / 2] + cc % 2])
        continue;
      for (int r = 0; r < 6; ++r) {
        if (!full && !mark[2 * tri[r / 2] + r % 2])
          continue;
        const int idx = entry[6 * cc + r];
        k[idx] += ke(r, cc);
        m[idx] += me(r, cc);
        c[idx] += mat.rayleigh_alpha_per_s * me(r, cc) + mat.rayleigh_beta_s * ke(r, cc);
      }
    }
  }
  if (options_.formulation == ElementFormulation::kAveragedVolumetric) {
    std::vector<int> blocks;
    for (int a : nodes)
      blocks.insert(blocks.end(), im.patch_nodes[a].begin(), im.patch_nodes[a].end());
    std::sort(blocks.begin(), blocks.end());
    blocks.erase(std::unique(blocks.begin(), blocks.end()), blocks.end());
    for (int a : blocks) {
      const auto& patch = im.patch_nodes[a];
      const Eigen::VectorXd& g = im.nodal_g[a];
      const int nd = static_cast<int>(g.size());
      const double coef = im.nodal_coef[a];
      const double beta = im.nodal_beta[a];
      for (int cc = 0; cc < nd; ++cc) {
        if (!full && !mark[2 * patch[cc / 2] + cc % 2])
          continue;
        for (int r = 0; r < nd; ++r) {
          if (!full && !mark[2 * patch[r / 2] + r % 2])
            continue;
          const int idx = im.nodal_entry[a][static_cast<std::size_t>(cc) * nd + r];
          const double kv = coef * g(r) * g(cc);
          k[idx] += kv;
          c[idx] += beta * kv;
        }
      }
    }
  }
  // Lumped mass: rho A t / 3 to each node of each triangle (row sums of the consistent mass).
  for (int a : nodes) {
    double mass = 0.0;
    for (int t : node_triangles_[a])
      mass += materials_[t].density_kg_m3 * mesh_.triangleArea(t) * options_.thickness_m / 3.0;
    m_lumped_(2 * a) = mass;
    m_lumped_(2 * a + 1) = mass;
  }
  for (int d : dofs)
    mark[d] = 0;
}

bool FemModel::canMoveNode(int node, const Point2& p_new, double min_area_m2) const {
  if (node < 0 || node >= nodeCount() || !p_new.allFinite())
    return false;
  for (int t : node_triangles_[node]) {
    std::array<Point2, 3> p;
    for (int k = 0; k < 3; ++k) {
      const int n = mesh_.triangles[t][k];
      p[k] = n == node ? p_new : mesh_.nodes[n];
    }
    if (!(signedArea(p[0], p[1], p[2]) > min_area_m2))
      return false;
  }
  return true;
}

std::vector<int> FemModel::moveNode(int node, const Point2& p_new) {
  if (node < 0 || node >= nodeCount()) {
    throw std::invalid_argument("FemModel::moveNode: node " + std::to_string(node) +
                                " out of range");
  }
  if (!p_new.allFinite()) {
    throw std::invalid_argument("FemModel::moveNode: node " + std::to_string(node) +
                                ": non-finite position");
  }
  for (int t : node_triangles_[node]) {
    std::array<Point2, 3> p;
    for (int k = 0; k < 3; ++k) {
      const int n = mesh_.triangles[t][k];
      p[k] = n == node ? p_new : mesh_.nodes[n];
    }
    const double area = signedArea(p[0], p[1], p[2]);
    if (!(area > 0.0)) {
      throw std::invalid_argument("FemModel::moveNode: moving node " + std::to_string(node) +
                                  " to (" + fmt(p_new.x()) + ", " + fmt(p_new.y()) +
                                  ") would give element " + std::to_string(t) + " signed area " +
                                  fmt(area) + " m^2 <= 0");
    }
  }
  mesh_.nodes[node] = p_new;
  const std::vector<int>& tris = node_triangles_[node];
  std::vector<int> nodes;  // nodes of the changed triangles = the node's patch
  for (int t : tris)
    nodes.insert(nodes.end(), mesh_.triangles[t].begin(), mesh_.triangles[t].end());
  std::sort(nodes.begin(), nodes.end());
  nodes.erase(std::unique(nodes.begin(), nodes.end()), nodes.end());
  Impl::recomputeBlocks(*this, tris, nodes);
  // Affected DOFs: those of the changed blocks (patch for CST; patches of the patch otherwise).
  std::vector<int> affected_nodes = nodes;
  if (options_.formulation == ElementFormulation::kAveragedVolumetric) {
    for (int a : nodes)
      affected_nodes.insert(affected_nodes.end(), impl_->patch_nodes[a].begin(),
                            impl_->patch_nodes[a].end());
    std::sort(affected_nodes.begin(), affected_nodes.end());
    affected_nodes.erase(std::unique(affected_nodes.begin(), affected_nodes.end()),
                         affected_nodes.end());
  }
  std::vector<int> dofs;
  dofs.reserve(2 * affected_nodes.size());
  for (int a : affected_nodes) {
    dofs.push_back(dofX(a));
    dofs.push_back(dofY(a));
  }
  Impl::resumEntries(*this, dofs);
  return dofs;
}

Eigen::VectorXd FemModel::elementStrainEnergy(const Eigen::VectorXd& u) const {
  if (u.size() != dofCount()) {
    throw std::invalid_argument("FemModel::elementStrainEnergy: u has size " +
                                std::to_string(u.size()) + ", expected " +
                                std::to_string(dofCount()));
  }
  const Impl& im = *impl_;
  const std::size_t n_tri = mesh_.triangles.size();
  Eigen::VectorXd energy(n_tri);
  const double inv_t = 1.0 / options_.thickness_m;
  for (std::size_t t = 0; t < n_tri; ++t) {
    const auto& tri = mesh_.triangles[t];
    Vector6 ue;
    for (int k = 0; k < 3; ++k) {
      ue(2 * k) = u(2 * tri[k]);
      ue(2 * k + 1) = u(2 * tri[k] + 1);
    }
    energy(t) = 0.5 * ue.dot(im.element_k[t] * ue) * inv_t;
  }
  if (options_.formulation == ElementFormulation::kAveragedVolumetric) {
    // Nodal volumetric energy V_a kappa_a theta_a^2 / 2 shared by the patch triangles in
    // proportion to their A_e / 3, so that the element energies sum to the total.
    for (int a = 0; a < nodeCount(); ++a) {
      const auto& patch = im.patch_nodes[a];
      double theta = 0.0;
      for (std::size_t p = 0; p < patch.size(); ++p) {
        theta +=
            im.nodal_g[a](2 * p) * u(2 * patch[p]) + im.nodal_g[a](2 * p + 1) * u(2 * patch[p] + 1);
      }
      for (int t : node_triangles_[a])
        energy(t) += mesh_.triangleArea(t) / 3.0 * 0.5 * im.nodal_kappa[a] * theta * theta;
    }
  }
  return energy;
}

Eigen::VectorXd FemModel::elementVonMises(const Eigen::VectorXd& u) const {
  if (u.size() != dofCount()) {
    throw std::invalid_argument("FemModel::elementVonMises: u has size " +
                                std::to_string(u.size()) + ", expected " +
                                std::to_string(dofCount()));
  }
  const std::size_t n_tri = mesh_.triangles.size();
  Eigen::VectorXd vm(n_tri);
  for (std::size_t t = 0; t < n_tri; ++t) {
    const auto& tri = mesh_.triangles[t];
    const CstGeometry g =
        cstGeometry(mesh_.nodes[tri[0]], mesh_.nodes[tri[1]], mesh_.nodes[tri[2]]);
    Vector6 ue;
    for (int k = 0; k < 3; ++k) {
      ue(2 * k) = u(2 * tri[k]);
      ue(2 * k + 1) = u(2 * tri[k] + 1);
    }
    const Eigen::Vector3d e = g.B * ue;
    // Von Mises depends only on the deviatoric stress 2 mu dev(e) (e_zz = 0, plane strain), the
    // same for both formulations (they differ only in the pressure).
    const double mu = shearModulus(materials_[t]);
    const double theta = e(0) + e(1);
    const double sxx = 2.0 * mu * (e(0) - theta / 3.0);
    const double syy = 2.0 * mu * (e(1) - theta / 3.0);
    const double szz = 2.0 * mu * (-theta / 3.0);
    const double sxy = mu * e(2);
    vm(t) = std::sqrt(1.5 * (sxx * sxx + syy * syy + szz * szz + 2.0 * sxy * sxy));
  }
  return vm;
}

}  // namespace needle_guidance::tissue

namespace needle_guidance::tissue {
namespace {

/// Rotation of the polar decomposition F = R U of a 2x2 deformation gradient (closed form in
/// 2-D: the angle of the skew part of F). Also defined (as the nearest rotation) for det F <= 0.
Eigen::Matrix2d polarRotation(const Eigen::Matrix2d& f) {
  const double angle = std::atan2(f(1, 0) - f(0, 1), f(0, 0) + f(1, 1));
  Eigen::Matrix2d r;
  r << std::cos(angle), -std::sin(angle), std::sin(angle), std::cos(angle);
  return r;
}

/// Displacement gradient of a triangle: grad u = sum_k u_k [dN_k/dx, dN_k/dy].
Eigen::Matrix2d displacementGradient(const CstGeometry& g, const std::array<int, 3>& tri,
                                     const Eigen::VectorXd& u) {
  Eigen::Matrix2d grad = Eigen::Matrix2d::Zero();
  for (int k = 0; k < 3; ++k) {
    const Eigen::Vector2d uk(u(2 * tri[k]), u(2 * tri[k] + 1));
    const Eigen::Vector2d dn(g.B(0, 2 * k), g.B(1, 2 * k + 1));
    grad += uk * dn.transpose();
  }
  return grad;
}

}  // namespace

template <typename Visit>
void FemModel::Impl::visitCorotational(const FemModel& model, const Eigen::VectorXd& u,
                                       Visit&& visit) {
  if (u.size() != model.dofCount()) {
    throw std::invalid_argument("FemModel: corotational displacement has size " +
                                std::to_string(u.size()) + ", expected " +
                                std::to_string(model.dofCount()));
  }
  const Impl& im = *model.impl_;
  const auto& mesh = model.mesh_;
  const std::size_t n_tri = mesh.triangles.size();
  std::vector<Eigen::Matrix2d> element_f(n_tri);
  std::vector<int> dofs(6);
  for (std::size_t t = 0; t < n_tri; ++t) {
    const auto& tri = mesh.triangles[t];
    const CstGeometry g = cstGeometry(mesh.nodes[tri[0]], mesh.nodes[tri[1]], mesh.nodes[tri[2]]);
    element_f[t] = Eigen::Matrix2d::Identity() + displacementGradient(g, tri, u);
    const Eigen::Matrix2d r = polarRotation(element_f[t]);
    // d = R^T x - X relative to the centroid (a uniform shift is in K_e's null space).
    const Point2 centroid = (mesh.nodes[tri[0]] + mesh.nodes[tri[1]] + mesh.nodes[tri[2]]) / 3.0;
    Matrix6 rb = Matrix6::Zero();
    Vector6 d;
    for (int k = 0; k < 3; ++k) {
      rb.block<2, 2>(2 * k, 2 * k) = r;
      const Point2 x_rel = mesh.nodes[tri[k]] - centroid;
      const Eigen::Vector2d xk = x_rel + Eigen::Vector2d(u(2 * tri[k]), u(2 * tri[k] + 1));
      d.segment<2>(2 * k) = r.transpose() * xk - x_rel;
      dofs[2 * k] = 2 * tri[k];
      dofs[2 * k + 1] = 2 * tri[k] + 1;
    }
    const Matrix6& ke = im.element_k[t];
    const Matrix6 k_rot = rb * ke * rb.transpose();
    const Vector6 f_int = rb * (ke * d);
    const ElementMaterial& mat = model.materials_[t];
    visit(dofs, im.element_entry[t].data(), Eigen::MatrixXd(k_rot), &im.element_m[t],
          mat.rayleigh_alpha_per_s, mat.rayleigh_beta_s, Eigen::VectorXd(f_int),
          0.5 * d.dot(ke * d));
  }
  if (model.options_.formulation != ElementFormulation::kAveragedVolumetric)
    return;
  for (int a = 0; a < model.nodeCount(); ++a) {
    // Patch rotation: polar rotation of the area-weighted mean deformation gradient.
    Eigen::Matrix2d f_mean = Eigen::Matrix2d::Zero();
    for (int t : model.node_triangles_[a])
      f_mean += mesh.triangleArea(t) * element_f[t];
    const Eigen::Matrix2d r = polarRotation(f_mean);
    const auto& patch = im.patch_nodes[a];
    const int nd = 2 * static_cast<int>(patch.size());
    dofs.resize(nd);
    Eigen::VectorXd rg(nd), d(nd);
    const Point2& center = mesh.nodes[a];
    for (int p = 0; p < nd / 2; ++p) {
      rg.segment<2>(2 * p) = r * im.nodal_g[a].segment<2>(2 * p);
      const Point2 x_rel = mesh.nodes[patch[p]] - center;
      const Eigen::Vector2d xk = x_rel + Eigen::Vector2d(u(2 * patch[p]), u(2 * patch[p] + 1));
      d.segment<2>(2 * p) = r.transpose() * xk - x_rel;
      dofs[2 * p] = 2 * patch[p];
      dofs[2 * p + 1] = 2 * patch[p] + 1;
    }
    const double coef = im.nodal_coef[a];
    const double theta = im.nodal_g[a].dot(d);
    visit(dofs, im.nodal_entry[a].data(), Eigen::MatrixXd(coef * rg * rg.transpose()), nullptr, 0.0,
          im.nodal_beta[a], Eigen::VectorXd(coef * theta * rg), 0.5 * coef * theta * theta);
  }
}

void FemModel::assembleCorotational(const Eigen::VectorXd& u, SparseMatrix& K_R, SparseMatrix& C_R,
                                    Eigen::VectorXd& f0) const {
  K_R = K_;
  C_R = C_;
  std::fill(K_R.valuePtr(), K_R.valuePtr() + K_R.nonZeros(), 0.0);
  std::fill(C_R.valuePtr(), C_R.valuePtr() + C_R.nonZeros(), 0.0);
  Eigen::VectorXd f_int = Eigen::VectorXd::Zero(dofCount());
  double* k = K_R.valuePtr();
  double* c = C_R.valuePtr();
  Impl::visitCorotational(*this, u,
                          [&](const std::vector<int>& dofs, const int* entries,
                              const Eigen::MatrixXd& k_rot, const Matrix6* me, double alpha,
                              double beta, const Eigen::VectorXd& f_block, double /*energy*/) {
                            const int nd = static_cast<int>(dofs.size());
                            for (int cc = 0; cc < nd; ++cc) {
                              f_int(dofs[cc]) += f_block(cc);
                              for (int r = 0; r < nd; ++r) {
                                const int idx = entries[static_cast<std::size_t>(cc) * nd + r];
                                k[idx] += k_rot(r, cc);
                                c[idx] += beta * k_rot(r, cc) + (me ? alpha * (*me)(r, cc) : 0.0);
                              }
                            }
                          });
  // f_int = K_R u - f0.
  f0 = K_R * u - f_int;
}

Eigen::VectorXd FemModel::corotationalForce(const Eigen::VectorXd& u) const {
  Eigen::VectorXd f_int = Eigen::VectorXd::Zero(dofCount());
  Impl::visitCorotational(
      *this, u,
      [&](const std::vector<int>& dofs, const int*, const Eigen::MatrixXd&, const Matrix6*, double,
          double, const Eigen::VectorXd& f_block, double) {
        for (std::size_t i = 0; i < dofs.size(); ++i)
          f_int(dofs[i]) += f_block(static_cast<Eigen::Index>(i));
      });
  return f_int;
}

double FemModel::corotationalStrainEnergy(const Eigen::VectorXd& u) const {
  double energy = 0.0;
  Impl::visitCorotational(
      *this, u,
      [&](const std::vector<int>&, const int*, const Eigen::MatrixXd&, const Matrix6*, double,
          double, const Eigen::VectorXd&, double e) { energy += e; });
  return energy;
}

}  // namespace needle_guidance::tissue
