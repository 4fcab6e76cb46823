// Deformable registration with tissue-parameter estimation (dissertation 3.2, 3.3.2-3.3.3).
//
// Variables. The optimisers work in scaled variables theta = (s, g): s_c = ln(E_c / 1 Pa) for
// every soft class except the reference class (its modulus is fixed: only ratios are
// identifiable when all boundary conditions are displacements, see the header), and
// g = f / F0 for the force DOFs of set L, F0 = E_ref x 1 mm x 1 m (the force that moves tissue
// of the reference modulus by about 1 mm; forces are per metre of slice thickness). The box
// [Y_min, Y_max] of 3.2.4 is the box [ln Y_min, ln Y_max] in s; moduli at a bound are set to the
// bound exactly.
//
// kSteepestDescent (3.2.4): steepest ascent of Q with Armijo's rule: candidates
// theta + 2^t lambda grad Q for integer t from 0 upward while Q keeps improving (the largest
// improving t is taken), or downward until Q improves; stop when |grad Q| < epsilon. The
// gradient is by central finite differences: the s components by re-solving the FEM, the g
// components through the force Green's functions of the current factorisation (u is linear in
// g, so this equals re-solving).
//
// kFast: projected Levenberg-Marquardt on a smooth residual: signed distances of the deformed
// probe-out prostate boundary nodes to the probe-in outline and of the probe-in outline's
// vertices to the deformed boundary (arc-length weighted, both directions), plus the energy
// penalty mu * (W_f - W_0) / W_0 (the quadratic counterpart of E). The Jacobian is analytic:
// du/dg from the Green's functions, du/ds_c = -K_ff^-1 (E_c K_c u). Q is evaluated at every
// accepted iterate and the iterate with the highest Q is returned.
#include "needle_guidance/registration/deformable_registration.h"

#include <Eigen/Cholesky>
#include <Eigen/Dense>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <exception>
#include <limits>
#include <map>
#include <sstream>
#include <stdexcept>

#include "slice_model.h"

