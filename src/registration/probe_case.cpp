// Seeded synthetic probe-in / probe-out slice pairs with known truth (stand-ins for 3.3.1).
#include "needle_guidance/registration/probe_case.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <random>
#include <stdexcept>

#include "needle_guidance/registration/deformable_registration.h"
#include "slice_model.h"

namespace needle_guidance::registration {

const char* toString(ProbeType type) {
  return type == ProbeType::kBalloon ? "balloon" : "rigid";
}

namespace {

constexpr double kMm = 1e-3;  // [m per mm]
constexpr double kPoissonRatio = 0.49;
constexpr double kBalloonRadius_m = 0.024;    // 48 mm diameter (3.3.1)
constexpr double kRigidHalfWidth_m = 0.0145;  // 29 mm right-left (3.3.1)
constexpr double kRigidDepth_m = 0.0165;      // 16.5 mm anterior-posterior (3.3.1)
constexpr double kProbeMargin_m = 0.0005;     // rectum must lie this far inside the probe

class Rng {
public:
  explicit Rng(std::uint64_t seed) : engine_(seed) {}
  double uniform(double lo, double hi) { return lo + (hi - lo) * unit(); }
  double normal() {  // Box-Muller, portable across standard libraries
    const double u1 = std::max(unit(), 1e-300), u2 = unit();
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * M_PI * u2);
  }

private:
  double unit() { return static_cast<double>(engine_() >> 11) * 0x1.0p-53; }
  std::mt19937_64 engine_;
};

Polygon ellipse(const Point2& centre, double a, double b, int n, double phase = 0.0) {
  std::vector<Point2> v;
  for (int k = 0; k < n; ++k) {
    const double t = phase + 2.0 * M_PI * k / n;
    v.emplace_back(centre.x() + a * std::cos(t), centre.y() + b * std::sin(t));
  }
  return Polygon(v);
}

/// Smooth segmentation noise: displaces every vertex along its normal by a sum of random
/// low-order Fourier modes of the arc length, scaled to the given RMS [m].
Polygon addContourNoise(const std::vector<Point2>& vertices, double rms_m, Rng& rng) {
  const std::size_t n = vertices.size();
  if (rms_m <= 0.0)
    return Polygon(vertices);
  std::vector<double> s(n, 0.0);
  for (std::size_t i = 1; i < n; ++i)
    s[i] = s[i - 1] + (vertices[i] - vertices[i - 1]).norm();
  const double length = s[n - 1] + (vertices[0] - vertices[n - 1]).norm();
  std::vector<double> delta(n, 0.0);
  for (int k = 2; k <= 8; ++k) {
    const double amp = rng.normal() / k, phase = rng.uniform(0.0, 2.0 * M_PI);
    for (std::size_t i = 0; i < n; ++i)
      delta[i] += amp * std::cos(2.0 * M_PI * k * s[i] / length + phase);
  }
  double ms = 0.0;
  for (double d : delta)
    ms += d * d;
  const double scale = rms_m / std::sqrt(std::max(ms / n, 1e-300));
  const double orientation = Polygon(vertices).isCounterClockwise() ? 1.0 : -1.0;
  std::vector<Point2> out(n);
  for (std::size_t i = 0; i < n; ++i) {
    const Point2 tangent = vertices[(i + 1) % n] - vertices[(i + n - 1) % n];
    const Point2 normal = orientation * Point2(tangent.y(), -tangent.x()).normalized();  // outward
    out[i] = vertices[i] + scale * delta[i] * normal;
  }
  return Polygon(out);
}

/// Resamples a closed polyline to about `spacing_m` between vertices (arc-length uniform).
std::vector<Point2> resample(const std::vector<Point2>& vertices, double spacing_m) {
  const std::size_t n = vertices.size();
  std::vector<double> s(n + 1, 0.0);
  for (std::size_t i = 0; i < n; ++i)
    s[i + 1] = s[i] + (vertices[(i + 1) % n] - vertices[i]).norm();
  const int m = std::max(8, static_cast<int>(std::round(s[n] / spacing_m)));
  std::vector<Point2> out;
  std::size_t seg = 0;
  for (int k = 0; k < m; ++k) {
    const double target = s[n] * k / m;
    while (seg + 1 < n && s[seg + 1] < target)
      ++seg;
    const double len = s[seg + 1] - s[seg];
    const double t = len > 0.0 ? (target - s[seg]) / len : 0.0;
    out.push_back(vertices[seg] + t * (vertices[(seg + 1) % n] - vertices[seg]));
  }
  return out;
}

}  // namespace

