// The probe-out slice's biomechanical model (dissertation 3.2.2, 3.3.2); see slice_model.h.
#include "slice_model.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <set>
#include <stdexcept>
#include <unordered_map>
#include <utility>

#include "needle_guidance/tissue/fem_model.h"

namespace needle_guidance::registration::detail {
namespace {

using geometry::MeshingOptions;
using geometry::MeshRegion;
using geometry::Segment;
using geometry::TriangleMesh;

void addEdges(const Polygon& polygon, std::vector<Segment>& lines) {
  for (std::size_t i = 0; i < polygon.size(); ++i)
    lines.push_back(polygon.edge(i));
}

/// Region list for meshDomain and the role of each region index (index i + 1 = regions[i]).
enum class Role { kSurrounding, kCg, kPz, kRectum, kBone, kBladder };

struct RegionSetup {
  std::vector<MeshRegion> regions;
  std::vector<Role> roles;  // per mesh region index (0 = background)
};

RegionSetup regionSetup(const SliceSegmentation& seg) {
  RegionSetup setup;
  setup.roles.push_back(Role::kSurrounding);
  const auto add = [&](const std::string& name, const Polygon& polygon, Role role) {
    setup.regions.push_back(MeshRegion{name, polygon});
    setup.roles.push_back(role);
  };
  add("cg", seg.cg.outer, Role::kCg);
  add("pz", seg.pz.outer, Role::kPz);
  add("rectum", seg.rectum.outer, Role::kRectum);
  for (std::size_t b = 0; b < seg.bones.size(); ++b)
    add("bone" + std::to_string(b), seg.bones[b].outer, Role::kBone);
  if (seg.bladder)
    add("bladder", seg.bladder->outer, Role::kBladder);
  return setup;
}

/// Meshes with graded sizes: min_edge h at the prostate and rectum, growing to 3 h.
TriangleMesh meshWithSize(const SliceSegmentation& seg, const RegionSetup& setup, double h_m) {
  MeshingOptions options;
  options.min_edge_m = h_m;
  options.max_edge_m = 3.0 * h_m;
  options.grading_length_m = 0.015;
  options.min_angle_deg = 25.0;
  addEdges(seg.cg.outer, options.refine_lines);
  addEdges(seg.pz.outer, options.refine_lines);
  addEdges(seg.rectum.outer, options.refine_lines);
  return geometry::meshDomain(seg.domain, "surrounding", setup.regions, options);
}

int countTissueNodes(const TriangleMesh& mesh, const std::vector<Role>& roles) {
  std::vector<char> used(mesh.nodes.size(), 0);
  for (std::size_t t = 0; t < mesh.triangles.size(); ++t) {
    const Role role = roles[static_cast<std::size_t>(mesh.triangle_region[t])];
    if (role == Role::kRectum || role == Role::kBladder)
      continue;
    for (int k : mesh.triangles[t])
      used[static_cast<std::size_t>(k)] = 1;
  }
  return static_cast<int>(std::count(used.begin(), used.end(), 1));
}

}  // namespace

namespace {

/// The prostate's boundary loops: directed edges of CG u PZ triangles whose reverse is not in
/// the set, chained into closed loops of node indices.
std::vector<std::vector<int>> prostateBoundaryLoops(const geometry::TriangleMesh& mesh,
                                                    const std::vector<int>& triangle_class) {
  std::vector<std::vector<int>> loops;
  std::map<std::pair<int, int>, int> directed;
  for (std::size_t t = 0; t < mesh.triangles.size(); ++t) {
    const int cls = triangle_class[t];
    if (cls != kCentralGland && cls != kPeripheralZone)
      continue;
    for (int k = 0; k < 3; ++k) {
      const int a = mesh.triangles[t][static_cast<std::size_t>(k)];
      const int b = mesh.triangles[t][static_cast<std::size_t>((k + 1) % 3)];
      directed[{a, b}] = 1;
    }
  }
  std::unordered_map<int, int> next;
  for (const auto& entry : directed) {
    if (!directed.count({entry.first.second, entry.first.first}))
      next[entry.first.first] = entry.first.second;
  }
  std::set<int> visited;
  for (const auto& entry : next) {
    if (visited.count(entry.first))
      continue;
    std::vector<int> loop;
    int node = entry.first;
    while (!visited.count(node) && next.count(node)) {
      visited.insert(node);
      loop.push_back(node);
      node = next[node];
    }
    if (loop.size() >= 3)
      loops.push_back(std::move(loop));
  }
  return loops;
}

}  // namespace

SliceModel buildSliceModel(const SliceSegmentation& seg, int target_nodes, double poisson) {
  const RegionSetup setup = regionSetup(seg);
  // Node count ~ h^-k: secant iteration on log n vs log h from a uniform-mesh guess.
  const double area_m2 = seg.domain.area();
  double h = 1.6 * std::sqrt(1.155 * area_m2 / std::max(target_nodes, 1));
  TriangleMesh best;
  int best_n = -1;
  double prev_h = 0.0, prev_n = 0.0, slope = -1.6;
  for (int iteration = 0; iteration < 6; ++iteration) {
    TriangleMesh mesh = meshWithSize(seg, setup, h);
    const int n = countTissueNodes(mesh, setup.roles);
    if (best_n < 0 || std::abs(n - target_nodes) < std::abs(best_n - target_nodes)) {
      best = std::move(mesh);
      best_n = n;
    }
    if (std::abs(n - target_nodes) <= 0.08 * target_nodes)
      break;
    if (iteration > 0 && std::abs(std::log(h / prev_h)) > 1e-6 && n != prev_n) {
      slope = std::clamp(std::log(n / prev_n) / std::log(h / prev_h), -3.0, -0.5);
    }
    prev_h = h;
    prev_n = n;
    h *= std::exp(std::log(static_cast<double>(target_nodes) / n) / slope);
  }

  // Drop the rectum lumen and the bladder cavity (its volume may change: 3.2.1) and compact
  // the nodes.
  SliceModel model;
  const auto is_cavity = [&](std::size_t t) {
    const Role role = setup.roles[static_cast<std::size_t>(best.triangle_region[t])];
    return role == Role::kRectum || role == Role::kBladder;
  };
  std::vector<char> rectum_node(best.nodes.size(), 0), other_node(best.nodes.size(), 0),
      bladder_node(best.nodes.size(), 0);
  std::map<std::pair<int, int>, bool> bladder_edges;
  for (std::size_t t = 0; t < best.triangles.size(); ++t) {
    const Role role = setup.roles[static_cast<std::size_t>(best.triangle_region[t])];
    for (int k = 0; k < 3; ++k) {
      const auto node = static_cast<std::size_t>(best.triangles[t][static_cast<std::size_t>(k)]);
      if (role == Role::kRectum)
        rectum_node[node] = 1;
      if (role == Role::kBladder)
        bladder_node[node] = 1;
      if (!is_cavity(t))
        other_node[node] = 1;
      if (role == Role::kBladder)
        bladder_edges[{best.triangles[t][static_cast<std::size_t>(k)],
                       best.triangles[t][static_cast<std::size_t>((k + 1) % 3)]}] = true;
    }
  }
  std::vector<int> new_index(best.nodes.size(), -1);
  TriangleMesh& mesh = model.mesh;
  mesh.region_names = best.region_names;
  for (std::size_t i = 0; i < best.nodes.size(); ++i) {
    if (other_node[i]) {
      new_index[i] = static_cast<int>(mesh.nodes.size());
      mesh.nodes.push_back(best.nodes[i]);
    }
  }
  for (const auto& entry : bladder_edges) {
    const auto [a, b] = entry.first;
    if (bladder_edges.count({b, a}))
      continue;  // interior edge of the cavity
    if (new_index[static_cast<std::size_t>(a)] < 0 || new_index[static_cast<std::size_t>(b)] < 0)
      continue;
    model.bladder_wall_edges.push_back(
        {new_index[static_cast<std::size_t>(a)], new_index[static_cast<std::size_t>(b)]});
  }
  std::set<int> fixed;
  for (std::size_t t = 0; t < best.triangles.size(); ++t) {
    const int region = best.triangle_region[t];
    const Role role = setup.roles[static_cast<std::size_t>(region)];
    if (is_cavity(t))
      continue;
    std::array<int, 3> tri{};
    for (int k = 0; k < 3; ++k)
      tri[static_cast<std::size_t>(k)] =
          new_index[static_cast<std::size_t>(best.triangles[t][static_cast<std::size_t>(k)])];
    mesh.triangles.push_back(tri);
    mesh.triangle_region.push_back(region);
    int cls = kSurrounding;
    if (role == Role::kCg)
      cls = kCentralGland;
    if (role == Role::kPz)
      cls = kPeripheralZone;
    if (role == Role::kBone) {
      cls = -1;
      fixed.insert(tri.begin(), tri.end());
    }
    model.triangle_class.push_back(cls);
  }
  model.fixed_nodes.assign(fixed.begin(), fixed.end());

  const Polygon& rectum = seg.rectum.outer;
  double a2 = 0.0;
  Point2 c = Point2::Zero();
  for (std::size_t i = 0; i < rectum.size(); ++i) {
    const Point2& p = rectum.vertices()[i];
    const Point2& q = rectum.vertices()[(i + 1) % rectum.size()];
    const double cross = p.x() * q.y() - q.x() * p.y();
    a2 += cross;
    c += (p + q) * cross;
  }
  model.rectum_centre = c / (3.0 * a2);
  for (std::size_t i = 0; i < best.nodes.size(); ++i) {
    if (rectum_node[i] && other_node[i] && !fixed.count(new_index[i]))
      model.rectum_nodes.push_back(new_index[i]);
    if (bladder_node[i] && other_node[i] && !fixed.count(new_index[i]))
      model.bladder_nodes.push_back(new_index[i]);
  }
  const Point2 centre = model.rectum_centre;
  std::sort(model.rectum_nodes.begin(), model.rectum_nodes.end(), [&](int a, int b) {
    const Point2 da = mesh.nodes[static_cast<std::size_t>(a)] - centre;
    const Point2 db = mesh.nodes[static_cast<std::size_t>(b)] - centre;
    return std::atan2(da.y(), da.x()) < std::atan2(db.y(), db.x());
  });
  std::sort(model.bladder_nodes.begin(), model.bladder_nodes.end());

  model.prostate_loops = prostateBoundaryLoops(mesh, model.triangle_class);

  // Unit stiffness per class: K is linear in the per-element moduli (fixed nu), so
  // K_c = K(1 + [class == c]) - K(1) exactly; all share the FemModel's sparsity pattern.
  tissue::FemOptions fem_options;
  fem_options.formulation = tissue::ElementFormulation::kAveragedVolumetric;
  const auto materials = [&](int boosted) {
    std::vector<tissue::ElementMaterial> m(mesh.triangles.size());
    for (std::size_t t = 0; t < m.size(); ++t) {
      const int cls = model.triangle_class[t] < 0 ? kSurrounding : model.triangle_class[t];
      m[t].young_modulus_Pa = cls == boosted ? 2.0 : 1.0;
      m[t].poisson_ratio = poisson;
    }
    return m;
  };
  const tissue::FemModel base(mesh, materials(-1), fem_options);
  for (int c = 0; c < kSoftClassCount; ++c) {
    const tissue::FemModel boosted(mesh, materials(c), fem_options);
    SparseMatrix k = boosted.stiffness();
    const SparseMatrix& k1 = base.stiffness();
    if (k.nonZeros() != k1.nonZeros())
      throw std::logic_error("buildSliceModel: stiffness patterns differ");
    for (Eigen::Index i = 0; i < k.nonZeros(); ++i)
      k.valuePtr()[i] -= k1.valuePtr()[i];
    model.unit_stiffness[static_cast<std::size_t>(c)] = std::move(k);
  }
  return model;
}

Loops deformedLoops(const SliceModel& model, const Eigen::VectorXd& u) {
  Loops loops;
  for (const auto& loop : model.prostate_loops) {
    std::vector<Point2> points;
    points.reserve(loop.size());
    for (int node : loop) {
      points.push_back(model.mesh.nodes[static_cast<std::size_t>(node)] +
                       Point2(u(2 * node), u(2 * node + 1)));
    }
    loops.push_back(std::move(points));
  }
  return loops;
}

SliceSolver::SliceSolver(const SliceModel& model, const std::vector<Point2>& rectum_displacement,
                         std::vector<int> force_nodes)
    : model_(model), force_nodes_(std::move(force_nodes)) {
  n_dof_ = 2 * static_cast<int>(model.mesh.nodes.size());
  std::vector<char> prescribed(static_cast<std::size_t>(n_dof_), 0);
  u_prescribed_ = Eigen::VectorXd::Zero(n_dof_);
  for (int node : model.fixed_nodes)
    prescribed[2 * node] = prescribed[2 * node + 1] = 1;
  for (std::size_t i = 0; i < model.rectum_nodes.size(); ++i) {
    const int node = model.rectum_nodes[i];
    prescribed[2 * node] = prescribed[2 * node + 1] = 1;
    u_prescribed_(2 * node) = rectum_displacement[i].x();
    u_prescribed_(2 * node + 1) = rectum_displacement[i].y();
  }
  free_index_.assign(static_cast<std::size_t>(n_dof_), -1);
  for (int d = 0; d < n_dof_; ++d) {
    if (!prescribed[static_cast<std::size_t>(d)]) {
      free_index_[static_cast<std::size_t>(d)] = static_cast<int>(free_dofs_.size());
      free_dofs_.push_back(d);
    }
  }
  for (int node : force_nodes_) {
    for (int d : {2 * node, 2 * node + 1}) {
      if (free_index_[static_cast<std::size_t>(d)] >= 0)
        force_dofs_.push_back(d);
    }
  }
  // K_ff pattern and the position of every full-pattern entry in it.
  const SparseMatrix& k = model.unit_stiffness[0];
  std::vector<Eigen::Triplet<double>> triplets;
  for (int col = 0; col < k.outerSize(); ++col) {
    for (SparseMatrix::InnerIterator it(k, col); it; ++it) {
      const int fr = free_index_[static_cast<std::size_t>(it.row())];
      const int fc = free_index_[static_cast<std::size_t>(it.col())];
      if (fr >= 0 && fc >= 0)
        triplets.emplace_back(fr, fc, 1.0);
    }
  }
  const int n_free = static_cast<int>(free_dofs_.size());
  k_ff_.resize(n_free, n_free);
  k_ff_.setFromTriplets(triplets.begin(), triplets.end());
  k_ff_.makeCompressed();
  ff_position_.assign(static_cast<std::size_t>(k.nonZeros()), -1);
  Eigen::Index nz = 0;
  for (int col = 0; col < k.outerSize(); ++col) {
    for (SparseMatrix::InnerIterator it(k, col); it; ++it, ++nz) {
      const int fr = free_index_[static_cast<std::size_t>(it.row())];
      const int fc = free_index_[static_cast<std::size_t>(it.col())];
      if (fr < 0 || fc < 0)
        continue;
      const int* begin = k_ff_.innerIndexPtr() + k_ff_.outerIndexPtr()[fc];
      const int* end = k_ff_.innerIndexPtr() + k_ff_.outerIndexPtr()[fc + 1];
      ff_position_[static_cast<std::size_t>(nz)] =
          static_cast<int>(std::lower_bound(begin, end, fr) - k_ff_.innerIndexPtr());
    }
  }
  ldlt_.analyzePattern(k_ff_);
}

bool SliceSolver::setModuli(const Moduli& modulus_Pa) {
  if (factorized_ && modulus_Pa == moduli_)
    return true;
  std::fill(k_ff_.valuePtr(), k_ff_.valuePtr() + k_ff_.nonZeros(), 0.0);
  for (int c = 0; c < kSoftClassCount; ++c) {
    const SparseMatrix& kc = model_.unit_stiffness[static_cast<std::size_t>(c)];
    const double e = modulus_Pa[static_cast<std::size_t>(c)];
    for (Eigen::Index i = 0; i < kc.nonZeros(); ++i) {
      const int pos = ff_position_[static_cast<std::size_t>(i)];
      if (pos >= 0)
        k_ff_.valuePtr()[pos] += e * kc.valuePtr()[i];
    }
  }
  moduli_ = modulus_Pa;
  ldlt_.factorize(k_ff_);
  ++factorizations_;
  factorized_ = ldlt_.info() == Eigen::Success;
  if (!factorized_)
    return false;
  // u0: K_ff u_f = -K_fp u_p.
  const Eigen::VectorXd rhs = -multiplyK(u_prescribed_);
  u0_ = u_prescribed_ + solveFree(rhs);
  factorized_ = u0_.allFinite();
  return factorized_;
}

Eigen::VectorXd SliceSolver::solveFree(const Eigen::VectorXd& b_full) const {
  Eigen::VectorXd b(static_cast<Eigen::Index>(free_dofs_.size()));
  for (std::size_t i = 0; i < free_dofs_.size(); ++i)
    b(static_cast<Eigen::Index>(i)) = b_full(free_dofs_[i]);
  const Eigen::VectorXd x = ldlt_.solve(b);
  Eigen::VectorXd out = Eigen::VectorXd::Zero(n_dof_);
  for (std::size_t i = 0; i < free_dofs_.size(); ++i)
    out(free_dofs_[i]) = x(static_cast<Eigen::Index>(i));
  return out;
}

Eigen::VectorXd SliceSolver::forceResponse(const Eigen::VectorXd& force_N) const {
  Eigen::VectorXd b = Eigen::VectorXd::Zero(n_dof_);
  for (std::size_t k = 0; k < force_dofs_.size(); ++k)
    b(force_dofs_[k]) = force_N(static_cast<Eigen::Index>(k));
  return solveFree(b);
}

Eigen::MatrixXd SliceSolver::greensFunctions() const {
  const auto n_free = static_cast<Eigen::Index>(free_dofs_.size());
  const auto n_force = static_cast<Eigen::Index>(force_dofs_.size());
  Eigen::MatrixXd b = Eigen::MatrixXd::Zero(n_free, n_force);
  for (Eigen::Index k = 0; k < n_force; ++k)
    b(free_index_[static_cast<std::size_t>(force_dofs_[static_cast<std::size_t>(k)])], k) = 1.0;
  const Eigen::MatrixXd x = ldlt_.solve(b);
  Eigen::MatrixXd out = Eigen::MatrixXd::Zero(n_dof_, n_force);
  for (std::size_t i = 0; i < free_dofs_.size(); ++i)
    out.row(free_dofs_[i]) = x.row(static_cast<Eigen::Index>(i));
  return out;
}

Eigen::VectorXd SliceSolver::multiplyK(const Eigen::VectorXd& u) const {
  Eigen::VectorXd out = Eigen::VectorXd::Zero(n_dof_);
  for (int c = 0; c < kSoftClassCount; ++c) {
    out += moduli_[static_cast<std::size_t>(c)] *
           (model_.unit_stiffness[static_cast<std::size_t>(c)] * u);
  }
  return out;
}

}  // namespace needle_guidance::registration::detail