namespace needle_guidance::registration {

const char* toString(RegistrationStatus status) {
  switch (status) {
    case RegistrationStatus::kConverged:
      return "converged";
    case RegistrationStatus::kConvergedAtBound:
      return "converged_at_bound";
    case RegistrationStatus::kAlreadyAligned:
      return "already_aligned";
    case RegistrationStatus::kMaxIterations:
      return "max_iterations";
    case RegistrationStatus::kInvalidSegmentation:
      return "invalid_segmentation";
    case RegistrationStatus::kProbeDoesNotEncloseRectum:
      return "probe_does_not_enclose_rectum";
    case RegistrationStatus::kMeshingFailed:
      return "meshing_failed";
    case RegistrationStatus::kSolveFailed:
      return "solve_failed";
    case RegistrationStatus::kUnavailable:
      return "unavailable";
  }
  return "unknown";
}

bool hasMapping(RegistrationStatus status) {
  return status == RegistrationStatus::kConverged ||
         status == RegistrationStatus::kConvergedAtBound ||
         status == RegistrationStatus::kAlreadyAligned ||
         status == RegistrationStatus::kMaxIterations;
}

const char* softClassName(int soft_class) {
  switch (soft_class) {
    case kSurrounding:
      return "surrounding";
    case kCentralGland:
      return "cg";
    case kPeripheralZone:
      return "pz";
    default:
      return "unknown";
  }
}

std::optional<Point2> RegistrationResult::forward(const Point2& probe_out_m) const {
  return mapping ? mapping->forward(probe_out_m) : std::nullopt;
}

std::optional<Point2> RegistrationResult::inverse(const Point2& probe_in_m) const {
  return mapping ? mapping->inverse(probe_in_m) : std::nullopt;
}

std::optional<Point2> projectOntoProbe(const Point2& rectum_centre, const Point2& wall_point,
                                       const Polygon& probe) {
  const Point2 d = wall_point - rectum_centre;
  if (!(d.squaredNorm() > 0.0))
    return std::nullopt;
  double best_t = std::numeric_limits<double>::infinity();
  for (std::size_t i = 0; i < probe.size(); ++i) {
    const geometry::Segment e = probe.edge(i);
    const Point2 s = e.b - e.a;
    const double denom = d.x() * s.y() - d.y() * s.x();
    if (std::abs(denom) < 1e-300)
      continue;
    const Point2 ac = e.a - rectum_centre;
    const double t = (ac.x() * s.y() - ac.y() * s.x()) / denom;
    const double u = (ac.x() * d.y() - ac.y() * d.x()) / denom;
    if (t > 1e-12 && u >= -1e-12 && u <= 1.0 + 1e-12)
      best_t = std::min(best_t, t);
  }
  if (!std::isfinite(best_t))
    return std::nullopt;
  return Point2(rectum_centre + best_t * d);
}

Loops prostateLoops(const SliceSegmentation& probe_out) {
  // Union of CG and PZ: directed edges of both (counter-clockwise) minus shared edges.
  std::vector<std::pair<Point2, Point2>> edges;
  for (const Polygon* p : {&probe_out.cg.outer, &probe_out.pz.outer}) {
    if (p->size() < 3)
      continue;
    const Polygon ccw = p->counterClockwise();
    for (std::size_t i = 0; i < ccw.size(); ++i)
      edges.emplace_back(ccw.vertices()[i], ccw.vertices()[(i + 1) % ccw.size()]);
  }
  const auto key = [](const Point2& p) { return std::make_pair(p.x(), p.y()); };
  std::map<std::pair<double, double>, std::vector<std::size_t>> from;
  std::vector<bool> removed(edges.size(), false);
  for (std::size_t i = 0; i < edges.size(); ++i)
    from[key(edges[i].first)].push_back(i);
  for (std::size_t i = 0; i < edges.size(); ++i) {
    if (removed[i])
      continue;
    const auto it = from.find(key(edges[i].second));
    if (it == from.end())
      continue;
    for (std::size_t j : it->second) {
      if (!removed[j] && key(edges[j].second) == key(edges[i].first)) {
        removed[i] = removed[j] = true;
        break;
      }
    }
  }
  Loops loops;
  std::vector<bool> used(removed);
  for (std::size_t i = 0; i < edges.size(); ++i) {
    if (used[i])
      continue;
    std::vector<Point2> loop;
    std::size_t e = i;
    while (!used[e]) {
      used[e] = true;
      loop.push_back(edges[e].first);
      std::size_t next = edges.size();
      const auto it = from.find(key(edges[e].second));
      if (it != from.end()) {
        for (std::size_t j : it->second) {
          if (!used[j]) {
            next = j;
            break;
          }
        }
      }
      if (next == edges.size())
        break;
      e = next;
    }
    if (loop.size() >= 3)
      loops.push_back(std::move(loop));
  }
  return loops;
}

namespace {

using detail::Moduli;
using detail::SliceModel;
using detail::SliceSolver;
using Clock = std::chrono::steady_clock;

constexpr double kAlignedDiceTol = 1e-9;  // Dice within this of 1 counts as already aligned

double secondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

/// Signed distance from p to the loops' boundary (positive outside), its gradient in p, and
/// the nearest edge (loop, edge index, parameter along the edge).
struct SignedDistance {
  double d = 0.0;
  Point2 grad = Point2::Zero();
  std::size_t loop = 0, edge = 0;
  double t = 0.0;
};

int windingNumber(const Loops& region, const Point2& p) {
  int w = 0;
  for (const auto& loop : region) {
    const std::size_t n = loop.size();
    for (std::size_t i = 0; i < n; ++i) {
      const Point2& a = loop[i];
      const Point2& b = loop[(i + 1) % n];
      const double c = (b.x() - a.x()) * (p.y() - a.y()) - (b.y() - a.y()) * (p.x() - a.x());
      if (a.y() <= p.y()) {
        if (b.y() > p.y() && c > 0.0)
          ++w;
      } else if (b.y() <= p.y() && c < 0.0) {
        --w;
      }
    }
  }
  return w;
}

SignedDistance signedDistance(const Loops& region, const Point2& p) {
  SignedDistance best;
  double best_d2 = std::numeric_limits<double>::infinity();
  for (std::size_t l = 0; l < region.size(); ++l) {
    const auto& loop = region[l];
    const std::size_t n = loop.size();
    for (std::size_t i = 0; i < n; ++i) {
      const Point2& a = loop[i];
      const Point2 ab = loop[(i + 1) % n] - a;
      const double len2 = ab.squaredNorm();
      const double t = len2 > 0.0 ? std::clamp((p - a).dot(ab) / len2, 0.0, 1.0) : 0.0;
      const double d2 = (a + t * ab - p).squaredNorm();
      if (d2 < best_d2) {
        best_d2 = d2;
        best.loop = l;
        best.edge = i;
        best.t = t;
      }
    }
  }
  if (!std::isfinite(best_d2))
    return best;
  const bool inside = windingNumber(region, p) != 0;
  const auto& loop = region[best.loop];
  const Point2& a = loop[best.edge];
  const Point2 ab = loop[(best.edge + 1) % loop.size()] - a;
  const Point2 c = a + best.t * ab;
  const double dist = std::sqrt(best_d2);
  best.d = inside ? -dist : dist;
  if (dist > 1e-12) {
    best.grad = (p - c) / best.d;  // unit, pointing towards increasing signed distance
  } else {
    best.grad = Point2(ab.y(), -ab.x()).normalized();  // outward normal (region on the left)
  }
  return best;
}

/// Arc-length weights sqrt(l_i / L) of the vertices of loops (half the adjacent edge lengths).
std::vector<double> arcWeights(const Loops& loops) {
  std::vector<double> w;
  double total = 0.0;
  for (const auto& loop : loops) {
    const std::size_t n = loop.size();
    for (std::size_t i = 0; i < n; ++i) {
      const double l =
          0.5 * ((loop[(i + 1) % n] - loop[i]).norm() + (loop[i] - loop[(i + n - 1) % n]).norm());
      w.push_back(l);
      total += l;
    }
  }
  for (double& x : w)
    x = total > 0.0 ? std::sqrt(x / total) : 0.0;
  return w;
}

/// One evaluation of the model at theta.
struct Evaluation {
  bool ok = false;
  Eigen::VectorXd u;     // all DOFs [m]
  double w0 = 0.0;       // strain energy without forces [J/m]
  double delta_w = 0.0;  // extra strain energy due to the forces [J/m]
  double energy_share = 0.0;
  double dice = 0.0;
  double q = 0.0;
};

class Problem {
public:
  Problem(const SliceModel& model, const std::vector<Point2>& rectum_displacement,
          std::vector<int> force_nodes, const Loops& target, const RegistrationOptions& options)
      : model_(model),
        solver_(model, rectum_displacement, std::move(force_nodes)),
        target_(target),
        target_weights_(arcWeights(target)),
        options_(options) {
    for (int c = 0; c < kSoftClassCount; ++c) {
      if (c != options.reference_class)
        free_classes_.push_back(c);
    }
    log_min_ = std::log(options.min_modulus_Pa);
    log_max_ = std::log(options.max_modulus_Pa);
    force_scale_N_ =
        options.initial_modulus_Pa[static_cast<std::size_t>(options.reference_class)] * 1e-3;
    Loops reference_loops;
    for (const auto& loop : model.prostate_loops) {
      std::vector<Point2> pts;
      for (int node : loop)
        pts.push_back(model.mesh.nodes[static_cast<std::size_t>(node)]);
      reference_loops.push_back(std::move(pts));
    }
    loop_weights_ = arcWeights(reference_loops);
  }