namespace {

/// The rigid probe (a 29 x 16.5 mm half-ellipse below a flat top) pushed `push` past the rectum's
/// top, moved back in 0.25 mm steps until it encloses the rectum with a margin [m].
Polygon rigidProbeOutline(Rng& rng, const Point2& rectum_centre, double r_y, const Polygon& rectum,
                          double& push) {
  Polygon probe;
  push = rng.uniform(3.0, 4.5) * kMm;
  for (int attempt = 0; attempt < 20; ++attempt, push -= 0.25 * kMm) {
    const double y_top = rectum_centre.y() + r_y + push;
    const double cx = rectum_centre.x() + rng.uniform(-0.5, 0.5) * kMm;
    std::vector<Point2> v;
    for (int k = 0; k < 8; ++k)
      v.emplace_back(cx + kRigidHalfWidth_m * (1.0 - 2.0 * k / 8.0), y_top);
    for (int k = 0; k < 32; ++k) {
      const double t = M_PI + M_PI * k / 32.0;
      v.emplace_back(cx + kRigidHalfWidth_m * std::cos(t), y_top + kRigidDepth_m * std::sin(t));
    }
    probe = Polygon(v);
    bool encloses = true;
    for (const Point2& q : rectum.vertices()) {
      encloses = encloses && probe.contains(q) && probe.distanceToBoundary(q) >= kProbeMargin_m;
    }
    if (encloses)
      break;
  }
  return probe;
}

/// The forward FEM (the hidden truth): the probe pushes the rectum wall onto its outline, the
/// bladder wall carries the hidden pressure, the regions have the hidden moduli; returns the
/// displacement of every node of `fine` (x, y interleaved) [m].
Eigen::VectorXd forwardDisplacement(const detail::SliceModel& fine, const Polygon& probe,
                                    const ProbeCaseTruth& truth) {
  std::vector<Point2> rectum_displacement;
  for (int node : fine.rectum_nodes) {
    const Point2& x = fine.mesh.nodes[static_cast<std::size_t>(node)];
    const auto y = projectOntoProbe(fine.rectum_centre, x, probe);
    if (!y)
      throw std::runtime_error("generateProbeCase: probe projection failed");
    rectum_displacement.push_back(*y - x);
  }
  detail::SliceSolver solver(fine, rectum_displacement, fine.bladder_nodes);
  detail::Moduli moduli{};
  moduli[kSurrounding] = truth.surrounding_modulus_Pa;
  moduli[kCentralGland] = truth.cg_modulus_Pa;
  moduli[kPeripheralZone] = truth.pz_modulus_Pa;
  if (!solver.setModuli(moduli))
    throw std::runtime_error("generateProbeCase: forward FEM failed");
  // Bladder pressure: p times the outward normal of every bladder-wall edge, half to each node.
  Eigen::VectorXd nodal = Eigen::VectorXd::Zero(solver.dofCount());
  for (const auto& edge : fine.bladder_wall_edges) {
    const Point2 d = fine.mesh.nodes[static_cast<std::size_t>(edge[1])] -
                     fine.mesh.nodes[static_cast<std::size_t>(edge[0])];
    const Point2 f =
        truth.bladder_pressure_Pa * Point2(d.y(), -d.x());  // |d| x normal out of the cavity
    for (int node : edge) {
      nodal(2 * node) += 0.5 * f.x();
      nodal(2 * node + 1) += 0.5 * f.y();
    }
  }
  Eigen::VectorXd force(solver.forceDofCount());
  for (int k = 0; k < solver.forceDofCount(); ++k)
    force(k) = nodal(solver.forceDofs()[static_cast<std::size_t>(k)]);
  return solver.u0() + solver.forceResponse(force);
}

/// The test points carried into the probe-in slice by the forward FEM mapping; throws if one
/// falls outside the mesh.
std::vector<Point2> mappedTestPoints(const PointMapping& mapping, const std::vector<Point2>& out) {
  std::vector<Point2> in;
  for (const Point2& p : out) {
    const auto y = mapping.forward(p);
    if (!y)
      throw std::runtime_error("generateProbeCase: test point outside the forward mesh");
    in.push_back(*y);
  }
  return in;
}

}  // namespace

