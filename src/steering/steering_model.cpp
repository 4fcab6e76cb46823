// Discretisation of the steerable-needle MDP (dissertation 5.4.2).
#include "needle_guidance/steering/steering_model.h"
#include "needle_guidance/math.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <thread>
#include <utility>

#include "needle_guidance/format.h"

namespace needle_guidance::steering {
namespace {

/// Bumped whenever the discretisation changes meaning, so old table files are refused.
constexpr const char* kModelVersion = "needle_guidance steering MDP v1";
/// Largest state count (flat indices and stencil offsets are 32-bit in the solver).
constexpr std::int64_t kMaxStates = std::int64_t{1} << 31;
/// Slack on grid-count floors: a 10 cm workspace at 1 mm is 100 columns, not 99.
constexpr double kCountSlack = 1e-9;

int wrap(int k, int n) {
  const int r = k % n;
  return r < 0 ? r + n : r;
}

/// Standard normal CDF.
double normalCdf(double z) {
  return 0.5 * std::erfc(-z / std::sqrt(2.0));
}

std::string num(double v) {
  return formatNumber(v, 10);
}

/// Exact-enough double segment test for collision checks of arc chords (the chords are an
/// approximation of the arc anyway): true if the closed segments share a point.
double cross(const Point2& o, const Point2& a, const Point2& b) {
  return (a.x() - o.x()) * (b.y() - o.y()) - (a.y() - o.y()) * (b.x() - o.x());
}
bool onBox(const Point2& a, const Point2& b, const Point2& p) {
  return std::min(a.x(), b.x()) <= p.x() && p.x() <= std::max(a.x(), b.x()) &&
         std::min(a.y(), b.y()) <= p.y() && p.y() <= std::max(a.y(), b.y());
}
bool segmentsTouch(const Point2& a, const Point2& b, const Point2& c, const Point2& d) {
  const double d1 = cross(a, b, c);
  const double d2 = cross(a, b, d);
  const double d3 = cross(c, d, a);
  const double d4 = cross(c, d, b);
  if (((d1 > 0 && d2 < 0) || (d1 < 0 && d2 > 0)) && ((d3 > 0 && d4 < 0) || (d3 < 0 && d4 > 0))) {
    return true;
  }
  return (d1 == 0 && onBox(a, b, c)) || (d2 == 0 && onBox(a, b, d)) ||
         (d3 == 0 && onBox(c, d, a)) || (d4 == 0 && onBox(c, d, b));
}

struct Box {
  double min_x, min_y, max_x, max_y;
  bool overlaps(const Box& o) const {
    return min_x <= o.max_x && o.min_x <= max_x && min_y <= o.max_y && o.min_y <= max_y;
  }
};

Box boxOf(const Point2& a, const Point2& b) {
  return {std::min(a.x(), b.x()), std::min(a.y(), b.y()), std::max(a.x(), b.x()),
          std::max(a.y(), b.y())};
}

class Fnv1a {
public:
  void bytes(const void* data, std::size_t n) {
    const auto* p = static_cast<const unsigned char*>(data);
    for (std::size_t i = 0; i < n; ++i) {
      h_ ^= p[i];
      h_ *= 1099511628211ull;
    }
  }
  void f64(double v) { bytes(&v, sizeof v); }
  void i64(std::int64_t v) { bytes(&v, sizeof v); }
  void str(const std::string& s) {
    i64(static_cast<std::int64_t>(s.size()));
    bytes(s.data(), s.size());
  }
  std::uint64_t value() const { return h_; }

private:
  std::uint64_t h_ = 14695981039346656037ull;
};

}  // namespace

std::string toString(TransitionModel model) {
  return model == TransitionModel::kRounded ? "rounded" : "interpolated";
}

std::optional<TransitionModel> transitionModelFromString(const std::string& text) {
  if (text == toString(TransitionModel::kRounded)) {
    return TransitionModel::kRounded;
  }
  if (text == toString(TransitionModel::kInterpolated)) {
    return TransitionModel::kInterpolated;
  }
  return std::nullopt;
}

SteeringProblem problemFromScene(const scene::Scene& scene, const std::string& target_name) {
  if (!scene.steering) {
    throw std::invalid_argument("problemFromScene: scene '" + scene.name +
                                "' has no steering section");
  }
  if (scene.targets.empty()) {
    throw std::invalid_argument("problemFromScene: scene '" + scene.name + "' has no targets");
  }
  SteeringProblem problem;
  problem.workspace_min = scene.workspace_min;
  problem.workspace_max = scene.workspace_max;
  problem.obstacles = scene.obstacles;
  problem.target = target_name.empty() ? scene.targets.front() : scene.target(target_name);
  problem.params.grid_spacing_m = scene.steering->grid_spacing_m;
  problem.params.orientations = scene.steering->orientations;
  problem.params.orientation_subdivision = scene.steering->orientation_subdivision;
  problem.params.radius_m = scene.needle.radius_of_curvature_m;
  problem.params.sigma_insert_rad = scene.steering->sigma_insert_rad;
  problem.params.sigma_flip_rad = scene.steering->sigma_flip_rad;
  const std::optional<TransitionModel> model =
      transitionModelFromString(scene.steering->transition_model);
  if (!model) {
    throw std::invalid_argument("problemFromScene: scene '" + scene.name +
                                "' steering.transition_model '" + scene.steering->transition_model +
                                "' is not rounded or interpolated");
  }
  problem.params.transition_model = *model;
  problem.ps_tolerance = scene.steering->ps_tolerance;
  return problem;
}

std::uint64_t problemHash(const SteeringProblem& problem) {
  Fnv1a h;
  h.str(kModelVersion);
  h.f64(problem.workspace_min.x());
  h.f64(problem.workspace_min.y());
  h.f64(problem.workspace_max.x());
  h.f64(problem.workspace_max.y());
  h.i64(static_cast<std::int64_t>(problem.obstacles.size()));
  for (const auto& o : problem.obstacles) {
    h.i64(static_cast<std::int64_t>(o.polygon.size()));
    for (const auto& v : o.polygon.vertices()) {
      h.f64(v.x());
      h.f64(v.y());
    }
    h.f64(o.clearance_m);
  }
  h.f64(problem.target.position.x());
  h.f64(problem.target.position.y());
  h.f64(problem.target.radius_m);
  const SteeringParams& p = problem.params;
  h.f64(p.grid_spacing_m);
  h.i64(p.orientations);
  if (p.orientation_subdivision != 1) {  // s = 1 keeps the hashes of 5.4.2 tables
    h.i64(p.orientation_subdivision);
  }
  h.f64(p.radius_m);
  h.f64(p.sigma_insert_rad);
  h.f64(p.sigma_flip_rad);
  h.f64(p.tail_mass);
  h.f64(p.arc_chord_tolerance_m);
  if (p.transition_model != TransitionModel::kRounded) {  // kRounded keeps the 5.4.2 hashes
    h.str(toString(p.transition_model));
  }
  return h.value();
}

// ---- GridSpec ----------------------------------------------------------------------------------

double GridSpec::alphaRad() const {
  return 2.0 * kPi / nc;
}

Point2 GridSpec::point(int ix, int iy) const {
  return origin + spacing_m * Point2(ix, iy);
}

void GridSpec::decode(StateId s, int& ix, int& iy, int& k, Bevel& b) const {
  k = static_cast<int>(s % nc);
  const std::int64_t rest = s / nc;
  b = static_cast<Bevel>(rest % 2);
  const std::int64_t pos = rest / 2;
  ix = static_cast<int>(pos / ny);
  iy = static_cast<int>(pos % ny);
}

StateId GridSpec::nearestState(const TipPose& pose) const {
  const double fx = (pose.p_SceneTip.x() - origin.x()) / spacing_m;
  const double fy = (pose.p_SceneTip.y() - origin.y()) / spacing_m;
  const double fk = pose.theta_rad / alphaRad();
  // The negated comparisons also reject NaN. The grid has floor(width / Delta) columns, so the
  // workspace reaches up to (but less than) one spacing beyond the last column and row: a pose
  // there belongs to the last column or row, the nearest grid point it has.
  if (!(fx >= -0.5 && fx < nx + 1.0 && fy >= -0.5 && fy < ny + 1.0 && std::abs(fk) < 1e15)) {
    return -1;
  }
  const int ix = std::min(nx - 1, static_cast<int>(std::floor(fx + 0.5)));
  const int iy = std::min(ny - 1, static_cast<int>(std::floor(fy + 0.5)));
  const std::int64_t kk = static_cast<std::int64_t>(std::floor(fk + 0.5)) % nc;
  const int k = static_cast<int>(kk < 0 ? kk + nc : kk);
  return state(ix, iy, k, pose.bevel);
}

TipPose GridSpec::pose(StateId s) const {
  int ix = 0, iy = 0, k = 0;
  Bevel b = Bevel::kLeft;
  decode(s, ix, iy, k, b);
  TipPose p;
  p.p_SceneTip = point(ix, iy);
  const double theta = k * alphaRad();
  p.theta_rad = theta > kPi + 1e-12 ? theta - 2.0 * kPi : theta;
  p.bevel = b;
  return p;
}

// ---- SteeringModel
// -------------------------------------------------------------------------------

SteeringModel::SteeringModel(SteeringProblem problem, int threads) : problem_(std::move(problem)) {
  const SteeringParams& p = problem_.params;
  const std::string where = "SteeringModel: ";
  if (p.orientations < 4 || p.orientations % 4 != 0) {
    // 5.4.2: the 180-degree rotation of a flip and the axis-aligned orientations (theta = 0,
    // +-90 degrees) must fall on control-circle points.
    throw std::invalid_argument(where + "orientations N_c = " + std::to_string(p.orientations) +
                                " is not a positive multiple of 4 (dissertation 5.4.2)");
  }
  if (p.orientation_subdivision < 1 || p.orientation_subdivision > 64) {
    throw std::invalid_argument(where + "orientation_subdivision s = " +
                                std::to_string(p.orientation_subdivision) + " is not in [1, 64]");
  }
  const int tracked = p.orientations * p.orientation_subdivision;
  if (p.orientations > 4096 || tracked > 4096) {
    throw std::invalid_argument(where + "orientations N_c = " + std::to_string(p.orientations) +
                                " times orientation_subdivision s = " +
                                std::to_string(p.orientation_subdivision) + " exceeds 4096");
  }
  if (!(p.grid_spacing_m > 0.0) || !std::isfinite(p.grid_spacing_m)) {
    throw std::invalid_argument(where + "grid_spacing_m must be finite and > 0, got " +
                                num(p.grid_spacing_m));
  }
  if (!(p.radius_m > 0.0) || !std::isfinite(p.radius_m)) {
    throw std::invalid_argument(where + "radius_m must be finite and > 0, got " + num(p.radius_m));
  }
  if (!(p.sigma_insert_rad >= 0.0) || !std::isfinite(p.sigma_insert_rad)) {
    throw std::invalid_argument(where + "sigma_insert_rad must be finite and >= 0, got " +
                                num(p.sigma_insert_rad));
  }
  if (!(p.sigma_flip_rad >= 0.0) || !std::isfinite(p.sigma_flip_rad)) {
    throw std::invalid_argument(where + "sigma_flip_rad must be finite and >= 0, got " +
                                num(p.sigma_flip_rad));
  }
  if (!(p.tail_mass > 0.0 && p.tail_mass < 1.0)) {
    throw std::invalid_argument(where + "tail_mass must be in (0, 1), got " + num(p.tail_mass));
  }
  if (!(p.arc_chord_tolerance_m > 0.0) || !std::isfinite(p.arc_chord_tolerance_m)) {
    throw std::invalid_argument(where + "arc_chord_tolerance_m must be finite and > 0, got " +
                                num(p.arc_chord_tolerance_m));
  }
  if (threads < 1) {
    throw std::invalid_argument(where + "threads must be >= 1, got " + std::to_string(threads));
  }
  const Point2 size = problem_.workspace_max - problem_.workspace_min;
  if (!problem_.workspace_min.allFinite() || !problem_.workspace_max.allFinite() ||
      !(size.x() > 0.0) || !(size.y() > 0.0)) {
    throw std::invalid_argument(
        where + "empty or non-finite workspace [" + num(problem_.workspace_min.x()) + ", " +
        num(problem_.workspace_max.x()) + "] x [" + num(problem_.workspace_min.y()) + ", " +
        num(problem_.workspace_max.y()) + "]");
  }
  const double fnx = std::floor(size.x() / p.grid_spacing_m + kCountSlack);
  const double fny = std::floor(size.y() / p.grid_spacing_m + kCountSlack);
  if (fnx < 1.0 || fny < 1.0) {
    throw std::invalid_argument(where + "workspace " + num(size.x()) + " x " + num(size.y()) +
                                " m is narrower than grid_spacing_m = " + num(p.grid_spacing_m));
  }
  if (fnx * fny * 2.0 * tracked >= static_cast<double>(kMaxStates)) {
    throw std::invalid_argument(where + "too many states (" + num(fnx * fny * 2.0 * tracked) +
                                "); the limit is 2^31");
  }
  if (!(problem_.target.radius_m >= 0.0) || !problem_.target.position.allFinite()) {
    throw std::invalid_argument(where + "target '" + problem_.target.name +
                                "' radius must be >= 0, got " + num(problem_.target.radius_m));
  }
  for (const auto& o : problem_.obstacles) {
    if (!(o.clearance_m >= 0.0) || !std::isfinite(o.clearance_m)) {
      throw std::invalid_argument(where + "obstacle '" + o.name +
                                  "' clearance_m must be finite and >= 0, got " +
                                  num(o.clearance_m));
    }
  }
  grid_.origin = problem_.workspace_min;
  grid_.spacing_m = p.grid_spacing_m;
  grid_.nx = static_cast<int>(fnx);
  grid_.ny = static_cast<int>(fny);
  grid_.nc = tracked;
  hash_ = problemHash(problem_);

  // Obstacles expanded by their clearance (Minkowski sum, 5.3); arcs of the offset within a
  // twentieth of the grid spacing.
  const double chord_error_m = std::min(1e-4, 0.05 * p.grid_spacing_m);
  for (const auto& o : problem_.obstacles) {
    expanded_.push_back(o.polygon.offset(o.clearance_m, chord_error_m).counterClockwise());
  }
  buildDeflections();
  buildStencils();
  buildCells();
  buildValidity(threads);
}

double SteeringModel::arcLength_m() const {
  return 2.0 * kPi * problem_.params.radius_m / problem_.params.orientations;
}

namespace {

/// Probabilities of the discrete deflections d alpha, d = first..first + size - 1, of beta ~
/// N(0, sigma) (5.4.2, figure 5.4): the normal integrated over bins of width alpha centred on
/// the deflections, the smallest +-m whose tails hold less than tail_mass, tails folded into the
/// end bins; when 2m + 1 > nc the normal wrapped onto all nc orientations.
std::vector<double> binProbabilities(double sigma, double alpha, int nc, double tail_mass,
                                     int& first) {
  std::vector<double> probs;
  if (sigma == 0.0) {
    first = 0;
    return {1.0};
  }
  int m = 0;
  while (std::erfc((m + 0.5) * alpha / (sigma * std::sqrt(2.0))) >= tail_mass && 2 * m + 1 <= nc) {
    ++m;
  }
  if (2 * m + 1 > nc) {
    first = -(nc / 2 - 1);
    const int wraps = static_cast<int>(std::ceil(10.0 * sigma / (2.0 * kPi))) + 1;
    double total = 0.0;
    for (int i = 0; i < nc; ++i) {
      const int d = first + i;
      double mass = 0.0;
      for (int w = -wraps; w <= wraps; ++w) {
        const double lo = ((d - 0.5) + static_cast<double>(w) * nc) * alpha / sigma;
        const double hi = ((d + 0.5) + static_cast<double>(w) * nc) * alpha / sigma;
        mass += normalCdf(hi) - normalCdf(lo);
      }
      probs.push_back(mass);
      total += mass;
    }
    for (double& q : probs) {
      q /= total;
    }
    return probs;
  }
  first = -m;
  for (int d = -m; d <= m; ++d) {
    // Tails folded into the end transitions (5.4.2, figure 5.4).
    const double lo = d == -m ? 0.0 : normalCdf((d - 0.5) * alpha / sigma);
    const double hi = d == m ? 1.0 : normalCdf((d + 0.5) * alpha / sigma);
    probs.push_back(hi - lo);
  }
  return probs;
}

/// Variance [rad^2] of the discrete deflections of binProbabilities.
double binVariance(double sigma, double alpha, int nc, double tail_mass) {
  int first = 0;
  const std::vector<double> p = binProbabilities(sigma, alpha, nc, tail_mass, first);
  double var = 0.0;
  for (std::size_t i = 0; i < p.size(); ++i) {
    const double beta = (first + static_cast<int>(i)) * alpha;
    var += p[i] * beta * beta;
  }
  return var;
}

/// sigma' whose binned deflections have variance sigma^2 (bisection; the binned variance grows
/// monotonically with sigma'). Binning at bin centres inflates the variance by about alpha^2 / 12
/// (Sheppard) for sigma > alpha / 2 and shrinks it for sigma << alpha; the needle's spread after
/// many steps is the sum of the per-step variances, so matching it removes the bias.
double varianceMatchedSigma(double sigma, double alpha, int nc, double tail_mass) {
  if (sigma == 0.0 || (2.0 * sigma > kPi / 2.0)) {
    return sigma;  // no deflection, or wide enough to wrap: no matching
  }
  const double target = sigma * sigma;
  double lo = 0.0, hi = 2.0 * sigma;
  while (binVariance(hi, alpha, nc, tail_mass) < target) {
    hi *= 2.0;
  }
  for (int i = 0; i < 60; ++i) {
    const double mid = 0.5 * (lo + hi);
    (binVariance(mid, alpha, nc, tail_mass) < target ? lo : hi) = mid;
  }
  return 0.5 * (lo + hi);
}

}  // namespace

void SteeringModel::buildDeflections() {
  const int nc = grid_.nc;
  const double alpha = grid_.alphaRad();
  const double sigmas[2] = {problem_.params.sigma_insert_rad, problem_.params.sigma_flip_rad};
  const bool matched = problem_.params.transition_model == TransitionModel::kInterpolated;
  for (int u = 0; u < 2; ++u) {
    bin_sigma_[u] =
        matched ? varianceMatchedSigma(sigmas[u], alpha, nc, problem_.params.tail_mass) : sigmas[u];
    deflection_p_[u] =
        binProbabilities(bin_sigma_[u], alpha, nc, problem_.params.tail_mass, first_d_[u]);
    std::vector<double>& p = deflection_p_[u];
    if (matched && p.size() >= 3 && static_cast<int>(p.size()) < nc) {
      // The binned variance jumps where the tail cut m grows, so bisection stops just below
      // sigma^2: move the remainder from the centre bin to the two end bins (+-m alpha).
      double var = 0.0;
      for (std::size_t i = 0; i < p.size(); ++i) {
        const double beta = (first_d_[u] + static_cast<int>(i)) * alpha;
        var += p[i] * beta * beta;
      }
      const double m_alpha = -first_d_[u] * alpha;
      const double eps = (sigmas[u] * sigmas[u] - var) / (2.0 * m_alpha * m_alpha);
      const std::size_t centre = p.size() / 2;
      if (eps > 0.0 && 2.0 * eps < p[centre]) {
        p.front() += eps;
        p.back() += eps;
        p[centre] -= 2.0 * eps;
      }
    }
  }
}

template <typename AddBin>
void SteeringModel::fillStencils(int entries_per_bin, AddBin&& add) {
  const int nc = grid_.nc;
  const int s = problem_.params.orientation_subdivision;
  stencil_.clear();
  stencil_start_.assign(static_cast<std::size_t>(4 * nc + 1), 0);
  max_transitions_ = 0;
  max_row_reach_ = 0;
  for (int k = 0; k < nc; ++k) {
    for (int b = 0; b < 2; ++b) {
      for (int u = 0; u < 2; ++u) {
        const std::size_t slot = stencilSlot(k, static_cast<Bevel>(b), static_cast<Control>(u));
        stencil_start_[slot] = stencil_.size();
        const int traced = u == 0 ? b : 1 - b;  // insert keeps the bevel, flip turns it
        const auto& probs = deflection_p_[u];
        for (std::size_t i = 0; i < probs.size(); ++i) {
          const int o = wrap(k + first_d_[u] + static_cast<int>(i), nc);
          const int o_next = wrap(traced == 0 ? o + s : o - s, nc);
          add(k, b, traced, traced * nc + o, o_next, probs[i]);
        }
        max_transitions_ =
            std::max(max_transitions_, entries_per_bin * static_cast<int>(probs.size()));
      }
    }
  }
  stencil_start_.back() = stencil_.size();
}

void SteeringModel::buildStencils() {
  if (problem_.params.transition_model == TransitionModel::kInterpolated) {
    buildInterpolatedStencils();
    return;
  }
  const int nc = grid_.nc;
  const double r_cells = problem_.params.radius_m / grid_.spacing_m;
  const double alpha = grid_.alphaRad();
  const int s = problem_.params.orientation_subdivision;  // one arc turns s orientation steps
  // Rounded control-circle points of the bevel-left circle (figure 5.3): the point whose
  // counter-clockwise tangent is theta_m = m alpha lies at r (sin theta_m, -cos theta_m) from the
  // centre. The bevel-right circle is its 180-degree rotation, so its rounded points are the
  // negated ones (std::lround rounds halves away from zero, symmetrically).
  std::vector<int> rx(static_cast<std::size_t>(nc)), ry(static_cast<std::size_t>(nc));
  for (int m = 0; m < nc; ++m) {
    rx[static_cast<std::size_t>(m)] = static_cast<int>(std::lround(r_cells * std::sin(m * alpha)));
    ry[static_cast<std::size_t>(m)] = static_cast<int>(std::lround(-r_cells * std::cos(m * alpha)));
  }
  disp_x_.assign(static_cast<std::size_t>(2 * nc), 0);
  disp_y_.assign(static_cast<std::size_t>(2 * nc), 0);
  for (int o = 0; o < nc; ++o) {
    const auto so = static_cast<std::size_t>(o);
    const auto next = static_cast<std::size_t>(wrap(o + s, nc));
    const auto prev = static_cast<std::size_t>(wrap(o - s, nc));
    disp_x_[so] = rx[next] - rx[so];  // left: o -> o + s
    disp_y_[so] = ry[next] - ry[so];
    disp_x_[so + static_cast<std::size_t>(nc)] = rx[so] - rx[prev];  // right: o -> o - s
    disp_y_[so + static_cast<std::size_t>(nc)] = ry[so] - ry[prev];
  }
  const std::int64_t ny = grid_.ny;
  fillStencils(1, [&](int k, int b, int traced, int arc, int o_next, double p) {
    const std::int64_t dx = disp_x_[static_cast<std::size_t>(arc)];
    const std::int64_t dy = disp_y_[static_cast<std::size_t>(arc)];
    StencilEntry e;
    e.offset =
        static_cast<std::int32_t>((dx * ny + dy) * 2 * nc + (traced * nc + o_next) - (b * nc + k));
    e.probability = static_cast<float>(p);
    e.arc = static_cast<std::uint16_t>(arc);
    e.dy = static_cast<std::int16_t>(dy);
    e.dpos = static_cast<std::int32_t>(dx * ny + dy);
    stencil_.push_back(e);
    max_row_reach_ = std::max(max_row_reach_, static_cast<int>(std::abs(dy)));
  });
}

void SteeringModel::buildInterpolatedStencils() {
  const int nc = grid_.nc;
  const double alpha = grid_.alphaRad();
  // The exact end point of each arc from the origin, in grid steps: floor in disp_x_ / disp_y_,
  // the fraction in frac_x_ / frac_y_ (bilinear weights of the cell's four corners).
  disp_x_.assign(static_cast<std::size_t>(2 * nc), 0);
  disp_y_.assign(static_cast<std::size_t>(2 * nc), 0);
  frac_x_.assign(static_cast<std::size_t>(2 * nc), 0.0);
  frac_y_.assign(static_cast<std::size_t>(2 * nc), 0.0);
  for (int a = 0; a < 2 * nc; ++a) {
    TipPose start;
    start.theta_rad = (a % nc) * alpha;
    start.bevel = a < nc ? Bevel::kLeft : Bevel::kRight;
    const Point2 end =
        advanceTip(start, Control::kInsert, 0.0, arcLength_m(), problem_.params.radius_m)
            .p_SceneTip /
        grid_.spacing_m;
    const auto sa = static_cast<std::size_t>(a);
    disp_x_[sa] = static_cast<int>(std::floor(end.x()));
    disp_y_[sa] = static_cast<int>(std::floor(end.y()));
    frac_x_[sa] = end.x() - disp_x_[sa];
    frac_y_[sa] = end.y() - disp_y_[sa];
  }
  const std::int64_t ny = grid_.ny;
  fillStencils(4, [&](int k, int b, int traced, int arc, int o_next, double p) {
    const auto sa = static_cast<std::size_t>(arc);
    for (int corner = 0; corner < 4; ++corner) {
      const int cx = corner & 1, cy = corner >> 1;
      const double w =
          (cx ? frac_x_[sa] : 1.0 - frac_x_[sa]) * (cy ? frac_y_[sa] : 1.0 - frac_y_[sa]);
      const std::int64_t dx = disp_x_[sa] + cx;
      const std::int64_t dy = disp_y_[sa] + cy;
      StencilEntry e;
      e.offset = static_cast<std::int32_t>((dx * ny + dy) * 2 * nc + (traced * nc + o_next) -
                                           (b * nc + k));
      e.probability = static_cast<float>(p * w);
      e.arc = static_cast<std::uint16_t>(arc);
      e.dy = static_cast<std::int16_t>(dy);
      e.corner = static_cast<std::uint8_t>(corner);
      e.dpos = static_cast<std::int32_t>(dx * ny + dy);
      stencil_.push_back(e);
      max_row_reach_ = std::max(max_row_reach_, static_cast<int>(std::abs(dy)));
    }
  });
}

void SteeringModel::buildCells() {
  cells_.assign(static_cast<std::size_t>(grid_.numPositions()),
                static_cast<std::uint8_t>(Cell::kFree));
  std::vector<Point2> lo, hi;
  for (const auto& poly : expanded_) {
    lo.push_back(poly.minCorner());
    hi.push_back(poly.maxCorner());
  }
  const scene::Target& t = problem_.target;
  target_cells_ = 0;
  std::int64_t obstacle_target_cells = 0;
  for (int ix = 0; ix < grid_.nx; ++ix) {
    for (int iy = 0; iy < grid_.ny; ++iy) {
      const Point2 q = grid_.point(ix, iy);
      bool in_obstacle = false;
      for (std::size_t i = 0; i < expanded_.size() && !in_obstacle; ++i) {
        in_obstacle = q.x() >= lo[i].x() && q.x() <= hi[i].x() && q.y() >= lo[i].y() &&
                      q.y() <= hi[i].y() && expanded_[i].contains(q);
      }
      const bool in_target = (q - t.position).norm() <= t.radius_m;
      Cell c = Cell::kFree;
      if (in_obstacle) {
        c = Cell::kObstacle;
        obstacle_target_cells += in_target ? 1 : 0;
      } else if (in_target) {
        c = Cell::kTarget;
        ++target_cells_;
      }
      cells_[static_cast<std::size_t>(grid_.position(ix, iy))] = static_cast<std::uint8_t>(c);
    }
  }
  if (target_cells_ == 0) {
    std::string why = "no grid point lies inside it";
    if (obstacle_target_cells > 0) {
      why = "all " + std::to_string(obstacle_target_cells) +
            " of its grid points lie inside expanded obstacles";
    }
    diagnostics_.push_back("SteeringModel: target '" + t.name + "' (centre (" +
                           num(t.position.x()) + ", " + num(t.position.y()) + ") m, radius " +
                           num(t.radius_m) + " m) is unreachable: " + why + "; P_s = 0 everywhere");
  }
}

std::uint8_t SteeringModel::endMask(int ix, int iy, int arc) const {
  const auto sa = static_cast<std::size_t>(arc);
  std::uint8_t em = 0;
  for (int corner = 0; corner < 4; ++corner) {
    const int ex = ix + disp_x_[sa] + (corner & 1);
    const int ey = iy + disp_y_[sa] + (corner >> 1);
    if (ex >= 0 && ex < grid_.nx && ey >= 0 && ey < grid_.ny &&
        cells_[static_cast<std::size_t>(grid_.position(ex, ey))] ==
            static_cast<std::uint8_t>(Cell::kFree)) {
      em |= static_cast<std::uint8_t>(1u << corner);
    }
  }
  const Point2 end = grid_.point(ix, iy) +
                     grid_.spacing_m * Point2(disp_x_[sa] + frac_x_[sa], disp_y_[sa] + frac_y_[sa]);
  if ((end - problem_.target.position).norm() <= problem_.target.radius_m) {
    em |= kEndInTarget;
  }
  return em;
}

/// Every arc (bevel * nc + orientation) from the origin as a polyline whose chords lie within
/// arc_chord_tolerance_m of the true arc, with its bounding box; returns the farthest distance
/// any arc point gets from the start [m].
static double arcPolylines(const SteeringParams& params, double alpha, int nc, double arc_length_m,
                           std::vector<std::vector<Point2>>& arc_points,
                           std::vector<Box>& arc_box) {
  const double r = params.radius_m;
  const double max_step = 2.0 * std::acos(std::max(-1.0, 1.0 - params.arc_chord_tolerance_m / r));
  const double turn = arc_length_m / r;  // one arc turns 2 pi / N_c
  const int segments = std::max(1, static_cast<int>(std::ceil(turn / max_step)));
  const int n_arcs = 2 * nc;
  arc_points.assign(static_cast<std::size_t>(n_arcs), {});
  arc_box.assign(static_cast<std::size_t>(n_arcs), Box{0, 0, 0, 0});
  double reach = 0.0;
  for (int a = 0; a < n_arcs; ++a) {
    TipPose start;
    start.theta_rad = (a % nc) * alpha;
    start.bevel = a < nc ? Bevel::kLeft : Bevel::kRight;
    auto& pts = arc_points[static_cast<std::size_t>(a)];
    Box box{0, 0, 0, 0};
    for (int i = 0; i <= segments; ++i) {
      const Point2 p =
          i == 0
              ? Point2(0, 0)
              : advanceTip(start, Control::kInsert, 0.0, arc_length_m * i / segments, r).p_SceneTip;
      pts.push_back(p);
      box = {std::min(box.min_x, p.x()), std::min(box.min_y, p.y()), std::max(box.max_x, p.x()),
             std::max(box.max_y, p.y())};
      reach = std::max(reach, p.norm());
    }
    arc_box[static_cast<std::size_t>(a)] = box;
  }
  return reach;
}

void SteeringModel::buildValidity(int threads) {
  const int nc = grid_.nc;
  const int n_arcs = 2 * nc;
  words_ = (n_arcs + 63) / 64;
  const std::int64_t n_pos = grid_.numPositions();
  valid_.assign(static_cast<std::size_t>(n_pos * words_), 0);
  all_valid_.assign(static_cast<std::size_t>(n_pos), 0);
  const bool interpolated = problem_.params.transition_model == TransitionModel::kInterpolated;
  if (interpolated) {
    end_mask_.assign(static_cast<std::size_t>(n_pos * n_arcs), 0);
  }

  // Each arc as a polyline relative to its start point (the same at every position).
  std::vector<std::vector<Point2>> arc_points;
  std::vector<Box> arc_box;
  const double reach =
      arcPolylines(problem_.params, grid_.alphaRad(), nc, arcLength_m(), arc_points,
                   arc_box);  // farthest any arc point gets from the start [m]

  // Expanded-obstacle edges, binned on a uniform grid of cell size `reach` so each position
  // looks at the bins within reach only.
  std::vector<Point2> ea, eb;
  std::vector<Box> ebox;
  for (const auto& poly : expanded_) {
    for (std::size_t i = 0; i < poly.size(); ++i) {
      const auto e = poly.edge(i);
      ea.push_back(e.a);
      eb.push_back(e.b);
      ebox.push_back(boxOf(e.a, e.b));
    }
  }
  const Point2 wmin = problem_.workspace_min;
  const Point2 wmax = problem_.workspace_max;
  const double bin = std::max(reach, grid_.spacing_m);
  const int bx = std::max(1, static_cast<int>(std::ceil((wmax.x() - wmin.x()) / bin)));
  const int by = std::max(1, static_cast<int>(std::ceil((wmax.y() - wmin.y()) / bin)));
  std::vector<std::vector<int>> bins(static_cast<std::size_t>(bx * by));
  auto bin_x = [&](double x) {
    return std::clamp(static_cast<int>(std::floor((x - wmin.x()) / bin)), 0, bx - 1);
  };
  auto bin_y = [&](double y) {
    return std::clamp(static_cast<int>(std::floor((y - wmin.y()) / bin)), 0, by - 1);
  };
  for (std::size_t e = 0; e < ea.size(); ++e) {
    for (int i = bin_x(ebox[e].min_x); i <= bin_x(ebox[e].max_x); ++i) {
      for (int j = bin_y(ebox[e].min_y); j <= bin_y(ebox[e].max_y); ++j) {
        bins[static_cast<std::size_t>(i * by + j)].push_back(static_cast<int>(e));
      }
    }
  }
  const double slack = 1e-9 * std::max(1.0, (wmax - wmin).norm());

  auto work = [&](int ix_begin, int ix_end) {
    std::vector<int> stamp(ea.size(), -1);
    std::vector<int> near;
    for (int ix = ix_begin; ix < ix_end; ++ix) {
      for (int iy = 0; iy < grid_.ny; ++iy) {
        const std::int64_t pos = grid_.position(ix, iy);
        if (cells_[static_cast<std::size_t>(pos)] != static_cast<std::uint8_t>(Cell::kFree)) {
          continue;  // absorbing: no transitions
        }
        const Point2 q = grid_.point(ix, iy);
        const int stamp_id = static_cast<int>(pos % std::numeric_limits<int>::max());
        near.clear();
        for (int i = bin_x(q.x() - reach); i <= bin_x(q.x() + reach); ++i) {
          for (int j = bin_y(q.y() - reach); j <= bin_y(q.y() + reach); ++j) {
            for (int e : bins[static_cast<std::size_t>(i * by + j)]) {
              if (stamp[static_cast<std::size_t>(e)] == stamp_id) {
                continue;
              }
              stamp[static_cast<std::size_t>(e)] = stamp_id;
              if (geometry::pointSegmentDistance(q, ea[static_cast<std::size_t>(e)],
                                                 eb[static_cast<std::size_t>(e)]) <=
                  reach + slack) {
                near.push_back(e);
              }
            }
          }
        }
        std::uint64_t* mask = valid_.data() + pos * words_;
        bool all = true;
        for (int a = 0; a < n_arcs; ++a) {
          const auto sa = static_cast<std::size_t>(a);
          const int ex = ix + disp_x_[sa];
          const int ey = iy + disp_y_[sa];
          const Box& ab = arc_box[sa];
          bool ok = (interpolated || (ex >= 0 && ex < grid_.nx && ey >= 0 && ey < grid_.ny)) &&
                    q.x() + ab.min_x >= wmin.x() - slack && q.x() + ab.max_x <= wmax.x() + slack &&
                    q.y() + ab.min_y >= wmin.y() - slack && q.y() + ab.max_y <= wmax.y() + slack;
          if (ok && !near.empty()) {
            const Box moved{q.x() + ab.min_x, q.y() + ab.min_y, q.x() + ab.max_x, q.y() + ab.max_y};
            const auto& pts = arc_points[sa];
            for (int e : near) {
              const auto se = static_cast<std::size_t>(e);
              if (!moved.overlaps(ebox[se])) {
                continue;
              }
              for (std::size_t i = 0; i + 1 < pts.size() && ok; ++i) {
                ok = !segmentsTouch(q + pts[i], q + pts[i + 1], ea[se], eb[se]);
              }
              if (!ok) {
                break;
              }
            }
          }
          if (interpolated) {
            const std::uint8_t em = ok ? endMask(ix, iy, a) : 0;
            end_mask_[static_cast<std::size_t>(pos * n_arcs + a)] = em;
            ok = em != 0;
            all = all && em == 15;
          }
          if (ok) {
            mask[a / 64] |= std::uint64_t{1} << (a % 64);
          } else {
            all = false;
          }
        }
        all_valid_[static_cast<std::size_t>(pos)] = all ? 1 : 0;
      }
    }
  };
  const int n_threads = std::max(1, std::min(threads, grid_.nx));
  if (n_threads == 1) {
    work(0, grid_.nx);
  } else {
    std::vector<std::thread> pool;
    for (int t = 0; t < n_threads; ++t) {
      pool.emplace_back(work, grid_.nx * t / n_threads, grid_.nx * (t + 1) / n_threads);
    }
    for (auto& th : pool) {
      th.join();
    }
  }
}

std::vector<std::vector<Transition>> SteeringModel::successorGroups(StateId s,
                                                                    Control control) const {
  if (s < 0 || s >= numStates()) {
    throw std::out_of_range("SteeringModel::successors: state " + std::to_string(s) +
                            " not in [0, " + std::to_string(numStates()) + ")");
  }
  int ix = 0, iy = 0, k = 0;
  Bevel b = Bevel::kLeft;
  grid_.decode(s, ix, iy, k, b);
  const std::int64_t pos = grid_.position(ix, iy);
  if (cell(pos) != Cell::kFree) {
    return {{{s, 1.0}}};
  }
  const bool interpolated = transitionModel() == TransitionModel::kInterpolated;
  const std::size_t per = interpolated ? 4 : 1;
  const StencilEntry* begin = stencilBegin(k, b, control);
  const std::vector<double>& probs = deflection_p_[static_cast<int>(control)];
  std::vector<std::vector<Transition>> out;
  for (std::size_t i = 0; i < probs.size(); ++i) {
    const StencilEntry* e = begin + i * per;
    const double p = probs[i];
    if (!arcValid(pos, e->arc)) {
      out.push_back({{kFailState, p}});
      continue;
    }
    if (!interpolated) {
      out.push_back({{s + e->offset, p}});
      continue;
    }
    const std::uint8_t em = endMask(pos, e->arc);
    if (em & kEndInTarget) {
      out.push_back({{kSuccessState, p}});
      continue;
    }
    double kept = 0.0;
    for (std::size_t c = 0; c < 4; ++c) {
      kept += (em >> e[c].corner) & 1u ? double(e[c].probability) : 0.0;
    }
    std::vector<Transition> group;
    for (std::size_t c = 0; c < 4; ++c) {
      if (((em >> e[c].corner) & 1u) && e[c].probability > 0.0f) {
        group.push_back({s + e[c].offset, p * double(e[c].probability) / kept});
      }
    }
    out.push_back(std::move(group));
  }
  return out;
}

std::vector<Transition> SteeringModel::successors(StateId s, Control control) const {
  std::vector<Transition> out;
  for (auto& group : successorGroups(s, control)) {
    out.insert(out.end(), group.begin(), group.end());
  }
  return out;
}

}  // namespace needle_guidance::steering