  int freeClassCount() const { return static_cast<int>(free_classes_.size()); }
  int forceCount() const { return solver_.forceDofCount(); }
  int size() const { return freeClassCount() + forceCount(); }
  SliceSolver& solver() { return solver_; }
  int evaluations() const { return evaluations_; }
  double forceScale() const { return force_scale_N_; }
  const std::vector<int>& freeClasses() const { return free_classes_; }
  double logMin() const { return log_min_; }
  double logMax() const { return log_max_; }

  Eigen::VectorXd initialTheta() const {
    Eigen::VectorXd theta = Eigen::VectorXd::Zero(size());
    for (int i = 0; i < freeClassCount(); ++i) {
      theta(i) = std::clamp(std::log(options_.initial_modulus_Pa[static_cast<std::size_t>(
                                free_classes_[static_cast<std::size_t>(i)])]),
                            log_min_, log_max_);
    }
    return theta;
  }

  void project(Eigen::VectorXd& theta) const {
    for (int i = 0; i < freeClassCount(); ++i)
      theta(i) = std::clamp(theta(i), log_min_, log_max_);
  }

  bool atBound(const Eigen::VectorXd& theta, int i) const {
    return theta(i) <= log_min_ || theta(i) >= log_max_;
  }

  /// Moduli of theta; a modulus at its bound is the bound exactly.
  Moduli moduli(const Eigen::VectorXd& theta) const {
    Moduli m = options_.initial_modulus_Pa;
    for (int i = 0; i < freeClassCount(); ++i) {
      const auto c = static_cast<std::size_t>(free_classes_[static_cast<std::size_t>(i)]);
      double e = theta(i) == std::log(options_.initial_modulus_Pa[c])
                     ? options_.initial_modulus_Pa[c]
                     : std::exp(theta(i));
      if (theta(i) <= log_min_)
        e = options_.min_modulus_Pa;
      if (theta(i) >= log_max_)
        e = options_.max_modulus_Pa;
      m[c] = e;
    }
    return m;
  }

  Eigen::VectorXd forcesN(const Eigen::VectorXd& theta) const {
    return force_scale_N_ * theta.tail(forceCount());
  }