ProbeCase generateProbeCase(ProbeType type, std::uint64_t seed, const ProbeCaseOptions& options) {
  Rng rng(seed * 0x9E3779B97F4A7C15ULL + (type == ProbeType::kBalloon ? 17 : 91));
  ProbeCase pc;
  pc.type = type;
  pc.seed = seed;
  SliceSegmentation& out = pc.probe_out;

  // Field of view (x: left-right, y: anterior) [m].
  out.domain = Polygon(
      {{-50 * kMm, -72 * kMm}, {50 * kMm, -72 * kMm}, {50 * kMm, 45 * kMm}, {-50 * kMm, 45 * kMm}});

  // Prostate: perturbed ellipse, 40 vertices (vertex 30 on the posterior midline).
  const int n_p = 40;
  const double a = rng.uniform(19, 23) * kMm, b = rng.uniform(14, 17) * kMm;
  const double e2 = rng.uniform(-0.03, 0.03), e3 = rng.uniform(-0.025, 0.025),
               p2 = rng.uniform(0, 2 * M_PI), p3 = rng.uniform(0, 2 * M_PI);
  std::vector<Point2> prostate;
  for (int k = 0; k < n_p; ++k) {
    const double t = 2.0 * M_PI * k / n_p;
    const double scale = 1.0 + e2 * std::cos(2 * t + p2) + e3 * std::cos(3 * t + p3);
    prostate.emplace_back(a * scale * std::cos(t), b * scale * std::sin(t));
  }
  // CG: the anterior arc (vertices k1..k2) closed by a sagging inner arc; PZ: the rest.
  const int k1 = 2, k2 = 18, m_inner = 9;
  const double depth = rng.uniform(0.55, 0.72) * b;
  const Point2 left = prostate[k2], right = prostate[k1];
  std::vector<Point2> inner;  // from left to right, excluding the end points
  for (int j = 1; j <= m_inner; ++j) {
    const double s = static_cast<double>(j) / (m_inner + 1);
    inner.push_back(left + s * (right - left) - Point2(0.0, depth * std::sin(M_PI * s)));
  }
  std::vector<Point2> cg(prostate.begin() + k1, prostate.begin() + k2 + 1);
  cg.insert(cg.end(), inner.begin(), inner.end());
  std::vector<Point2> pz;
  for (int k = k2; k != k1; k = (k + 1) % n_p)
    pz.push_back(prostate[static_cast<std::size_t>(k)]);
  pz.push_back(prostate[k1]);
  pz.insert(pz.end(), inner.rbegin(), inner.rend());
  out.cg = Polygon(cg);
  out.pz = Polygon(pz);
  double y_post = 0.0, y_ant = 0.0;
  for (const Point2& p : prostate) {
    y_post = std::min(y_post, p.y());
    y_ant = std::max(y_ant, p.y());
  }

  // Rectum posterior to the prostate: a circle (balloon cases) or a collapsed ellipse (rigid
  // cases, so that the 29 x 16.5 mm probe can enclose it).
  const double gap = rng.uniform(1.5, 3.0) * kMm;
  double r_x, r_y;
  if (type == ProbeType::kBalloon) {
    r_x = r_y = rng.uniform(7.5, 9.0) * kMm;
  } else {
    r_x = rng.uniform(8.0, 9.5) * kMm;
    r_y = rng.uniform(4.0, 5.0) * kMm;
  }
  const Point2 rectum_centre(rng.uniform(-1.0, 1.0) * kMm, y_post - gap - r_y);
  out.rectum = ellipse(rectum_centre, r_x, r_y, 20, M_PI / 20);

  // Pubic bones (fixed) and bladder, anterior.
  const double bone_dy = rng.uniform(-1.0, 1.0) * kMm;
  out.bones.push_back(ellipse(Point2(-25 * kMm, 37 * kMm + bone_dy), 11 * kMm, 5 * kMm, 12));
  out.bones.push_back(ellipse(Point2(25 * kMm, 37 * kMm - bone_dy), 11 * kMm, 5 * kMm, 12));
  out.bones.push_back(ellipse(Point2(0.0, -66 * kMm), 28 * kMm, 4 * kMm, 16));  // sacrum / coccyx
  const double bl_b = rng.uniform(5.0, 7.0) * kMm;
  out.bladder = Outline(ellipse(Point2(0.0, y_ant + rng.uniform(2.0, 3.0) * kMm + bl_b),
                                rng.uniform(10.0, 12.0) * kMm, bl_b, 24));

  // Probe outline in the probe-in slice.
  Polygon probe;
  double push = 0.0;
  if (type == ProbeType::kBalloon) {
    push = rng.uniform(8.0, 12.0) * kMm;
    const Point2 c(rectum_centre.x() + rng.uniform(-1.0, 1.0) * kMm,
                   rectum_centre.y() + r_y + push - kBalloonRadius_m);
    probe = ellipse(c, kBalloonRadius_m, kBalloonRadius_m, 64);
  } else {
    probe = rigidProbeOutline(rng, rectum_centre, r_y, out.rectum.outer, push);
  }

  // Forward FEM on a finer mesh with the hidden moduli and bladder pressure.
  ProbeCaseTruth& truth = pc.truth;
  truth.cg_modulus_Pa = rng.uniform(options.cg_modulus_range_Pa[0], options.cg_modulus_range_Pa[1]);
  truth.pz_modulus_Pa = rng.uniform(options.pz_modulus_range_Pa[0], options.pz_modulus_range_Pa[1]);
  truth.surrounding_modulus_Pa =
      rng.uniform(options.surrounding_modulus_range_Pa[0], options.surrounding_modulus_range_Pa[1]);
  truth.bladder_pressure_Pa =
      (rng.uniform(0.0, 1.0) < 0.5 ? -1.0 : 1.0) *
      rng.uniform(options.bladder_pressure_range_Pa[0], options.bladder_pressure_range_Pa[1]);
  truth.probe_push_m = push;
  const detail::SliceModel fine =
      detail::buildSliceModel(out, options.truth_target_nodes, kPoissonRatio);
  truth.forward_mesh_nodes = static_cast<int>(fine.mesh.nodes.size());
  const Eigen::VectorXd u = forwardDisplacement(fine, probe, truth);

  std::vector<Point2> displacement(fine.mesh.nodes.size());
  for (std::size_t i = 0; i < displacement.size(); ++i)
    displacement[i] =
        Point2(u(static_cast<Eigen::Index>(2 * i)), u(static_cast<Eigen::Index>(2 * i + 1)));
  auto mapping = std::make_shared<MeshMapping>(fine.mesh, displacement);
  truth.mapping = mapping;

  // Probe-in outlines: exact, then with segmentation noise.
  const Loops deformed = detail::deformedLoops(fine, u);
  if (deformed.size() != 1)
    throw std::runtime_error("generateProbeCase: prostate boundary is not one loop");
  truth.probe_in_prostate = Polygon(deformed[0]);
  truth.probe_outline = probe;
  const auto mapped = [&](const Polygon& p) {
    const auto v = mapPolygonForward(*mapping, p.vertices());
    if (!v)
      throw std::runtime_error("generateProbeCase: structure outside the forward mesh");
    return Polygon(*v);
  };
  truth.probe_in_cg = mapped(out.cg.outer);
  truth.probe_in_pz = mapped(out.pz.outer);
  truth.probe_in_bladder = mapped(out.bladder->outer);  // the wall nodes are mesh nodes
  pc.probe_in.prostate =
      addContourNoise(resample(deformed[0], 1.0 * kMm), options.noise_rms_m, rng);
  pc.probe_in.probe =
      addContourNoise(resample(probe.vertices(), 1.0 * kMm), options.noise_rms_m, rng);

  // Homologous test points: the posterior CG border at the midline (3.3.4), then random
  // points inside the gland at least 2 mm from its outline.
  const Polygon gland(prostate);
  pc.test_points_out.push_back(inner[m_inner / 2]);
  for (int attempt = 0;
       attempt < 10000 && static_cast<int>(pc.test_points_out.size()) < options.test_points;
       ++attempt) {
    const Point2 p(rng.uniform(-a, a), rng.uniform(y_post, y_ant));
    if (gland.contains(p) && gland.distanceToBoundary(p) >= 2.0 * kMm)
      pc.test_points_out.push_back(p);
  }
  pc.test_points_in = mappedTestPoints(*mapping, pc.test_points_out);
  const SegmentationCheck check = checkSegmentation(pc.probe_out, pc.probe_in);
  if (!check.ok)
    throw std::runtime_error("generateProbeCase: invalid synthetic segmentation: " + check.problem);
  return pc;
}

double meanPointError(const PointMapping& mapping, const ProbeCase& probe_case, int* unmapped) {
  double sum = 0.0;
  int missing = 0;
  const std::size_t n =
      std::min(probe_case.test_points_out.size(), probe_case.test_points_in.size());
  for (std::size_t i = 0; i < n; ++i) {
    const auto y = mapping.forward(probe_case.test_points_out[i]);
    if (!y)
      ++missing;
    sum += ((y ? *y : probe_case.test_points_out[i]) - probe_case.test_points_in[i]).norm();
  }
  if (unmapped)
    *unmapped = missing;
  return n > 0 ? sum / static_cast<double>(n) : 0.0;
}

}  // namespace needle_guidance::registration
