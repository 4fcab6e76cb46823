// CGAL Mesh_3 meshing of tissue_3d scenes and the element quality rule (tet_mesh_3d.h).
#include "needle_guidance/tissue_3d/tet_mesh_3d.h"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Labeled_mesh_domain_3.h>
#include <CGAL/Mesh_complex_3_in_triangulation_3.h>
#include <CGAL/Mesh_criteria_3.h>
#include <CGAL/Mesh_triangulation_3.h>
#include <CGAL/make_mesh_3.h>

#include <cmath>
#include <map>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/cpu_time.h"

namespace needle_guidance::tissue_3d {
namespace {

using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Domain = CGAL::Labeled_mesh_domain_3<Kernel>;
using Tr = CGAL::Mesh_triangulation_3<Domain, CGAL::Default, CGAL::Sequential_tag>::type;
using C3t3 = CGAL::Mesh_complex_3_in_triangulation_3<Tr>;
using Criteria = CGAL::Mesh_criteria_3<Tr>;
using CgalPoint = Kernel::Point_3;

/// Element size: fine within fine_radius of a needle line (x from the block's entry face) or
/// of a target, growing linearly to the coarse size over one more fine_radius.
struct SizingField {
  using FT = Kernel::FT;
  using Index = Domain::Index;
  double coarse_m, fine_m, radius_m;
  std::vector<Eigen::Vector2d> lines;
  std::vector<Vector3> points;
  FT operator()(const CgalPoint& p, const int, const Index&) const {
    double d = 1e9;
    for (const Eigen::Vector2d& l : lines) {
      d = std::min(d, std::hypot(p.y() - l.x(), p.z() - l.y()));
    }
    for (const Vector3& q : points) {
      d = std::min(d, (Vector3(p.x(), p.y(), p.z()) - q).norm());
    }
    const double t = std::clamp((d - radius_m) / radius_m, 0.0, 1.0);
    return fine_m + t * (coarse_m - fine_m);
  }
};

std::string fmt(double v) {
  std::ostringstream out;
  out << v;
  return out.str();
}

}  // namespace

int TetMesh3::fixedCount() const {
  int n = 0;
  for (char f : node_fixed) {
    n += f != 0;
  }
  return n;
}

double tetQuality(const fem::Corners<3>& c) {
  double l2 = 0.0;
  for (int i = 0; i < 4; ++i) {
    for (int j = i + 1; j < 4; ++j) {
      l2 += (c[static_cast<std::size_t>(i)] - c[static_cast<std::size_t>(j)]).squaredNorm();
    }
  }
  const double l_rms = std::sqrt(l2 / 6.0);
  return l_rms > 0.0 ? 6.0 * std::sqrt(2.0) * fem::signedMeasure<3>(c) / (l_rms * l_rms * l_rms)
                     : 0.0;
}

void repairTetMesh(TetMesh3& mesh, double min_quality, TetMeshReport& report) {
  TetMesh3 kept;
  std::vector<int> new_index(mesh.nodes.size(), -1);
  report.min_quality = 1.0;
  for (int e = 0; e < mesh.elementCount(); ++e) {
    const fem::Corners<3> c = fem::corners<3>(mesh, e);
    const double q = tetQuality(c);
    const double volume = fem::signedMeasure<3>(c);
    if (volume < 0.0 && q < -min_quality) {
      throw std::invalid_argument("tetrahedral mesh: element " + std::to_string(e) +
                                  " is inverted (volume " + fmt(volume * 1e9) + " mm^3)");
    }
    if (q < min_quality) {
      ++report.dropped_elements;
      report.dropped_volume_m3 += std::abs(volume);
      continue;
    }
    report.min_quality = std::min(report.min_quality, q);
    std::array<int, 4> tet = mesh.elements[static_cast<std::size_t>(e)];
    for (int& n : tet) {
      int& ni = new_index[static_cast<std::size_t>(n)];
      if (ni < 0) {
        ni = kept.nodeCount();
        kept.nodes.push_back(mesh.nodes[static_cast<std::size_t>(n)]);
        kept.node_fixed.push_back(
            mesh.node_fixed.empty() ? 0 : mesh.node_fixed[static_cast<std::size_t>(n)]);
      }
      n = ni;
    }
    kept.elements.push_back(tet);
    kept.element_material.push_back(mesh.element_material[static_cast<std::size_t>(e)]);
  }
  if (report.dropped_elements > 0) {
    std::ostringstream note;
    note << "dropped " << report.dropped_elements << " element(s) of near-zero volume (quality < "
         << min_quality << ", total " << report.dropped_volume_m3 * 1e9 << " mm^3) and "
         << mesh.nodeCount() - kept.nodeCount() << " node(s) no other element uses";
    report.note = note.str();
  }
  if (kept.elements.empty()) {
    throw std::invalid_argument("tetrahedral mesh: every element has near-zero volume");
  }
  mesh = std::move(kept);
}

TetMesh3 meshTissue3d(const TissueScene3d& scene, const std::vector<Eigen::Vector2d>& lines,
                      double size_scale, TetMeshReport* report) {
  const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
  const RegionLocator3 locator(scene);
  // Labels: 0 outside, 1 block, 2 + r region r.
  std::function<int(const CgalPoint&)> label = [&locator](const CgalPoint& p) {
    const int r = locator.regionAt(Vector3(p.x(), p.y(), p.z()));
    return r == -2 ? 0 : r + 2;
  };
  const Vector3 margin = Vector3::Constant(1e-3);
  const Vector3 lo = scene.block_min_m - margin, hi = scene.block_max_m + margin;
  Domain domain(label, CGAL::Bbox_3(lo.x(), lo.y(), lo.z(), hi.x(), hi.y(), hi.z()), 1e-6);
  SizingField size{scene.sizing.size_m * size_scale,
                   scene.sizing.fine_size_m * size_scale,
                   scene.sizing.fine_radius_m,
                   lines,
                   {}};
  for (const Target3& t : scene.targets) {
    size.lines.emplace_back(t.position_m.y(), t.position_m.z());
    size.points.push_back(t.position_m);
  }
  namespace p = CGAL::parameters;
  const Criteria criteria(p::facet_angle = 25.0, p::facet_size = size,
                          p::facet_distance = scene.sizing.facet_distance_m,
                          p::cell_radius_edge_ratio = 3.0, p::cell_size = size);
  // The same scene gives the same mesh in every process (the planner and tissue_sim simulate
  // the same tissue): CGAL's default generator is seeded, and the sliver exudation runs to its
  // end (by default it stops after as long as the refinement took, a wall-clock limit).
  CGAL::get_default_random() = CGAL::Random(0);
  const C3t3 c3t3 =
      CGAL::make_mesh_3<C3t3>(domain, criteria, p::no_perturb(), p::exude(p::time_limit = 0));

  TetMesh3 mesh;
  std::map<Tr::Vertex_handle, int> index;
  const double face_tol = 2.0 * scene.sizing.facet_distance_m + 1e-9;
  auto nodeOf = [&](Tr::Vertex_handle v) {
    auto [it, inserted] = index.emplace(v, mesh.nodeCount());
    if (inserted) {
      const CgalPoint& q = v->point().point();
      mesh.nodes.emplace_back(q.x(), q.y(), q.z());
      bool fixed = false;
      for (const std::string& f : scene.fixed_faces) {
        const int axis = f[0] - 'x';
        const bool at_min = f.substr(2) == "min";
        const double plane = at_min ? scene.block_min_m(axis) : scene.block_max_m(axis);
        fixed = fixed || std::abs(mesh.nodes.back()(axis) - plane) <= face_tol;
      }
      mesh.node_fixed.push_back(fixed);
    }
    return it->second;
  };
  for (auto c = c3t3.cells_in_complex_begin(); c != c3t3.cells_in_complex_end(); ++c) {
    std::array<int, 4> tet{};
    for (int k = 0; k < 4; ++k) {
      tet[static_cast<std::size_t>(k)] = nodeOf(c->vertex(k));
    }
    const int sub = c3t3.subdomain_index(c);
    if (fem::signedMeasure<3>(fem::Corners<3>{mesh.nodes[tet[0]], mesh.nodes[tet[1]],
                                              mesh.nodes[tet[2]], mesh.nodes[tet[3]]}) < 0.0) {
      std::swap(tet[2], tet[3]);
    }
    mesh.elements.push_back(tet);
    mesh.element_material.push_back(sub - 1);  // 0 block, 1 + r region r
    if (sub >= 2 && scene.regions[static_cast<std::size_t>(sub - 2)].fixed) {
      for (int n : tet) {
        mesh.node_fixed[static_cast<std::size_t>(n)] = 1;
      }
    }
  }
  TetMeshReport local;
  TetMeshReport& r = report ? *report : local;
  repairTetMesh(mesh, kMinTetQuality, r);
  r.cpu_s = clock.seconds();
  if (mesh.fixedCount() < 4) {
    throw std::invalid_argument("meshTissue3d: scene '" + scene.name + "': only " +
                                std::to_string(mesh.fixedCount()) +
                                " fixed nodes: give block.fixed_faces or a fixed region");
  }
  return mesh;
}

double sizeScaleForTets(const TissueScene3d& scene, double n, int tets_at_scale_1) {
  const int at_1 =
      tets_at_scale_1 > 0 ? tets_at_scale_1 : meshTissue3d(scene, {}, 1.0).elementCount();
  const double scale = std::cbrt(at_1 / n);
  return scale * std::cbrt(meshTissue3d(scene, {}, scale).elementCount() / n);
}

int checkTissueScene3d(const std::string& path, bool mesh, std::ostream& out) {
  const TissueScene3d s = loadTissueScene3d(path);
  const Vector3 size = (s.block_max_m - s.block_min_m) * 1e2;
  out << "scene '" << s.name << "' (tissue_3d) from " << s.source << ": OK\n"
      << "  block " << size.x() << " x " << size.y() << " x " << size.z() << " cm, "
      << s.regions.size() << " regions, " << s.targets.size() << " targets, "
      << (s.workspace.use_template ? "template grid" : "lateral stage") << ", "
      << (s.corotational ? "corotational" : "linear") << " elasticity, cut track "
      << (s.needle.follow_tissue ? "follow_tissue" : "rest_line") << "\n";
  if (!s.needle.follow_tissue) {
    out << "  note: on the rest line seeds land on the needle's line; the tissue's sideways drift"
           " it leaves out moved seeds by up to 0.12 mm on the shipped scenes (docs/tissue_3d.md,"
           " cut track): keep it only where the placement tolerance is well above that\n";
  }
  if (mesh) {
    TetMeshReport report;
    const TetMesh3 m = meshTissue3d(s, {}, 1.0, &report);
    out << "  mesh: " << m.nodeCount() << " nodes, " << m.elementCount() << " tetrahedra ("
        << m.fixedCount() << " fixed nodes, min quality " << report.min_quality << ") in "
        << report.cpu_s << " s CPU\n";
    if (!report.note.empty()) {
      out << "  repaired: " << report.note << "\n";
    }
  }
  return 0;
}

}  // namespace needle_guidance::tissue_3d