  /// Two solves (3.2.4): without and with the external forces.
  Evaluation evaluate(const Eigen::VectorXd& theta, bool with_dice = true) {
    ++evaluations_;
    Evaluation ev;
    if (!solver_.setModuli(moduli(theta)))
      return ev;
    const Eigen::VectorXd& u0 = solver_.u0();
    ev.w0 = solver_.strainEnergy(u0);
    ev.u = u0;
    if (forceCount() > 0) {
      const Eigen::VectorXd f = forcesN(theta);
      const Eigen::VectorXd w = solver_.forceResponse(f);
      ev.u += w;
      double fw = 0.0;
      for (int k = 0; k < forceCount(); ++k)
        fw += f(k) * w(solver_.forceDofs()[static_cast<std::size_t>(k)]);
      ev.delta_w = 0.5 * fw;  // cross term vanishes: K u0 = 0 on free DOFs, w = 0 on prescribed
    }
    ev.ok = ev.u.allFinite();
    if (!ev.ok)
      return ev;
    finishEvaluation(ev, with_dice);
    return ev;
  }

  void finishEvaluation(Evaluation& ev, bool with_dice) const {
    const double wf = ev.w0 + ev.delta_w;
    ev.energy_share = wf > 0.0 ? std::max(0.0, ev.delta_w) / wf : 0.0;
    if (with_dice)
      ev.dice = diceSimilarity(detail::deformedLoops(model_, ev.u), target_);
    ev.q = ev.dice - options_.alpha * ev.energy_share;
  }

  /// Central-difference gradient of Q at theta (ev = evaluation at theta).
  Eigen::VectorXd gradientQ(const Eigen::VectorXd& theta, const Evaluation& ev) {
    const double h = options_.fd_step;
    Eigen::VectorXd grad = Eigen::VectorXd::Zero(size());
    for (int i = 0; i < freeClassCount(); ++i) {
      Eigen::VectorXd plus = theta, minus = theta;
      plus(i) = std::min(theta(i) + h, log_max_);
      minus(i) = std::max(theta(i) - h, log_min_);
      if (plus(i) - minus(i) <= 0.0)
        continue;
      const Evaluation ep = evaluate(plus), em = evaluate(minus);
      if (ep.ok && em.ok)
        grad(i) = (ep.q - em.q) / (plus(i) - minus(i));
    }
    if (forceCount() > 0) {
      solver_.setModuli(moduli(theta));
      const Eigen::MatrixXd green = solver_.greensFunctions();
      const Eigen::VectorXd f = forcesN(theta);
      for (int k = 0; k < forceCount(); ++k) {
        double q[2] = {0.0, 0.0};
        for (int sign = 0; sign < 2; ++sign) {
          const double df = (sign == 0 ? 1.0 : -1.0) * h * force_scale_N_;
          Evaluation e;
          e.u = ev.u + df * green.col(k);
          e.w0 = ev.w0;
          // delta_w(f + df e_k) = delta_w + df (G f)_k + df^2 G_kk / 2 (G symmetric on L)
          const int dof = solver_.forceDofs()[static_cast<std::size_t>(k)];
          double gf = 0.0;
          for (int j = 0; j < forceCount(); ++j)
            gf += green(dof, j) * f(j);
          e.delta_w = ev.delta_w + df * gf + 0.5 * df * df * green(dof, k);
          ++evaluations_;
          finishEvaluation(e, true);
          q[sign] = e.q;
        }
        grad(freeClassCount() + k) = (q[0] - q[1]) / (2.0 * h);
      }
    }
    // Projected gradient: no ascent through an active bound.
    for (int i = 0; i < freeClassCount(); ++i) {
      if ((theta(i) >= log_max_ && grad(i) > 0.0) || (theta(i) <= log_min_ && grad(i) < 0.0))
        grad(i) = 0.0;
    }
    return grad;
  }

  // ---- kFast: residual and Jacobian ----
  /// Residual r (boundary distances both ways) at displacement u; cost adds mu dW / W0.
  Eigen::VectorXd residual(const Eigen::VectorXd& u,
                           Eigen::MatrixXd* du_jacobian_rows = nullptr) const {
    const Loops deformed = detail::deformedLoops(model_, u);
    std::size_t n1 = 0;
    for (const auto& loop : deformed)
      n1 += loop.size();
    std::size_t n2 = 0;
    for (const auto& loop : target_)
      n2 += loop.size();
    Eigen::VectorXd r(static_cast<Eigen::Index>(n1 + n2));
    if (du_jacobian_rows)
      *du_jacobian_rows = Eigen::MatrixXd::Zero(r.size(), solver_.dofCount());
    std::size_t row = 0;
    for (std::size_t l = 0; l < deformed.size(); ++l) {
      for (std::size_t i = 0; i < deformed[l].size(); ++i, ++row) {
        const SignedDistance sd = signedDistance(target_, deformed[l][i]);
        const double w = loop_weights_[row];
        r(static_cast<Eigen::Index>(row)) = w * sd.d;
        if (du_jacobian_rows) {
          const int node = model_.prostate_loops[l][i];
          (*du_jacobian_rows)(static_cast<Eigen::Index>(row), 2 * node) = w * sd.grad.x();
          (*du_jacobian_rows)(static_cast<Eigen::Index>(row), 2 * node + 1) = w * sd.grad.y();
        }
      }
    }
    std::size_t j = 0;
    for (const auto& loop : target_) {
      for (const Point2& q : loop) {
        const SignedDistance sd = signedDistance(deformed, q);
        const double w = target_weights_[j++];
        r(static_cast<Eigen::Index>(row)) = w * sd.d;
        if (du_jacobian_rows && !deformed.empty()) {
          const auto& nodes = model_.prostate_loops[sd.loop];
          const int a = nodes[sd.edge], b = nodes[(sd.edge + 1) % nodes.size()];
          // d moves against the nearest boundary point c = (1-t) y_a + t y_b.
          for (const auto& [node, weight] :
               {std::make_pair(a, 1.0 - sd.t), std::make_pair(b, sd.t)}) {
            (*du_jacobian_rows)(static_cast<Eigen::Index>(row), 2 * node) -=
                w * weight * sd.grad.x();
            (*du_jacobian_rows)(static_cast<Eigen::Index>(row), 2 * node + 1) -=
                w * weight * sd.grad.y();
          }
        }
        ++row;
      }
    }
    return r;
  }

