// Needle insertion on an embedded cut track with condensed compliance, in 2-D and 3-D
// (embedded_needle.h).
#include "needle_guidance/fem/embedded_needle.h"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "needle_guidance/cpu_time.h"
#include "needle_guidance/math.h"

namespace needle_guidance::fem {
namespace {

constexpr double kEntryInset_m = 1e-5;  // the entry point lies this far inside the face
constexpr double kInsideTol = 1e-9;     // barycentric, round-off on shared faces
// A point outside an element's bounding box by more than this fraction of its largest side is
// outside the element by at least that much, so one barycentric weight is below about
// -kBoxMargin sin(a), a the element's sharpest angle: far below -kInsideTol for any element that
// is not degenerate (a > 1e-6 rad), so locate need not compute its weights.
constexpr double kBoxMargin = 1e-3;
constexpr double kCutTol_m = 1e-10;        // root finding of the cut length
constexpr double kEventTol_m = 1e-12;      // events closer than this to a segment end coincide
constexpr int kMaxEventsPerMove = 100000;  // bound against a stalled event loop
constexpr int kMaxCutIterations = 60;
constexpr double kFirstCutTrial_m = 2e-5;  // first trial length when bracketing the cut
constexpr double kMaxCutTrial_m = 2.5e-4;  // trials grow up to this (a quarter of a fine element)
// Corotational fixed point: converged when no node's warp changes by more than a tolerance
// derived from the seeds' step-halving target (docs/tissue_3d.md, "Settled to the accuracy the
// seed needs"). The state a seed is released from, whose tip's tissue point the seed is, is
// settled to a fiftieth of the target. Every other state (just before an event, at a move's
// end, in retraction) to EmbeddedNeedleParams::event_warp_tolerance_m, by default half of it:
// a warp error e there moves the event's location by the coupling (below one) times e, and
// the seed, whose tissue point is located afresh at every track point, by less (measured at
// most 0.1 e on the tuning scenes), so the seed stays within a twentieth of the target of the
// tightly settled insertion's.
constexpr double kReleaseWarpTol_m = kSeedStepTolerance_m / 50.0;
constexpr int kMaxWarpUpdates = 60;
// Beyond kMaxWarpUpdates the iteration goes on while the change still halves over every
// kContractionWindow updates (a slow but steady contraction: at that rate 0.01 mm shrinks to
// the tolerance in about 10 windows), up to kMaxContractingUpdates (about 10 s CPU at 50k
// tetrahedra, less than the insertion a refusal discards); a change that no longer shrinks
// so is a stall or a cycle and refuses the move.
constexpr std::size_t kContractionWindow = 20;
constexpr double kContraction = 0.5;
constexpr int kMaxContractingUpdates = 240;
// The warped stiffness is re-factored when the last kRewarpProbe updates, extrapolated at their
// mean rate, predict more than kRewarpBudget further updates (a refactorisation costs about as
// much as that many updates at 50k tetrahedra), at most kMaxRewarpsPerMove times per move.
constexpr int kRewarpProbe = 5;
constexpr double kRewarpBudget = 16.0;
constexpr int kMaxRewarpsPerMove = 4;
// Corotational: a segment of a move is solved again from its start on the warp settled where
// its event happens (or at its end) until a relocation moves its end (tip position, tip's
// tissue point, cut length) by at most the event tolerance on the warp
// (EmbeddedNeedleParams::event_warp_tolerance_m), or this many times. A relocation moves the end
// by the change of the warp since the last one times a coupling below one, so what remains
// after a move of that size is a fraction of it; a cut that snaps through (its first root comes
// and goes with the warp) alternates and takes the last (EmbeddedNeedleInfo::relocation_m).
constexpr int kMaxRelocations = 3;
// The warp at a segment's end (its event or the move's end) is first guessed by extending
// linearly in the tip position the warps settled at the last two segment ends, up to this many
// times their distance beyond the last; ends closer together than kMinWarpHistorySpacing_m
// (events at one tip position) count as one.
constexpr double kMaxPredictionRatio = 2.0;
constexpr double kMinWarpHistorySpacing_m = 1e-6;
// After a rewarp the compliance columns are solved again in one batch along the needle line up
// to this far beyond the tip, the rest as the tip gets there.
constexpr double kRewarpPrefetch_m = 5e-3;
// follow_tissue: the aim of the cut (X = p - u(X)) is converged when an iteration moves it by
// at most this, 5e4 times below the step-halving target of the seeds.
constexpr double kAimTol_m = 1e-10;
constexpr int kMaxAimIterations = 50;
constexpr double kMinCutDirectionX = 0.5;  // a track turning more than 60 degrees is refused
// The needle's cross-section (locateSection): samples at most half an element apart, within
// these bounds per dimension (2-D: a segment, 3-D: a disc).
constexpr int kMinSectionSamples[2] = {3, 7};
constexpr int kMaxSectionSamples[2] = {64, 256};
constexpr double kGoldenAngle = 2.399963229728653;  // pi (3 - sqrt 5): the sunflower disc rule

/// s where an affine function with values fa at sa and fb at sb equals level.
double crossing(double sa, double fa, double sb, double fb, double level) {
  const double t = (fb == fa) ? 1.0 : std::clamp((level - fa) / (fb - fa), 0.0, 1.0);
  return sa + t * (sb - sa);
}

std::string mm(double x_m) {
  return std::to_string(x_m * 1e3);
}

template <int Dim>
std::string pointText(const Point<Dim>& p) {
  std::string s = "[";
  for (int d = 0; d < Dim; ++d) {
    s += (d ? ", " : "") + mm(p(d));
  }
  return s + "] mm";
}

/// Edge length of a cell holding about one element: the Dim-th root of the measure per element.
double rootOf(double measure, int dim) {
  return dim == 3 ? std::cbrt(measure) : std::sqrt(measure);
}

/// Edge length of the regular simplex of this measure (area or volume) [m].
double regularEdge(double measure, int dim) {
  return dim == 3 ? std::cbrt(6.0 * std::sqrt(2.0) * measure)
                  : std::sqrt(4.0 * measure / std::sqrt(3.0));
}

/// Offsets of n equal-area samples of the needle's cross-section of radius a normal to +x: in 3-D
/// the sunflower rule on the disc (sample k at radius a sqrt((k + 1/2) / n), turned by the golden
/// angle from the last), in 2-D the midpoints of n equal parts of the diameter.
template <int Dim>
std::vector<Point<Dim>> sectionOffsets(double a, int n) {
  std::vector<Point<Dim>> out;
  for (int k = 0; k < n; ++k) {
    Point<Dim> q = Point<Dim>::Zero();
    if constexpr (Dim == 3) {
      const double r = a * std::sqrt((k + 0.5) / n), t = kGoldenAngle * k;
      q(1) = r * std::cos(t);
      q(2) = r * std::sin(t);
    } else {
      q(1) = a * (2.0 * k + 1.0 - n) / n;
    }
    out.push_back(q);
  }
  return out;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// EmbeddingTissue

/// Elements bucketed by their bounding boxes on a uniform grid of about one element per cell.
template <int Dim>
struct EmbeddingTissue<Dim>::Grid {
  using Cell = Eigen::Matrix<int, Dim, 1>;
  Point<Dim> lo, cell;
  Cell n;
  std::vector<std::vector<int>> buckets;
  /// Each element's bounding box, widened by kBoxMargin of its largest side (locate skips the
  /// weights of an element whose box does not hold the point).
  std::vector<Point<Dim>> box_lo, box_hi;
  int index(const Cell& c) const {
    int i = 0;
    for (int k = Dim - 1; k >= 0; --k) {
      i = i * n(k) + c(k);
    }
    return i;
  }
  Cell cellOf(const Point<Dim>& p) const {
    Cell c;
    for (int k = 0; k < Dim; ++k) {
      c(k) = std::clamp(static_cast<int>(std::floor((p(k) - lo(k)) / cell(k))), 0, n(k) - 1);
    }
    return c;
  }
};

template <int Dim>
EmbeddingTissue<Dim>::EmbeddingTissue(const SimplexMesh<Dim>& mesh,
                                      const std::vector<char>& node_fixed,
                                      const std::vector<Material>& materials, double thickness_m,
                                      bool corotational)
    : mesh_(&mesh), node_fixed_(node_fixed) {
  if (node_fixed_.size() != mesh.nodes.size() || mesh.elements.empty()) {
    throw std::invalid_argument("EmbeddingTissue: " + std::to_string(node_fixed_.size()) +
                                " fixed flags for " + std::to_string(mesh.nodes.size()) +
                                " nodes, or no element");
  }
  const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
  const SparseMatrix k = assembleStiffness<Dim>(mesh, materials, thickness_m);
  std::vector<char> fixed(static_cast<std::size_t>(Dim * mesh.nodeCount()), 0);
  for (int i = 0; i < mesh.nodeCount(); ++i) {
    if (node_fixed_[static_cast<std::size_t>(i)]) {
      for (int d = 0; d < Dim; ++d) {
        fixed[static_cast<std::size_t>(Dim * i + d)] = 1;
      }
    }
  }
  compliance_ = std::make_unique<CondensedCompliance>(k, fixed);
  if (corotational) {
    corotation_ = std::make_unique<CorotationalForces<Dim>>(mesh, materials, thickness_m);
  }
  assembly_cpu_s_ = clock.seconds();

  grid_ = std::make_unique<Grid>();
  Point<Dim> lo = mesh.nodes[0], hi = mesh.nodes[0];
  for (const auto& p : mesh.nodes) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  const double per_cell = rootOf((hi - lo).prod() / std::max(1, mesh.elementCount()), Dim);
  grid_->lo = lo;
  for (int k = 0; k < Dim; ++k) {
    grid_->n(k) = std::max(1, static_cast<int>((hi(k) - lo(k)) / (2.0 * per_cell)));
    grid_->cell(k) = (hi(k) - lo(k)) / grid_->n(k);
  }
  grid_->buckets.resize(static_cast<std::size_t>(grid_->n.prod()));
  grid_->box_lo.resize(mesh.elements.size());
  grid_->box_hi.resize(mesh.elements.size());
  for (int e = 0; e < mesh.elementCount(); ++e) {
    const Corners<Dim> c = corners<Dim>(mesh, e);
    Point<Dim> a = c[0], b = c[0];
    for (const auto& p : c) {
      a = a.cwiseMin(p);
      b = b.cwiseMax(p);
    }
    const double margin = kBoxMargin * (b - a).maxCoeff();
    grid_->box_lo[static_cast<std::size_t>(e)] = a.array() - margin;
    grid_->box_hi[static_cast<std::size_t>(e)] = b.array() + margin;
    const typename Grid::Cell ca = grid_->cellOf(a), cb = grid_->cellOf(b);
    typename Grid::Cell at = ca;
    while (true) {  // every cell of the box [ca, cb], x fastest
      grid_->buckets[static_cast<std::size_t>(grid_->index(at))].push_back(e);
      int k = 0;
      while (k < Dim && at(k) == cb(k)) {
        at(k) = ca(k);
        ++k;
      }
      if (k == Dim) {
        break;
      }
      ++at(k);
    }
  }
}

template <int Dim>
EmbeddingTissue<Dim>::~EmbeddingTissue() = default;

template <int Dim>
Eigen::VectorXd EmbeddingTissue<Dim>::corotationDisplacement(const Eigen::VectorXd& u) const {
  if (!corotation_) {
    return {};
  }
  const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
  int inverted = 0;
  Eigen::VectorXd v =
      -compliance_->solveSinglePrecision(corotation_->correction(u, &inverted, &last_turn_rad_));
  inverted_elements_ = inverted;
  corotation_cpu_s_ += clock.seconds();
  if (!v.allFinite()) {
    throw std::runtime_error("EmbeddingTissue: the corotational displacement is not finite");
  }
  return v;
}

template <int Dim>
void EmbeddingTissue<Dim>::warpReference(const Eigen::VectorXd& u) const {
  if (!corotation_) {
    return;
  }
  const CpuStopwatch clock(CpuStopwatch::Scope::kProcess);
  compliance_->refactor(corotation_->warpedStiffness(u));
  ++reference_version_;
  corotation_cpu_s_ += clock.seconds();
}

template <int Dim>
std::optional<EmbeddedPoint<Dim>> EmbeddingTissue<Dim>::locate(const Point<Dim>& p) const {
  const auto& bucket = grid_->buckets[static_cast<std::size_t>(grid_->index(grid_->cellOf(p)))];
  EmbeddedPoint<Dim> best;
  double best_min = -1e300;
  for (int e : bucket) {
    const std::size_t ei = static_cast<std::size_t>(e);
    if ((p.array() < grid_->box_lo[ei].array()).any() ||
        (p.array() > grid_->box_hi[ei].array()).any()) {
      continue;  // outside the element by far more than kInsideTol in its weights
    }
    const Eigen::Matrix<double, Dim + 1, 1> w = barycentric<Dim>(corners<Dim>(*mesh_, e), p);
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

template <int Dim>
std::optional<EmbeddedPoint<Dim>> EmbeddingTissue<Dim>::locateSection(const Point<Dim>& p,
                                                                      double radius_m) const {
  std::optional<EmbeddedPoint<Dim>> centre = locate(p);
  if (!centre || !(radius_m > 0.0)) {
    return centre;
  }
  // Samples no farther apart than half the element at p: spacing a sqrt(pi / n) on the disc,
  // 2a / n on the segment.
  const double h =
      regularEdge(std::abs(signedMeasure<Dim>(corners<Dim>(*mesh_, centre->element))), Dim);
  const double wanted = Dim == 3 ? 4.0 * kPi * radius_m * radius_m / (h * h) : 4.0 * radius_m / h;
  const int n = std::clamp(static_cast<int>(std::ceil(wanted)), kMinSectionSamples[Dim - 2],
                           kMaxSectionSamples[Dim - 2]);
  std::vector<NodeWeight>& section = centre->section;
  int used = 0;
  for (const Point<Dim>& offset : sectionOffsets<Dim>(radius_m, n)) {
    const std::optional<EmbeddedPoint<Dim>> q = locate(p + offset);
    if (!q) {
      continue;  // beyond the tissue's surface
    }
    ++used;
    const auto& nodes = mesh_->elements[static_cast<std::size_t>(q->element)];
    for (int a = 0; a < Dim + 1; ++a) {
      auto at = std::find_if(section.begin(), section.end(),
                             [&](const NodeWeight& w) { return w.node == nodes[a]; });
      if (at == section.end()) {
        section.push_back({nodes[a], q->weights(a)});
      } else {
        at->weight += q->weights(a);
      }
    }
  }
  if (used == 0) {
    section.clear();  // every sample beyond the surface: the point itself
  }
  for (NodeWeight& w : section) {
    w.weight /= used;
  }
  return centre;
}

template <int Dim>
bool EmbeddingTissue<Dim>::rigidElement(int element) const {
  for (int n : mesh_->elements[static_cast<std::size_t>(element)]) {
    if (!node_fixed_[static_cast<std::size_t>(n)]) {
      return false;
    }
  }
  return true;
}

// ---------------------------------------------------------------------------------------------
// EmbeddedNeedle

template <int Dim>
EmbeddedNeedle<Dim>::EmbeddedNeedle(const EmbeddingTissue<Dim>& tissue,
                                    const EmbeddedNeedleParams& params, double entry_x_m,
                                    double max_tip_x_m)
    : tissue_(&tissue), params_(params), entry_x_m_(entry_x_m), max_tip_x_m_(max_tip_x_m) {
  if (!(params.cutting_force_N >= 0.0) || !(params.track_spacing_m > 0.0) ||
      !(params.kinetic_friction_N_per_m >= 0.0) ||
      !(params.static_friction_N_per_m >= params.kinetic_friction_N_per_m) ||
      !std::isfinite(entry_x_m) ||
      ((params.follow_tissue || params.section_load) && !(params.tip_radius_m > 0.0)) ||
      !(params.event_warp_tolerance_m > 0.0 && std::isfinite(params.event_warp_tolerance_m))) {
    throw std::invalid_argument(
        "EmbeddedNeedle: needs cutting_force >= 0, track_spacing > 0, 0 <= kinetic friction <= "
        "static friction, a finite entry face, a finite event tolerance on the warp > 0 and, when "
        "the track follows the tissue or the load is spread over the needle's section, a tip "
        "radius > 0");
  }
  s_ = entry_x_m - 1e-3;
}

template <int Dim>
typename EmbeddedNeedle<Dim>::Vector EmbeddedNeedle<Dim>::onLine(double x) const {
  Vector p;
  p(0) = x;
  p.template tail<Dim - 1>() = lateral_;
  return p;
}

template <int Dim>
std::optional<typename EmbeddedNeedle<Dim>::Point_> EmbeddedNeedle<Dim>::constraintPoint(
    const Vector& x) const {
  return sectionPoint(x, params_.section_load ? params_.tip_radius_m : 0.0);
}

template <int Dim>
std::optional<typename EmbeddedNeedle<Dim>::Point_> EmbeddedNeedle<Dim>::sectionPoint(
    const Vector& x, double radius_m) const {
  std::optional<Point_> p = tissue_->locateSection(x, radius_m);
  if (p && p->section.empty()) {  // a point force: the element's corners
    const auto& nodes = tissue_->mesh().elements[static_cast<std::size_t>(p->element)];
    for (int a = 0; a < Dim + 1; ++a) {
      p->section.push_back({nodes[a], p->weights(a)});
    }
  }
  return p;
}

template <int Dim>
void EmbeddedNeedle<Dim>::prefetchLine(const Lateral& lateral,
                                       std::optional<double> end_x_m) const {
  // The cut track is the reference line at this lateral position: the columns of every node
  // under the needle's cross-section along it are solved in one batch instead of a few per step.
  constexpr double kSample_m = 2e-4;
  std::vector<int> dofs;
  std::vector<char> seen(static_cast<std::size_t>(tissue_->mesh().nodeCount()), 0);
  const double end = end_x_m.value_or(max_tip_x_m_ + 2.0 * params_.track_spacing_m);
  Vector p;
  p.template tail<Dim - 1>() = lateral;
  for (double x = entry_x_m_ + kEntryInset_m; x <= end; x += kSample_m) {
    p(0) = x;
    const std::optional<Point_> e = constraintPoint(p);
    if (!e) {
      break;
    }
    for (const NodeWeight& w : e->section) {
      if (!seen[static_cast<std::size_t>(w.node)]) {
        seen[static_cast<std::size_t>(w.node)] = 1;
        for (int d = 0; d < Dim; ++d) {
          dofs.push_back(Dim * w.node + d);
        }
      }
    }
  }
  tissue_->compliance().require(dofs);
}

template <int Dim>
void EmbeddedNeedle<Dim>::requireColumns(const Point_& p) const {
  std::vector<int> dofs;
  for (const NodeWeight& w : p.section) {
    for (int d = 0; d < Dim; ++d) {
      dofs.push_back(Dim * w.node + d);
    }
  }
  tissue_->compliance().require(dofs);
}

template <int Dim>
typename EmbeddedNeedle<Dim>::Block EmbeddedNeedle<Dim>::block(const Point_& p,
                                                               const Point_& q) const {
  const auto& g = tissue_->compliance();
  Block b = Block::Zero();
  for (const NodeWeight& wq : q.section) {
    for (int d = 0; d < Dim; ++d) {
      const Eigen::VectorXd& col = g.column(Dim * wq.node + d);
      Vector sum = Vector::Zero();
      for (const NodeWeight& wp : p.section) {
        sum += wp.weight * col.template segment<Dim>(Dim * wp.node);
      }
      b.col(d) += wq.weight * sum;
    }
  }
  return b;
}

template <int Dim>
typename EmbeddedNeedle<Dim>::Solution EmbeddedNeedle<Dim>::solveAt(double s, const Point_* tip,
                                                                    bool tip_axial_free) const {
  ++solves_;
  ++total_solves_;
  const int ns = static_cast<int>(shaft_.size());
  const int m = ns + (tip ? 1 : 0);
  Solution sol;
  sol.forces = Eigen::VectorXd::Zero(Dim * m);
  sol.displacement = Eigen::VectorXd::Zero(Dim * m);
  if (m == 0) {
    return sol;
  }
  Eigen::MatrixXd c(Dim * m, Dim * m);
  c.topLeftCorner(Dim * ns, Dim * ns) = shaft_compliance_;
  if (tip) {
    requireColumns(*tip);
    for (int k = 0; k < ns; ++k) {
      const Block b = block(shaft_[static_cast<std::size_t>(k)].point, *tip);
      c.template block<Dim, Dim>(Dim * k, Dim * ns) = b;
      c.template block<Dim, Dim>(Dim * ns, Dim * k) = b.transpose();
    }
    c.template block<Dim, Dim>(Dim * ns, Dim * ns) = block(*tip, *tip);
  }
  // Prescribed components (value: displacement) and force components (value: force).
  std::vector<int> fixed, loaded;
  Eigen::VectorXd value(Dim * m);
  for (int k = 0; k < ns; ++k) {
    const ShaftPoint& p = shaft_[static_cast<std::size_t>(k)];
    for (int d = 1; d < Dim; ++d) {
      if (!p.held) {
        value(Dim * k + d) = 0.0;
        loaded.push_back(Dim * k + d);
      } else {
        value(Dim * k + d) = lateral_(d - 1) - p.point.reference_m(d);
        fixed.push_back(Dim * k + d);
      }
    }
    if (p.stuck) {
      value(Dim * k) = s + p.offset_m - p.point.reference_m.x();
      fixed.push_back(Dim * k);
    } else {
      value(Dim * k) = direction_ * params_.kinetic_friction_N_per_m * p.share_m;
      loaded.push_back(Dim * k);
    }
  }
  if (tip) {
    value.template segment<Dim>(Dim * ns) = onLine(s) - tip->reference_m;
    for (int d = 0; d < Dim; ++d) {
      if (d == 0 && tip_axial_free) {
        value(Dim * ns) = 0.0;
        loaded.push_back(Dim * ns);
      } else {
        fixed.push_back(Dim * ns + d);
      }
    }
  }
  // The corotational part of the displacement adds to the compliance's answer.
  Eigen::VectorXd warp = Eigen::VectorXd::Zero(Dim * m);
  for (int k = 0; k < m && warp_.size() > 0; ++k) {
    warp.template segment<Dim>(Dim * k) =
        warpAt(k < ns ? shaft_[static_cast<std::size_t>(k)].point : *tip);
  }
  const int nf = static_cast<int>(fixed.size()), nl = static_cast<int>(loaded.size());
  Eigen::MatrixXd cff(nf, nf), cfl(nf, nl);
  Eigen::VectorXd rhs(nf), fl(nl);
  for (int j = 0; j < nl; ++j) {
    fl(j) = value(loaded[static_cast<std::size_t>(j)]);
  }
  for (int i = 0; i < nf; ++i) {
    rhs(i) = value(fixed[static_cast<std::size_t>(i)]) - warp(fixed[static_cast<std::size_t>(i)]);
    for (int j = 0; j < nf; ++j) {
      cff(i, j) = c(fixed[static_cast<std::size_t>(i)], fixed[static_cast<std::size_t>(j)]);
    }
    for (int j = 0; j < nl; ++j) {
      cfl(i, j) = c(fixed[static_cast<std::size_t>(i)], loaded[static_cast<std::size_t>(j)]);
    }
  }
  const Eigen::VectorXd ff = cff.ldlt().solve(rhs - cfl * fl);
  for (int i = 0; i < nf; ++i) {
    sol.forces(fixed[static_cast<std::size_t>(i)]) = ff(i);
  }
  for (int j = 0; j < nl; ++j) {
    sol.forces(loaded[static_cast<std::size_t>(j)]) = fl(j);
  }
  sol.displacement = c * sol.forces + warp;
  sol.tip_force_N = tip ? sol.forces(Dim * ns) : 0.0;
  return sol;
}

template <int Dim>
typename EmbeddedNeedle<Dim>::Point_ EmbeddedNeedle<Dim>::along(double cut_m) const {
  const Vector p = tip_.reference_m + cut_m * cut_dir_;
  std::optional<Point_> e = constraintPoint(p);
  if (!e) {
    throw std::runtime_error("the cut track leaves the tissue mesh at " + pointText<Dim>(p));
  }
  if (tissue_->rigidElement(e->element)) {
    throw std::runtime_error(
        "the needle meets rigid tissue (every node of the element held "
        "fixed) at " +
        pointText<Dim>(p));
  }
  return *e;
}

template <int Dim>
double EmbeddedNeedle<Dim>::cutLength(double s) const {
  const double fb = params_.cutting_force_N;
  const double f_start = solveAt(s, &tip_).tip_force_N;
  if (f_start <= fb) {
    return 0.0;
  }
  // The tip's tissue point cannot pass the needle tip: the cut is at most `room`. The cut
  // progresses continuously from the current point, so it ends at the FIRST length where the tip
  // force falls to f_b: the force is not monotone in the length (a point's compliance varies
  // within its element and across a stiffness contrast), and a farther root is reached only
  // once the nearer one has vanished. Marching out in growing trials brackets the first root.
  const double room = std::max(0.0, s - tip_.reference_m.x()) / cut_dir_.x();
  double lo = 0.0, f_lo = f_start - fb;
  double hi = 0.0, f_hi = 0.0;
  const double to_event = next_event_cut_m_ - cut_total_m_;  // the next track point
  for (double trial = kFirstCutTrial_m;; trial = std::min(2.0 * trial, kMaxCutTrial_m)) {
    hi = std::min(room, lo + trial);
    if (lo < to_event && hi > to_event) {
      hi = to_event;  // a trial on the track point: the cut ends there or before, never past it
    }
    const Point_ p_hi = along(hi);
    f_hi = solveAt(s, &p_hi).tip_force_N - fb;
    if (f_hi < 0.0) {
      break;
    }
    if (hi >= room) {
      return room;
    }
    lo = hi;
    f_lo = f_hi;
  }
  // Illinois regula falsi on the tip force, which falls as the cut lengthens.
  int side = 0;
  for (int it = 0; it < kMaxCutIterations && hi - lo > kCutTol_m; ++it) {
    const double mid = (lo * f_hi - hi * f_lo) / (f_hi - f_lo);
    const Point_ p = along(mid);
    const double f = solveAt(s, &p).tip_force_N - fb;
    if (f > 0.0) {
      lo = mid;
      f_lo = f;
      if (side == 1) {
        f_hi *= 0.5;
      }
      side = 1;
    } else {
      hi = mid;
      f_hi = f;
      if (side == -1) {
        f_lo *= 0.5;
      }
      side = -1;
    }
    if (std::abs(f) < 1e-12 * fb) {
      return mid;
    }
  }
  return 0.5 * (lo + hi);
}

template <int Dim>
void EmbeddedNeedle<Dim>::commit(double s, const Point_* tip) {
  s_ = s;
  if (tip) {
    tip_ = *tip;
  }
  committed_ = solveAt(s, tip_active_ ? &tip_ : nullptr);
  for (std::size_t k = 0; k < shaft_.size(); ++k) {
    shaft_[k].world_x_m =
        shaft_[k].point.reference_m.x() + committed_.displacement(Dim * static_cast<int>(k));
  }
}

template <int Dim>
void EmbeddedNeedle<Dim>::addTrackPoint(const Point_& p) {
  requireColumns(p);
  const int ns = static_cast<int>(shaft_.size());
  Eigen::MatrixXd c(Dim * ns + Dim, Dim * ns + Dim);
  c.topLeftCorner(Dim * ns, Dim * ns) = shaft_compliance_;
  for (int k = 0; k < ns; ++k) {
    const Block b = block(shaft_[static_cast<std::size_t>(k)].point, p);
    c.template block<Dim, Dim>(Dim * k, Dim * ns) = b;
    c.template block<Dim, Dim>(Dim * ns, Dim * k) = b.transpose();
  }
  c.template block<Dim, Dim>(Dim * ns, Dim * ns) = block(p, p);
  shaft_compliance_ = std::move(c);
  ShaftPoint sp;
  sp.point = p;
  sp.share_m = params_.track_spacing_m;
  // The needle slides past the tissue it has just cut at the insertion speed: the point
  // slips unless that speed is below the stick velocity.
  sp.world_x_m = worldOf(p.reference_m).x();
  sp.stuck = params_.insertion_velocity_m_s < params_.stick_velocity_m_s;
  sp.offset_m = sp.world_x_m - s_;
  // A followed track bends between its points: a linear element holds two of them on the
  // needle's axis (the tip and one shaft point), not more, so the others are free sideways.
  for (const ShaftPoint& q : shaft_) {
    sp.held = sp.held && !(params_.follow_tissue && q.held && q.point.element == p.element);
  }
  shaft_.push_back(sp);
}

template <int Dim>
void EmbeddedNeedle<Dim>::releaseShaftPoint(std::size_t k) {
  const int n = static_cast<int>(shaft_.size()), i = static_cast<int>(k);
  Eigen::MatrixXd c(Dim * n - Dim, Dim * n - Dim);
  std::vector<int> keep;
  for (int r = 0; r < Dim * n; ++r) {
    if (r / Dim != i) {
      keep.push_back(r);
    }
  }
  for (std::size_t a = 0; a < keep.size(); ++a) {
    for (std::size_t b = 0; b < keep.size(); ++b) {
      c(static_cast<int>(a), static_cast<int>(b)) = shaft_compliance_(keep[a], keep[b]);
    }
  }
  shaft_compliance_ = std::move(c);
  shaft_.erase(shaft_.begin() + static_cast<std::ptrdiff_t>(k));
}

template <int Dim>
typename EmbeddedNeedle<Dim>::Vector EmbeddedNeedle<Dim>::warpAt(const Point_& p) const {
  Vector v = Vector::Zero();
  for (std::size_t a = 0; a < p.section.size() && warp_.size() > 0; ++a) {
    v += p.section[a].weight * warp_.template segment<Dim>(Dim * p.section[a].node);
  }
  return v;
}

template <int Dim>
bool EmbeddedNeedle<Dim>::settleWarp(double tol_m) {
  if (!warped()) {
    return true;
  }
  if (warp_.size() == 0) {
    warp_ = Eigen::VectorXd::Zero(Dim * tissue_->mesh().nodeCount());
  }
  if (reference_version_ != tissue_->referenceVersion()) {
    adoptReference();  // another needle re-warped the shared tissue: the warp is a first guess
  }
  if (warp_updates_ == 0) {
    warp_mixer_.reset();  // the needle moved since the last update
    warp_changes_.clear();
  }
  const Eigen::VectorXd u = displacementField();
  const Eigen::VectorXd v = tissue_->corotationDisplacement(u);
  const double change = (v - warp_).lpNorm<Eigen::Infinity>();
  ++info_.corotation_updates;
  if (change <= tol_m) {
    warp_ = v;
    commit(s_, nullptr);
    warp_updates_ = 0;
    return true;
  }
  warp_changes_.push_back(change);
  if (++warp_updates_ > kMaxWarpUpdates) {  // counted since the last rewarp
    // Still contracting: continue up to kMaxContractingUpdates; else refuse.
    const std::size_t n = warp_changes_.size();
    const double before =
        n > kContractionWindow ? warp_changes_[n - 1 - kContractionWindow] : change;
    if (!(change <= kContraction * before) || warp_updates_ > kMaxContractingUpdates) {
      throw std::runtime_error(
          "the corotational iteration did not converge: the warp still changed by " + mm(change) +
          " mm after " + std::to_string(warp_updates_) + " updates (" + mm(before) + " mm " +
          std::to_string(kContractionWindow) + " updates before) and " +
          std::to_string(info_.rewarps) + " refactorisations of the warped stiffness");
    }
  }
  if (slowWarp(tol_m)) {
    rewarp(u);
    return false;
  }
  warp_ = warp_mixer_.next(warp_, v);
  commit(s_, nullptr);
  return false;
}

template <int Dim>
bool EmbeddedNeedle<Dim>::slowWarp(double tol_m) const {
  const int n = static_cast<int>(warp_changes_.size());
  if (n < kRewarpProbe || info_.rewarps >= kMaxRewarpsPerMove) {
    return false;
  }
  const double last = warp_changes_.back();
  const double before = warp_changes_[static_cast<std::size_t>(n - kRewarpProbe)];
  const double rate = std::pow(last / before, 1.0 / (kRewarpProbe - 1));
  if (!(rate < 1.0)) {
    return true;
  }
  return std::log(tol_m / last) / std::log(rate) > kRewarpBudget;
}

template <int Dim>
void EmbeddedNeedle<Dim>::holdDisplacement(const Eigen::VectorXd& u) {
  warp_.setZero();
  warp_ = u - displacementField();  // u = G f + warp on the current compliance
}

template <int Dim>
void EmbeddedNeedle<Dim>::rewarp(const Eigen::VectorXd& u) {
  kept_fields_.formAll();  // the kept states' displacements, on the factor about to be replaced
  tissue_->warpReference(u);
  adoptReference();
  holdDisplacement(u);
  commit(s_, nullptr);
  restartWarpIteration();
  ++info_.rewarps;
}

template <int Dim>
void EmbeddedNeedle<Dim>::restartWarpIteration() {
  warp_updates_ = 0;
  warp_mixer_.reset();
  warp_changes_.clear();
}

template <int Dim>
void EmbeddedNeedle<Dim>::adoptReference() {
  reference_version_ = tissue_->referenceVersion();
  if (!in_tissue_) {
    return;
  }
  prefetchLine(lateral_, std::min(s_ + kRewarpPrefetch_m, max_tip_x_m_));
  requireColumns(tip_);
  if (punctured_) {
    requireColumns(pending_track_);
  }
  const int ns = static_cast<int>(shaft_.size());
  shaft_compliance_.resize(Dim * ns, Dim * ns);
  for (int k = 0; k < ns; ++k) {
    requireColumns(shaft_[static_cast<std::size_t>(k)].point);
  }
  for (int k = 0; k < ns; ++k) {
    for (int l = 0; l < ns; ++l) {
      shaft_compliance_.template block<Dim, Dim>(Dim * k, Dim * l) = block(
          shaft_[static_cast<std::size_t>(k)].point, shaft_[static_cast<std::size_t>(l)].point);
    }
  }
}

template <int Dim>
typename EmbeddedNeedle<Dim>::Vector EmbeddedNeedle<Dim>::nodeDisplacement(
    int node, const Eigen::VectorXd& forces) const {
  Vector u = warp_.size() > 0 ? Vector(warp_.template segment<Dim>(Dim * node)) : Vector::Zero();
  const auto& g = tissue_->compliance();
  const int ns = static_cast<int>(shaft_.size());
  for (int k = 0; k < forces.size() / Dim; ++k) {
    const Point_& p = k < ns ? shaft_[static_cast<std::size_t>(k)].point : tip_;
    for (const NodeWeight& w : p.section) {
      for (int d = 0; d < Dim; ++d) {
        const double f = w.weight * forces(Dim * k + d);
        if (f != 0.0) {
          u += f * g.column(Dim * w.node + d).template segment<Dim>(Dim * node);
        }
      }
    }
  }
  return u;
}

template <int Dim>
typename EmbeddedNeedle<Dim>::Vector EmbeddedNeedle<Dim>::crossSectionDisplacement(
    const Vector& x, const Eigen::VectorXd& forces) const {
  // The needle's cross-section about x (the centre alone if every sample left the mesh).
  const std::optional<Point_> p = sectionPoint(x, params_.tip_radius_m);
  Vector sum = Vector::Zero();
  for (std::size_t a = 0; p && a < p->section.size(); ++a) {
    sum += p->section[a].weight * nodeDisplacement(p->section[a].node, forces);
  }
  return sum;
}

template <int Dim>
void EmbeddedNeedle<Dim>::aimCut() {
  cut_dir_ = Vector::UnitX();
  if (!params_.follow_tissue) {
    return;
  }
  // The tissue now on the needle axis one track spacing ahead of the tip: X = p - u(X), u
  // under the shaft's axial (friction) loads. The tip's cutting load is left out: a tip of
  // finite size pushes the tissue it cuts symmetrically aside, while the point load's
  // displacement next to it is set by the element size and its lateral part by the mesh's
  // asymmetry.
  Eigen::VectorXd forces = Eigen::VectorXd::Zero(Dim * static_cast<int>(shaft_.size()));
  for (int k = 0; k < forces.size() / Dim; ++k) {
    forces(Dim * k) = committed_.forces(Dim * k);
  }
  const Vector p = onLine(s_ + params_.track_spacing_m);
  Vector x = tip_.reference_m + params_.track_spacing_m * Vector::UnitX();
  double change = 0.0;
  for (int it = 0; it < kMaxAimIterations; ++it) {
    ++info_.aim_iterations;
    const Vector next = p - crossSectionDisplacement(x, forces);
    change = (next - x).norm();
    x = next;
    if (change <= kAimTol_m) {
      const Vector d = x - tip_.reference_m;
      if (!(d.norm() > 0.0) || d.x() < kMinCutDirectionX * d.norm()) {
        throw std::runtime_error("the tissue ahead of the tip at " + pointText<Dim>(p) +
                                 " has moved more than 60 degrees off the needle's direction");
      }
      cut_dir_ = d.normalized();
      return;
    }
  }
  throw std::runtime_error("the tissue ahead of the tip at " + pointText<Dim>(p) +
                           " was not located: the fixed point still moved by " + mm(change) +
                           " mm after " + std::to_string(kMaxAimIterations) + " iterations");
}

template <int Dim>
double EmbeddedNeedle<Dim>::stuckExcess(double s) const {
  double worst = -1e300;
  bool any = false;
  for (const ShaftPoint& p : shaft_) {
    any = any || p.stuck;
  }
  if (!any) {
    return worst;
  }
  const double to_event = next_event_cut_m_ - cut_total_m_;
  const Point_ tip = along(std::min(cutLength(s), to_event));
  const Solution sol = solveAt(s, &tip);
  for (std::size_t k = 0; k < shaft_.size(); ++k) {
    if (shaft_[k].stuck) {
      worst = std::max(worst, std::abs(sol.forces(Dim * static_cast<int>(k))) -
                                  params_.static_friction_N_per_m * shaft_[k].share_m);
    }
  }
  return worst;
}

template <int Dim>
double EmbeddedNeedle<Dim>::firstSlip(double target) const {
  constexpr int kBisections = 48;
  if (!(stuckExcess(target) > 0.0)) {
    return target;
  }
  double lo = s_, hi = target;
  for (int i = 0; i < kBisections && hi - lo > kEventTol_m; ++i) {
    const double mid = 0.5 * (lo + hi);
    (stuckExcess(mid) > 0.0 ? hi : lo) = mid;
  }
  return hi;
}

template <int Dim>
bool EmbeddedNeedle<Dim>::insertSegment(double target) {
  const double fb = params_.cutting_force_N;
  if (!punctured_) {
    // The tip presses the surface point: its force is affine in s until it reaches f_b.
    const double fa = solveAt(s_, &tip_).tip_force_N;
    const double f_end = solveAt(target, &tip_).tip_force_N;
    if (f_end < fb) {
      commit(target, nullptr);
      return true;
    }
    const double s_start = s_;
    commit(crossing(s_, fa, target, f_end, fb), nullptr);
    settleBeforeEvent(std::make_pair(s_start, target));
    punctured_ = true;
    pending_track_ = tip_;
    cut_total_m_ = 0.0;
    next_event_cut_m_ = params_.track_spacing_m;
    aimCut();
    ++info_.events;
    return false;
  }
  // A stuck shaft point slips where holding it first needs more than the static friction:
  // located by bisection on the tip position, the cut solved at each.
  const double end = firstSlip(target);
  if (end < target) {
    if (!cutTo(std::max(end, s_))) {
      return false;  // a track point came first
    }
    if (info_.stopped) {
      return true;  // the stop came first
    }
    settleBeforeEvent();
    // The point(s) at their static limit slip (at least the one nearest to it: progress).
    std::size_t nearest = shaft_.size();
    double nearest_ratio = -1.0;
    bool flipped = false;
    for (std::size_t k = 0; k < shaft_.size(); ++k) {
      ShaftPoint& p = shaft_[k];
      const double ratio = std::abs(committed_.forces(Dim * static_cast<int>(k))) /
                           (params_.static_friction_N_per_m * p.share_m);
      if (p.stuck && ratio >= 1.0 - 1e-9) {
        p.stuck = false;
        flipped = true;
      } else if (p.stuck && ratio > nearest_ratio) {
        nearest = k;
        nearest_ratio = ratio;
      }
    }
    if (!flipped && nearest < shaft_.size()) {
      shaft_[nearest].stuck = false;
    }
    commit(s_, nullptr);
    ++info_.events;
    return false;
  }
  return cutTo(target);
}

template <int Dim>
double EmbeddedNeedle<Dim>::heldTipX(const Point_& p, double target) {
  // With the tip's tissue point held at p the tip force is affine in s, so the event is located
  // exactly.
  const double fb = params_.cutting_force_N;
  const double fa = solveAt(s_, &p).tip_force_N;
  const double f_end = solveAt(target, &p).tip_force_N;
  const double s_event = f_end > fb ? crossing(s_, fa, target, f_end, fb) : target;
  if (!locating_) {
    return s_event;
  }
  const double s_start = s_;
  commit(s_event, &p);  // the state just before the event: the tip's tissue point at p
  settleBeforeEvent(f_end > fb ? std::make_optional(std::make_pair(s_start, target))
                               : std::nullopt);
  return s_;
}

template <int Dim>
std::optional<double> EmbeddedNeedle<Dim>::cutToStop() const {
  if (!stop_tissue_x_ || !punctured_ || direction_ < 0) {
    return std::nullopt;
  }
  return std::max(0.0, (*stop_tissue_x_ - tip_.reference_m.x()) / cut_dir_.x());
}

template <int Dim>
bool EmbeddedNeedle<Dim>::cutTo(double target) {
  const double cut = cutLength(target);
  const double to_event = next_event_cut_m_ - cut_total_m_;
  const std::optional<double> to_stop = cutToStop();
  if (to_stop && *to_stop < to_event && cut >= *to_stop - kCutTol_m) {
    // The cut reaches the stop before the next track point: located like a track point.
    const Point_ p = along(*to_stop);
    commit(heldTipX(p, target), &p);
    cut_total_m_ += *to_stop;
    info_.stopped = true;
    return true;
  }
  if (cut < to_event - kCutTol_m) {
    const Point_ p = along(cut);
    cut_total_m_ += cut;
    commit(target, &p);
    return true;
  }
  // The cut reaches the next track point.
  const Point_ p = along(to_event);
  const double s_event = heldTipX(p, target);
  cut_total_m_ = next_event_cut_m_;
  next_event_cut_m_ += params_.track_spacing_m;
  addTrackPoint(pending_track_);
  pending_track_ = p;
  commit(s_event, &p);
  aimCut();
  ++info_.events;
  return s_event >= target - kEventTol_m;
}

template <int Dim>
bool EmbeddedNeedle<Dim>::retractSegment(double target) {
  const double end = std::max(target, entry_x_m_);
  if (end < s_ - kEventTol_m && !shaft_.empty()) {
    const Solution a = solveAt(s_, nullptr), b = solveAt(end, nullptr);
    double s_event = end;
    for (std::size_t k = 0; k < shaft_.size(); ++k) {
      const int i = Dim * static_cast<int>(k);
      const ShaftPoint& p = shaft_[k];
      if (p.stuck) {
        const double limit = params_.static_friction_N_per_m * p.share_m;
        if (std::abs(b.forces(i)) > limit) {
          const double level = b.forces(i) > 0.0 ? limit : -limit;
          s_event = std::max(s_event, crossing(s_, a.forces(i), end, b.forces(i), level));
        }
      } else {
        // Released when the tip passes back over it: s = world x.
        const double ga = s_ - (p.point.reference_m.x() + a.displacement(i));
        const double gb = end - (p.point.reference_m.x() + b.displacement(i));
        if (gb <= 0.0) {
          s_event = std::max(s_event, crossing(s_, ga, end, gb, 0.0));
        }
      }
    }
    const Solution e = solveAt(s_event, nullptr);
    bool changed = false;
    for (std::size_t k = shaft_.size(); k-- > 0;) {
      const int i = Dim * static_cast<int>(k);
      ShaftPoint& p = shaft_[k];
      const double world_x = p.point.reference_m.x() + e.displacement(i);
      if (p.stuck &&
          std::abs(e.forces(i)) >= params_.static_friction_N_per_m * p.share_m * (1.0 - 1e-9)) {
        p.stuck = false;
        changed = true;
      } else if (!p.stuck && s_event <= world_x + kEventTol_m) {
        releaseShaftPoint(k);
        changed = true;
      }
    }
    commit(s_event, nullptr);
    info_.events += changed ? 1 : 0;
    if (s_event > end + kEventTol_m) {
      return false;
    }
  } else if (end < s_) {
    commit(end, nullptr);
  }
  if (target <= entry_x_m_) {
    // Out of the tissue: nothing holds it any more. Unloaded, the tissue is at rest, where the
    // corotated forces vanish: its warp is zero exactly (the seeds are read in this state, so
    // it owes nothing to the warp's tolerance).
    shaft_.clear();
    shaft_compliance_.resize(0, 0);
    warp_.setZero();
    in_tissue_ = punctured_ = tip_active_ = false;
    commit(target, nullptr);
  }
  return true;
}

template <int Dim>
void EmbeddedNeedle<Dim>::predictWarp(double s) {
  const bool valid = warped() && direction_ > 0 && punctured_ && warp_history_.size() == 2 &&
                     warp_history_version_ == reference_version_ &&
                     reference_version_ == tissue_->referenceVersion() &&
                     warp_history_.back().second.size() == warp_.size();
  if (!valid) {
    return;
  }
  const auto& [s_a, warp_a] = warp_history_.front();
  const auto& [s_b, warp_b] = warp_history_.back();
  const double ratio = std::clamp((s - s_b) / (s_b - s_a), 0.0, kMaxPredictionRatio);
  warp_ = warp_b + ratio * (warp_b - warp_a);
  commit(s_, nullptr);
}

template <int Dim>
void EmbeddedNeedle<Dim>::recordWarp() {
  const bool inserting = warped() && direction_ > 0 && punctured_;
  if (!inserting || warp_history_version_ != reference_version_ ||
      (!warp_history_.empty() && s_ < warp_history_.back().first)) {
    warp_history_.clear();  // a new reference or a new insertion: the history starts again
  }
  if (!inserting) {
    return;
  }
  warp_history_version_ = reference_version_;
  if (!warp_history_.empty() && s_ - warp_history_.back().first < kMinWarpHistorySpacing_m) {
    warp_history_.pop_back();  // events at one tip position: the later one stands for both
  }
  warp_history_.emplace_back(s_, warp_);
  if (warp_history_.size() > 2) {
    warp_history_.erase(warp_history_.begin());
  }
}

template <int Dim>
void EmbeddedNeedle<Dim>::settle(double tol_m) {
  while (!settleWarp(tol_m)) {
  }
}

template <int Dim>
void EmbeddedNeedle<Dim>::settleBeforeEvent(std::optional<std::pair<double, double>> tip_bracket) {
  if (!locating_) {
    return;
  }
  end_before_event_ = segmentEnd();
  if (repeatsRelocatedEnd(end_before_event_)) {
    // Relocated on the warp settled where the last round located this event, the event
    // repeats: that warp stands (see consistentSegment).
    event_warp_ = warp_;
    settle_skipped_ = true;
    return;
  }
  // The state before the settle, to fall back on; its displacement is formed only if needed.
  const double s_before = s_;
  const Eigen::VectorXd forces_before = committed_.forces;
  const Eigen::VectorXd warp_before = warp_;
  Eigen::VectorXd u;
  auto form = [&] {
    if (u.size() == 0) {
      u = displacementField(forces_before, warp_before);
    }
  };
  const auto kept = kept_fields_.keep(form);
  try {
    // An event where the tip holds its tissue point (a puncture, a track point) is located
    // again on each update of the warp: the tip force is affine in the tip x, and where it
    // reaches f_b depends on the warp. The settle and the event's location converge together,
    // and the relocation that follows (consistentSegment) finds its end repeated.
    auto locateTip = [&] {
      if (tip_bracket) {
        const auto [lo, hi] = *tip_bracket;
        const double f_lo = solveAt(lo, &tip_).tip_force_N;
        const double f_hi = solveAt(hi, &tip_).tip_force_N;
        commit(crossing(lo, f_lo, hi, f_hi, params_.cutting_force_N), nullptr);
        end_before_event_ = segmentEnd();
      }
    };
    if (predict_event_warp_) {
      predictWarp(s_);  // the segment was located on its start's warp: guess the event's
      locateTip();
    }
    while (!settleWarp(params_.event_warp_tolerance_m)) {
      locateTip();
    }
    event_warp_ = warp_;
  } catch (const std::runtime_error&) {
    // No converging warp in the state just before the event (the crushed tissue under a tip
    // about to puncture): the event stays located on the warp the segment started from,
    // expressed on the current factor.
    form();
    s_ = s_before;
    end_before_event_ = segmentEnd();
    commit(s_, nullptr);
    holdDisplacement(u);
    restartWarpIteration();
    commit(s_, nullptr);
  }
}

template <int Dim>
bool EmbeddedNeedle<Dim>::consistentSegment(double target) {
  if (!warped() || direction_ < 0) {
    // Linear tissue has no warp. Retraction: its events are located with the warp of the
    // segment's start (the seeds' tissue points are set; the needle leaves the tissue at rest).
    const bool done = direction_ > 0 ? insertSegment(target) : retractSegment(target);
    if (done) {
      settle(params_.event_warp_tolerance_m);
    }
    return done;
  }
  // The segment's event (puncture, a track point, stick to slip) and its cut are located with
  // the warp held fixed; the warp they need is the one of the state just before the event (or
  // at the segment's end), known only once the segment has been solved. The segment is solved
  // again from its start on that warp until its end repeats.
  // A relocation whose warp does not converge keeps the segment located before it.
  // A relocation whose end (before its event, or at the segment's end) repeats the last round's
  // to within the event tolerance e keeps the warp settled there without settling it again: the
  // warp changes by 30-150 um over a 1 mm track spacing (first changes of 30-150 um at a
  // contraction of 0.3-0.5), so over e of the end by at most about 0.15 e, below the event's
  // tolerance on the warp.
  relocated_from_.reset();
  settle_skipped_ = false;
  const EmbeddedNeedle start = *this;
  Fallback located;
  const auto kept = kept_fields_.keep([&] { located.form(); });
  bool located_done = false;
  SegmentEnd last = SegmentEnd::Zero();
  double moved = 0.0;
  for (int round = 0;; ++round) {
    event_warp_.resize(0);
    bool done = false;
    try {
      locating_ = true;
      predict_event_warp_ = round == 0;
      info_.stopped = false;
      done = insertSegment(target);
      locating_ = false;
      predict_event_warp_ = false;
      if (round == 0 && event_warp_.size() == 0) {
        if (transit_ && done) {
          return done;  // a transit end: located on the warp guessed for it, not settled
        }
        predictWarp(s_);
      }
      if (event_warp_.size() == 0 && repeatsRelocatedEnd(segmentEnd())) {
        settle_skipped_ = true;  // the segment's end repeats: its warp stands
      }
      while (!settle_skipped_ && event_warp_.size() == 0 &&
             !settleWarp(params_.event_warp_tolerance_m)) {
        insertSegment(s_);  // the tip force against f_b on the updated warp: puncture, cut
      }
    } catch (const std::runtime_error&) {
      locating_ = false;
      predict_event_warp_ = false;
      if (!located.state) {
        throw;
      }
      restoreFallback(located);
      return located_done;
    }
    const bool event = event_warp_.size() > 0;
    if (!event && !punctured_) {
      return done;  // the tip pins its surface point: the state at target holds any warp
    }
    const SegmentEnd end = segmentEnd();
    moved = round > 0 ? (end - last).template lpNorm<Eigen::Infinity>() : 0.0;
    if (round > 0 &&
        (settle_skipped_ || moved <= params_.event_warp_tolerance_m || round >= kMaxRelocations)) {
      if (settle_skipped_) {
        moved = ((event ? end_before_event_ : end) - *relocated_from_)
                    .template lpNorm<Eigen::Infinity>();
        settle_skipped_ = false;
      }
      relocated_from_.reset();
      info_.relocation_m = std::max(info_.relocation_m, moved);
      if (event && done && !transit_) {
        settle(params_.event_warp_tolerance_m);  // the move ends at its event
      }
      recordWarp();
      return done;
    }
    last = end;
    ++info_.relocations;
    located.take(*this);
    located_done = done;
    // Back to the segment's start on the warp just found.
    Eigen::VectorXd warp = event ? std::move(event_warp_) : std::move(warp_);
    const SegmentEnd settled_at = event ? end_before_event_ : end;
    restoreState(start, nullptr);
    warp_ = std::move(warp);
    relocated_from_ = settled_at;
    commit(s_, nullptr);
  }
}

template <int Dim>
typename EmbeddedNeedle<Dim>::SegmentEnd EmbeddedNeedle<Dim>::segmentEnd() const {
  SegmentEnd end;
  end << s_, tip_.reference_m, cut_total_m_;
  return end;
}

template <int Dim>
bool EmbeddedNeedle<Dim>::repeatsRelocatedEnd(const SegmentEnd& end) const {
  return relocated_from_ && (end - *relocated_from_).template lpNorm<Eigen::Infinity>() <=
                                params_.event_warp_tolerance_m;
}

template <int Dim>
void EmbeddedNeedle<Dim>::restoreState(const EmbeddedNeedle& from, const Eigen::VectorXd* u) {
  const EmbeddedNeedleInfo info = info_;
  const int solves = solves_;
  const long long total = total_solves_;
  *this = from;
  info_ = info;
  solves_ = solves;
  total_solves_ = total;
  if (reference_version_ != tissue_->referenceVersion()) {
    adoptReference();
    if (u) {  // the same displacement on the new reference: u = G f + warp
      holdDisplacement(*u);
    }
  }
  commit(s_, nullptr);
}

template <int Dim>
void EmbeddedNeedle<Dim>::restoreFallback(Fallback& fallback) {
  fallback.form();
  restoreState(*fallback.state, &fallback.u);
}

template <int Dim>
bool EmbeddedNeedle<Dim>::enter(const Lateral& lateral, std::string* why_not) {
  Vector p;
  p(0) = entry_x_m_ + kEntryInset_m;
  p.template tail<Dim - 1>() = lateral;
  std::optional<Point_> entry = constraintPoint(p);
  if (!entry || tissue_->rigidElement(entry->element)) {
    if (why_not) {
      *why_not = "the needle line at " + pointText<Dim>(p) +
                 (entry ? " meets rigid tissue at the entry face" : " misses the tissue mesh");
    }
    return false;
  }
  lateral_ = lateral;
  prefetchLine(lateral);
  s_ = entry->reference_m.x();
  tip_ = *entry;
  cut_dir_ = Vector::UnitX();
  in_tissue_ = tip_active_ = true;
  punctured_ = false;
  direction_ = 1;
  commit(s_, &tip_);
  ++info_.events;
  return true;
}

template <int Dim>
bool EmbeddedNeedle<Dim>::passTo(const Lateral& lateral, double tip_x, std::string* why_not) {
  struct Transit {
    bool& flag;
    explicit Transit(bool& f) : flag(f) { flag = true; }
    ~Transit() { flag = false; }
  } transit(transit_);
  return moveTo(lateral, tip_x, why_not);
}

template <int Dim>
bool EmbeddedNeedle<Dim>::moveTo(const Lateral& lateral, double tip_x, std::string* why_not) {
  auto refuse = [&](const std::string& why) {
    if (why_not) {
      *why_not = why;
    }
    return false;
  };
  if (!lateral.allFinite() || !std::isfinite(tip_x)) {
    return refuse("non-finite lateral position or tip position");
  }
  if (in_tissue_ && (lateral - lateral_).norm() > 1e-12) {
    return refuse("the lateral position can change only outside the tissue");
  }
  if (in_tissue_ && direction_ < 0 && tip_x > s_) {
    return refuse("the needle must leave the tissue before it is inserted again");
  }
  if (linear_model_ && tissue_->corotational() && tissue_->referenceVersion() != 0) {
    return refuse("the tissue's linear model is gone: its reference stiffness was re-warped (" +
                  std::to_string(tissue_->referenceVersion()) + " refactorisations)");
  }
  info_.events = 0;
  info_.corotation_updates = 0;
  info_.rewarps = 0;
  info_.relocations = 0;
  info_.relocation_m = 0.0;
  info_.aim_iterations = 0;
  info_.stopped = false;
  warp_updates_ = 0;
  solves_ = 0;
  if (!in_tissue_) {
    if (tip_x < entry_x_m_) {
      lateral_ = lateral;
      s_ = tip_x;
      direction_ = 1;
      return true;
    }
    if (!enter(lateral, why_not)) {
      return false;
    }
  }
  if (direction_ > 0 && !punctured_ && tip_x < s_ && tip_x >= entry_x_m_) {
    tip_x = s_;  // touching the entry face: nothing to move yet
  }
  if (tip_x < s_ && direction_ > 0) {
    // The needle stops and reverses: every shaft point sticks where it is; the tip's cut ends.
    direction_ = -1;
    tip_active_ = false;
    warp_history_.clear();
    for (ShaftPoint& p : shaft_) {
      p.stuck = true;
      p.offset_m = p.world_x_m - s_;
    }
    commit(s_, nullptr);
  }
  if (const std::optional<double> to_stop = cutToStop(); to_stop && *to_stop <= kCutTol_m) {
    info_.stopped = true;  // the tip's tissue point is at the stop already
    return true;
  }
  try {
    predictWarp(tip_x);
    for (int i = 0; i < kMaxEventsPerMove; ++i) {
      if (consistentSegment(tip_x)) {
        break;
      }
    }
  } catch (const std::runtime_error& e) {
    return refuse(e.what());
  }
  info_.tip_force_N = committed_.tip_force_N;
  info_.friction_force_N = 0.0;
  info_.slipping = 0;
  for (std::size_t k = 0; k < shaft_.size(); ++k) {
    info_.friction_force_N += committed_.forces(Dim * static_cast<int>(k));
    info_.slipping += shaft_[k].stuck ? 0 : 1;
  }
  info_.shaft_points = static_cast<int>(shaft_.size());
  info_.solves = solves_;
  return true;
}

template <int Dim>
std::optional<int> EmbeddedNeedle<Dim>::implantSeed(std::string* why_not) {
  if (!in_tissue_ || !punctured_ || !tip_active_) {
    if (why_not) {
      *why_not = "the needle tip is not in tissue";
    }
    return std::nullopt;
  }
  if (warped()) {
    // The seed is the tip's tissue point of this state: its warp settled to the release
    // tolerance (the cut solved again on every update, as at a segment's end).
    Fallback before;
    before.take(*this);
    const auto kept = kept_fields_.keep([&] { before.form(); });
    try {
      while (!settleWarp(kReleaseWarpTol_m)) {
        insertSegment(s_);
      }
    } catch (const std::runtime_error& e) {
      restoreFallback(before);
      if (why_not) {
        *why_not = std::string("the state the seed is released from: ") + e.what();
      }
      return std::nullopt;
    }
  }
  seeds_.push_back(tip_.reference_m);
  return static_cast<int>(seeds_.size()) - 1;
}

template <int Dim>
int EmbeddedNeedle<Dim>::addSeed(const Vector& reference_m) {
  if (!tissue_->locate(reference_m)) {
    throw std::invalid_argument("EmbeddedNeedle::addSeed: the seed's tissue point " +
                                pointText<Dim>(reference_m) + " is outside the mesh");
  }
  seeds_.push_back(reference_m);
  return static_cast<int>(seeds_.size()) - 1;
}

template <int Dim>
const typename EmbeddedNeedle<Dim>::Vector& EmbeddedNeedle<Dim>::seedReference(int seed) const {
  return seeds_.at(static_cast<std::size_t>(seed));
}

template <int Dim>
typename EmbeddedNeedle<Dim>::Vector EmbeddedNeedle<Dim>::worldOf(const Vector& reference) const {
  const std::optional<Point_> p = tissue_->locate(reference);
  if (!p) {
    throw std::invalid_argument("EmbeddedNeedle::worldOf: the point is outside the mesh");
  }
  Vector x = reference;
  const auto& nodes = tissue_->mesh().elements[static_cast<std::size_t>(p->element)];
  for (int a = 0; a < Dim + 1; ++a) {
    x += p->weights(a) * nodeDisplacement(nodes[a], committed_.forces);
  }
  return x;
}

template <int Dim>
typename EmbeddedNeedle<Dim>::Vector EmbeddedNeedle<Dim>::seedWorld(int seed) const {
  return worldOf(seedReference(seed));
}

template <int Dim>
std::vector<typename EmbeddedNeedle<Dim>::Vector> EmbeddedNeedle<Dim>::shaftReference() const {
  std::vector<Vector> out;
  for (const ShaftPoint& p : shaft_) {
    out.push_back(p.point.reference_m);
  }
  return out;
}

template <int Dim>
Eigen::VectorXd EmbeddedNeedle<Dim>::displacementField() const {
  return displacementField(committed_.forces, warp_);
}

template <int Dim>
Eigen::VectorXd EmbeddedNeedle<Dim>::displacementField(const Eigen::VectorXd& forces,
                                                       const Eigen::VectorXd& warp) const {
  // The needle's forces act on its points' section nodes only, whose compliance columns are
  // cached: the field is their combination (CondensedCompliance::solveSupported).
  Eigen::VectorXd f = Eigen::VectorXd::Zero(Dim * tissue_->mesh().nodeCount());
  std::vector<int> support;
  std::vector<char> listed(static_cast<std::size_t>(tissue_->mesh().nodeCount()), 0);
  const int ns = static_cast<int>(shaft_.size());
  for (int k = 0; k < forces.size() / Dim; ++k) {
    const Point_& p = k < ns ? shaft_[static_cast<std::size_t>(k)].point : tip_;
    for (const NodeWeight& w : p.section) {
      f.template segment<Dim>(Dim * w.node) += w.weight * forces.template segment<Dim>(Dim * k);
      if (!listed[static_cast<std::size_t>(w.node)]) {
        listed[static_cast<std::size_t>(w.node)] = 1;
        for (int d = 0; d < Dim; ++d) {
          support.push_back(Dim * w.node + d);
        }
      }
    }
  }
  Eigen::VectorXd u = tissue_->compliance().solveSupported(f, support);
  if (warp.size() > 0) {
    u += warp;
  }
  return u;
}

template class EmbeddingTissue<2>;
template class EmbeddingTissue<3>;
template class EmbeddedNeedle<2>;
template class EmbeddedNeedle<3>;

}  // namespace needle_guidance::fem