  double cost(const Evaluation& ev, double mu) const {
    const double reg = ev.w0 > 0.0 ? mu * ev.delta_w / ev.w0 : 0.0;
    return residual(ev.u).squaredNorm() + reg;
  }

private:
  const SliceModel& model_;
  SliceSolver solver_;
  Loops target_;
  std::vector<double> target_weights_;
  std::vector<double> loop_weights_;
  const RegistrationOptions& options_;
  std::vector<int> free_classes_;
  double log_min_ = 0.0, log_max_ = 0.0, force_scale_N_ = 1.0;
  int evaluations_ = 0;
};

struct OptimizerOutcome {
  Eigen::VectorXd theta;
  Evaluation best;
  int iterations = 0;
  bool converged = false;
  bool failed = false;
};

void record(RegistrationResult& result, const Problem& problem, const Eigen::VectorXd& theta,
            const Evaluation& ev, int iteration, Clock::time_point start) {
  IterationRecord rec;
  rec.iteration = iteration;
  rec.q = ev.q;
  rec.dice = ev.dice;
  rec.energy_share = ev.energy_share;
  rec.modulus_Pa = problem.moduli(theta);
  rec.seconds = secondsSince(start);
  result.trace.push_back(rec);
}

/// 3.2.4: steepest ascent with Armijo's rule and a finite-difference gradient.
OptimizerOutcome steepestDescent(Problem& problem, const RegistrationOptions& options,
                                 RegistrationResult& result, Clock::time_point start) {
  OptimizerOutcome out;
  out.theta = problem.initialTheta();
  out.best = problem.evaluate(out.theta);
  if (!out.best.ok) {
    out.failed = true;
    return out;
  }
  record(result, problem, out.theta, out.best, 0, start);
  for (int iteration = 1; iteration <= options.max_iterations; ++iteration) {
    const Eigen::VectorXd grad = problem.gradientQ(out.theta, out.best);
    if (grad.norm() < options.gradient_tolerance) {
      out.converged = true;
      break;
    }
    const auto candidate = [&](int t) {
      Eigen::VectorXd theta = out.theta + std::ldexp(options.step_size, t) * grad;
      problem.project(theta);
      return std::make_pair(theta, problem.evaluate(theta));
    };
    auto [best_theta, best_ev] = candidate(0);
    bool improved = best_ev.ok && best_ev.q > out.best.q;
    if (improved) {
      for (int t = 1; t <= 30; ++t) {  // the maximum t that still improves Q
        auto [theta, ev] = candidate(t);
        if (!ev.ok || ev.q <= best_ev.q)
          break;
        best_theta = theta;
        best_ev = ev;
      }
    } else {
      for (int t = -1; t >= -40 && !improved; --t) {
        auto [theta, ev] = candidate(t);
        if (ev.ok && ev.q > out.best.q) {
          best_theta = theta;
          best_ev = ev;
          improved = true;
        }
      }
    }
    if (!improved) {  // no ascent along the gradient: local optimum at FD resolution
      out.converged = true;
      break;
    }
    out.theta = best_theta;
    out.best = best_ev;
    out.iterations = iteration;
    record(result, problem, out.theta, out.best, iteration, start);
  }
  return out;
}

/// kFast: projected Levenberg-Marquardt on the boundary-distance residual.
OptimizerOutcome levenbergMarquardt(Problem& problem, const RegistrationOptions& options,
                                    RegistrationResult& result, Clock::time_point start) {
  OptimizerOutcome out;
  const int n_s = problem.freeClassCount();
  const int n = problem.size();
  const double mu = options.fast_force_regularisation_m2;
  Eigen::VectorXd theta = problem.initialTheta();
  Evaluation ev = problem.evaluate(theta);
  if (!ev.ok) {
    out.failed = true;
    return out;
  }
  out.theta = theta;
  out.best = ev;
  record(result, problem, theta, ev, 0, start);
  double cost = problem.cost(ev, mu);
  double lambda = 1e-3;
  for (int iteration = 1; iteration <= options.max_iterations; ++iteration) {
    // Jacobian of the residual with respect to theta.
    SliceSolver& solver = problem.solver();
    solver.setModuli(problem.moduli(theta));
    Eigen::MatrixXd dr_du;
    const Eigen::VectorXd r = problem.residual(ev.u, &dr_du);
    Eigen::MatrixXd du_dtheta(solver.dofCount(), n);
    du_dtheta.leftCols(n_s).setZero();
    Eigen::MatrixXd green;
    if (problem.forceCount() > 0) {
      green = solver.greensFunctions();
      du_dtheta.rightCols(problem.forceCount()) = problem.forceScale() * green;
    }
    Eigen::MatrixXd jac = dr_du * du_dtheta;
    // Stiffness columns: du/ds_c = -K_ff^-1 (E_c K_c u).
    for (int i = 0; i < n_s; ++i) {
      const int c = problem.freeClasses()[static_cast<std::size_t>(i)];
      const Eigen::VectorXd kcu = solver.classMultiply(c, ev.u);
      jac.col(i) = dr_du * (-solver.solveFree(kcu));
    }
    // Energy penalty mu dW / W0 = |R g|^2 with dW = 1/2 g^T (F0^2 P^T G) g.
    Eigen::MatrixXd reg_jac;
    Eigen::VectorXd reg_r;
    if (problem.forceCount() > 0 && ev.w0 > 0.0 && mu > 0.0) {
      Eigen::MatrixXd h(problem.forceCount(), problem.forceCount());
      for (int k = 0; k < problem.forceCount(); ++k)
        h.row(k) = green.row(solver.forceDofs()[static_cast<std::size_t>(k)]);
      h = 0.5 * (h + h.transpose()) * problem.forceScale() * problem.forceScale();
      const Eigen::LLT<Eigen::MatrixXd> llt(h);
      const Eigen::MatrixXd lt = llt.matrixU();  // h = U^T U
      reg_jac = Eigen::MatrixXd::Zero(problem.forceCount(), n);
      reg_jac.rightCols(problem.forceCount()) = std::sqrt(mu / (2.0 * ev.w0)) * lt;
      reg_r = reg_jac * theta;
    }
    Eigen::MatrixXd a = jac.transpose() * jac;
    Eigen::VectorXd b = jac.transpose() * r;
    if (reg_jac.size() > 0) {
      a += reg_jac.transpose() * reg_jac;
      b += reg_jac.transpose() * reg_r;
    }
    // Active set: moduli at a bound whose descent direction points outward stay fixed.
    std::vector<bool> active(static_cast<std::size_t>(n), false);
    for (int i = 0; i < n_s; ++i) {
      active[static_cast<std::size_t>(i)] = (theta(i) >= problem.logMax() && b(i) < 0.0) ||
                                            (theta(i) <= problem.logMin() && b(i) > 0.0);
    }
    bool accepted = false;
    double new_cost = cost;
    for (int attempt = 0; attempt < 12 && !accepted; ++attempt) {
      Eigen::MatrixXd m = a;
      for (int i = 0; i < n; ++i)
        m(i, i) += lambda * std::max(a(i, i), 1e-12) + 1e-18;
      Eigen::VectorXd rhs = -b;
      for (int i = 0; i < n; ++i) {
        if (!active[static_cast<std::size_t>(i)])
          continue;
        m.row(i).setZero();
        m.col(i).setZero();
        m(i, i) = 1.0;
        rhs(i) = 0.0;
      }
      const Eigen::VectorXd step = m.ldlt().solve(rhs);
      Eigen::VectorXd trial = theta + step;
      problem.project(trial);
      const Evaluation trial_ev = problem.evaluate(trial, false);
      if (!trial_ev.ok) {
        lambda *= 4.0;
        continue;
      }
      new_cost = problem.cost(trial_ev, mu);
      if (new_cost < cost) {
        accepted = true;
        theta = trial;
        ev = trial_ev;
        problem.finishEvaluation(ev, true);
        lambda = std::max(lambda / 3.0, 1e-9);
      } else {
        lambda *= 4.0;
      }
    }
    out.iterations = iteration;
    if (!accepted) {
      out.converged = true;
      break;
    }
    record(result, problem, theta, ev, iteration, start);
    if (ev.q > out.best.q) {
      out.best = ev;
      out.theta = theta;
    }
    const double decrease = cost - new_cost;
    cost = new_cost;
    if (decrease < options.fast_tolerance * cost) {
      out.converged = true;
      break;
    }
  }
  return out;
}

void validateOptions(const RegistrationOptions& o) {
  const auto require = [](bool ok, const std::string& message) {
    if (!ok)
      throw std::invalid_argument("registerSlices: " + message);
  };
  require(o.target_nodes >= 30, "target_nodes must be >= 30");
  require(o.poisson_ratio > -1.0 && o.poisson_ratio < 0.5, "poisson_ratio must be in (-1, 0.5)");
  require(o.min_modulus_Pa > 0.0 && o.min_modulus_Pa <= o.max_modulus_Pa,
          "need 0 < min_modulus_Pa <= max_modulus_Pa");
  for (double e : o.initial_modulus_Pa) {
    require(e >= o.min_modulus_Pa && e <= o.max_modulus_Pa,
            "initial moduli must lie within the bounds");
  }
  require(o.reference_class >= 0 && o.reference_class < kSoftClassCount,
          "reference_class out of range");
  require(o.alpha >= 0.0 && std::isfinite(o.alpha), "alpha must be >= 0");
  require(o.max_iterations >= 0, "max_iterations must be >= 0");
  require(o.step_size > 0.0 && o.fd_step > 0.0, "step_size and fd_step must be positive");
  require(o.fast_force_regularisation_m2 >= 0.0, "fast_force_regularisation_m2 must be >= 0");
  require(o.mrsi_spacing_m > 0.0, "mrsi_spacing_m must be positive");
}

}  // namespace

/// One line: status, Dice before and after, energy share, moduli, iterations, mesh size.
std::string summaryLine(const RegistrationResult& result, std::size_t mesh_nodes) {
  std::ostringstream msg;
  msg << toString(result.status) << ": Dice " << result.initial_dice * 100.0 << " % -> "
      << result.dice * 100.0 << " %, E " << result.energy_share * 100.0 << " %, moduli";
  for (int c = 0; c < kSoftClassCount; ++c)
    msg << " " << softClassName(c) << " " << result.modulus_Pa[static_cast<std::size_t>(c)] * 1e-3
        << " kPa";
  msg << ", " << result.iterations << " iterations, " << mesh_nodes << " nodes";
  if (result.mapping->invertedElements() > 0)
    msg << ", " << result.mapping->invertedElements() << " inverted elements";
  return msg.str();
}

RegistrationResult registerSlices(const SliceSegmentation& probe_out,
                                  const ProbeInSegmentation& probe_in,
                                  const RegistrationOptions& options) {
  validateOptions(options);
  const Clock::time_point start = Clock::now();
  RegistrationResult result;
  const auto refuse = [&](RegistrationStatus status, const std::string& message) {
    result.status = status;
    result.message = message;
    result.mapping.reset();
    result.seconds = secondsSince(start);
    return result;
  };

  // Input checks (3.2.1): simple, hole-free outlines inside the domain.
  const SegmentationCheck check = checkSegmentation(probe_out, probe_in);
  if (!check.ok)
    return refuse(RegistrationStatus::kInvalidSegmentation, check.problem);

  // Mesh and unit stiffness (3.2.2).
  std::optional<SliceModel> model;
  try {
    model.emplace(detail::buildSliceModel(probe_out, options.target_nodes, options.poisson_ratio));
  } catch (const std::exception& e) {
    return refuse(RegistrationStatus::kMeshingFailed, std::string("meshing failed: ") + e.what());
  }
  result.meshing_seconds = secondsSince(start);
  if (model->prostate_loops.empty())
    return refuse(RegistrationStatus::kInvalidSegmentation, "no prostate elements in the mesh");

  // Homologous rectum-wall displacements H (3.3.2): along rays from the rectum centre.
  const Polygon& probe = probe_in.probe.outer;
  const Point2 centre = model->rectum_centre;
  if (!probe.contains(centre)) {
    std::ostringstream msg;
    msg << "the rectum centre (" << centre.x() << ", " << centre.y()
        << ") m is not inside the probe outline";
    return refuse(RegistrationStatus::kProbeDoesNotEncloseRectum, msg.str());
  }
  double worst_outside = 0.0;
  for (const Point2& v : probe_out.rectum.outer.vertices()) {
    if (!probe.contains(v))
      worst_outside = std::max(worst_outside, probe.distanceToBoundary(v));
  }
  if (worst_outside > options.max_rectum_outside_probe_m) {
    std::ostringstream msg;
    msg << "the probe outline does not enclose the rectum: a rectum-wall point lies "
        << worst_outside * 1e3 << " mm outside it (limit "
        << options.max_rectum_outside_probe_m * 1e3 << " mm)";
    return refuse(RegistrationStatus::kProbeDoesNotEncloseRectum, msg.str());
  }
  std::vector<Point2> rectum_displacement;
  for (int node : model->rectum_nodes) {
    const Point2& x = model->mesh.nodes[static_cast<std::size_t>(node)];
    const auto y = projectOntoProbe(centre, x, probe);
    if (!y)
      return refuse(RegistrationStatus::kProbeDoesNotEncloseRectum,
                    "a ray from the rectum centre misses the probe outline");
    rectum_displacement.push_back(*y - x);
  }

  // Force set L (3.2.4).
  std::vector<int> force_nodes;
  if (options.force_set == ForceSet::kBladderBoundary) {
    force_nodes = model->bladder_nodes;
  } else if (options.force_set == ForceSet::kGlandBoundary) {
    for (const auto& loop : model->prostate_loops)
      force_nodes.insert(force_nodes.end(), loop.begin(), loop.end());
    std::sort(force_nodes.begin(), force_nodes.end());
    force_nodes.erase(std::unique(force_nodes.begin(), force_nodes.end()), force_nodes.end());
  }

  const Loops target = toLoops(probe_in.prostate.outer);
  Problem problem(*model, rectum_displacement, force_nodes, target, options);
  result.initial_dice = diceSimilarity(prostateLoops(probe_out), target);

  // Optimise p (3.2.4).
  OptimizerOutcome outcome;
  const Eigen::VectorXd theta0 = problem.initialTheta();
  const Evaluation initial = problem.evaluate(theta0);
  if (!initial.ok)
    return refuse(RegistrationStatus::kSolveFailed,
                  "the FEM factorisation failed at the initial moduli");
  if (initial.dice >= 1.0 - kAlignedDiceTol) {
    outcome.theta = theta0;
    outcome.best = initial;
    outcome.converged = true;
    record(result, problem, theta0, initial, 0, start);
    result.status = RegistrationStatus::kAlreadyAligned;
  } else {
    outcome = options.optimizer == Optimizer::kSteepestDescent
                  ? steepestDescent(problem, options, result, start)
                  : levenbergMarquardt(problem, options, result, start);
    if (outcome.failed || !outcome.best.ok)
      return refuse(RegistrationStatus::kSolveFailed, "the FEM solve failed during optimisation");
  }

  // Parameters and status.
  result.modulus_Pa = problem.moduli(outcome.theta);
  bool any_bound = false;
  for (int i = 0; i < problem.freeClassCount(); ++i) {
    const auto c = static_cast<std::size_t>(problem.freeClasses()[static_cast<std::size_t>(i)]);
    result.modulus_at_bound[c] = problem.atBound(outcome.theta, i);
    any_bound = any_bound || result.modulus_at_bound[c];
  }
  if (result.status != RegistrationStatus::kAlreadyAligned) {
    result.status = !outcome.converged ? RegistrationStatus::kMaxIterations
                    : any_bound        ? RegistrationStatus::kConvergedAtBound
                                       : RegistrationStatus::kConverged;
  }
  result.force_nodes = force_nodes;
  result.forces_N.assign(force_nodes.size(), Point2::Zero());
  if (problem.forceCount() > 0) {
    const Eigen::VectorXd f = problem.forcesN(outcome.theta);
    std::map<int, std::size_t> position;
    for (std::size_t i = 0; i < force_nodes.size(); ++i)
      position[force_nodes[i]] = i;
    for (int k = 0; k < problem.forceCount(); ++k) {
      const int dof = problem.solver().forceDofs()[static_cast<std::size_t>(k)];
      result.forces_N[position[dof / 2]](dof % 2) = f(k);
    }
  }
  result.dice = outcome.best.dice;
  result.energy_share = outcome.best.energy_share;
  result.q = outcome.best.q;
  result.iterations = outcome.iterations;
  result.objective_evaluations = problem.evaluations();

  // Deformation, T, T^-1 and the warped MRSI grid (3.2.2, 3.3.3).
  result.mesh = model->mesh;
  result.rectum_nodes = model->rectum_nodes;
  result.fixed_nodes = model->fixed_nodes;
  result.displacement_m.resize(model->mesh.nodes.size());
  for (std::size_t i = 0; i < result.displacement_m.size(); ++i) {
    result.displacement_m[i] = Point2(outcome.best.u(static_cast<Eigen::Index>(2 * i)),
                                      outcome.best.u(static_cast<Eigen::Index>(2 * i + 1)));
  }
  result.mapping = std::make_shared<MeshMapping>(result.mesh, result.displacement_m);
  result.mrsi_grid = warpMrsiGrid(*result.mapping, probe_in.prostate.outer, options.mrsi_spacing_m);
  result.message = summaryLine(result, model->mesh.nodes.size());
  result.seconds = secondsSince(start);
  return result;
}

}  // namespace needle_guidance::registration
