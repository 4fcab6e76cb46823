// Online noise adaptation of the steering policy (see adaptive_policy.h).
#include "needle_guidance/steering/adaptive_policy.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <stdexcept>
#include <utility>

namespace needle_guidance::steering {
namespace {

int index(Control u) {
  return u == Control::kInsert ? 0 : 1;
}

}  // namespace

AdaptivePolicy::AdaptivePolicy(SteeringProblem problem, std::shared_ptr<const PolicySource> initial,
                               AdaptationOptions options)
    : problem_(std::move(problem)),
      options_(std::move(options)),
      estimator_(options_.confidence),
      current_(std::move(initial)) {
  if (!current_ || !current_->model || !current_->table) {
    throw std::invalid_argument("AdaptivePolicy: no initial table");
  }
  const AdaptationOptions& o = options_;
  if (o.min_samples < 2 || !(o.false_resolve_rate > 0.0 && o.false_resolve_rate < 1.0) ||
      !(o.sigma_step >= 0.0) || !std::isfinite(o.sigma_step) || o.max_cached < 0 ||
      !(o.min_stopped_chord >= 0.0)) {
    throw std::invalid_argument(
        "AdaptivePolicy: need min_samples >= 2 (got " + std::to_string(o.min_samples) +
        "), false_resolve_rate in (0, 1) (got " + std::to_string(o.false_resolve_rate) +
        "), sigma_step >= 0 (got " + std::to_string(o.sigma_step) + "), max_cached >= 0 (got " +
        std::to_string(o.max_cached) + "), min_stopped_chord >= 0");
  }
  problem_.params = current_->model->params();
  sigma0_[0] = problem_.params.sigma_insert_rad;
  sigma0_[1] = problem_.params.sigma_flip_rad;
  cache_.emplace_back(current_->model->hash(), current_);
}

AdaptivePolicy::~AdaptivePolicy() {
  if (pending_.valid()) {
    pending_.wait();  // the solve owns nothing of ours but must not outlive its inputs
  }
}

ControlLookup AdaptivePolicy::lookup(const TipPose& pose) const {
  return current()->table->lookup(pose);
}

std::shared_ptr<const PolicySource> AdaptivePolicy::current() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return current_;
}

double AdaptivePolicy::assumedSigma(Control control) const {
  return control == Control::kInsert ? problem_.params.sigma_insert_rad
                                     : problem_.params.sigma_flip_rad;
}

double AdaptivePolicy::testConfidence(std::int64_t n) const {
  const double m = options_.min_samples;
  const double nn = static_cast<double>(std::max<std::int64_t>(n, options_.min_samples));
  return 1.0 - 0.5 * options_.false_resolve_rate * m / (nn * (nn + 1.0));
}

bool AdaptivePolicy::solving() const {
  return pending_.valid();
}

void AdaptivePolicy::observe(const TipPose& before, const TipPose& after, Control control) {
  const double delta = current()->model->arcLength_m();
  estimator_.addStep(before, after, control, delta, problem_.params.radius_m);
  afterSample(control);
}

bool AdaptivePolicy::observeStopped(const TipPose& before, const TipPose& stopped,
                                    Control control) {
  const double delta = current()->model->arcLength_m();
  const std::optional<double> beta =
      NoiseEstimator::deflectionOfStoppedStep(before, stopped, options_.min_stopped_chord * delta);
  if (!beta) {
    return false;
  }
  estimator_.add(control, *beta);
  afterSample(control);
  return true;
}

double AdaptivePolicy::rounded(Control control, double sigma_rad) const {
  const double s0 = sigma0_[index(control)];
  if (options_.sigma_step <= 0.0 || !(s0 > 0.0) || !(sigma_rad > 0.0)) {
    return sigma_rad;
  }
  const double step = std::log1p(options_.sigma_step);
  return s0 * std::exp(step * std::round(std::log(sigma_rad / s0) / step));
}

void AdaptivePolicy::afterSample(Control control) {
  ++steps_;
  SigmaSample sample;
  sample.step = steps_;
  sample.insert = estimator_.estimate(Control::kInsert);
  sample.flip = estimator_.estimate(Control::kFlip);
  trajectory_.push_back(sample);
  const std::int64_t n = (control == Control::kInsert ? sample.insert : sample.flip).samples;
  if (!options_.adapt || pending_.valid() || n < options_.min_samples) {
    return;
  }
  const SigmaEstimate tested = estimator_.estimate(control, testConfidence(n));
  if (tested.contains(assumedSigma(control))) {
    return;
  }
  // Only the control whose interval excluded its sigma changes; the other keeps its own.
  double next[2] = {problem_.params.sigma_insert_rad, problem_.params.sigma_flip_rad};
  next[index(control)] = rounded(control, tested.sigma_rad);
  if (next[0] == problem_.params.sigma_insert_rad && next[1] == problem_.params.sigma_flip_rad) {
    return;  // the estimate rounds to the sigma in use
  }
  startResolve(control, next[0], next[1]);
}

void AdaptivePolicy::startResolve(Control trigger, double sigma_insert_rad, double sigma_flip_rad) {
  pending_problem_ = withNoise(problem_, sigma_insert_rad, sigma_flip_rad);
  Resolve r;
  r.requested_at_step = steps_;
  r.trigger = trigger;
  r.sigma_insert_rad = sigma_insert_rad;
  r.sigma_flip_rad = sigma_flip_rad;
  const std::uint64_t hash = problemHash(pending_problem_);
  const auto hit = std::find_if(cache_.begin(), cache_.end(),
                                [hash](const auto& entry) { return entry.first == hash; });
  if (hit != cache_.end()) {
    r.cached = true;
    std::promise<std::shared_ptr<const PolicySource>> ready;
    ready.set_value(hit->second);
    pending_ = ready.get_future();
  } else {
    const SteeringProblem p = pending_problem_;
    const AdaptationOptions o = options_;
    pending_ = std::async(std::launch::async, [p, o]() -> std::shared_ptr<const PolicySource> {
      SelectionOptions s;
      s.solver = o.solver;
      s.threads = o.threads;
      Result<PolicySource> solved = solveOrLoad(p, o.scene_name, o.table_dir, s);
      if (!solved) {
        throw std::runtime_error("AdaptivePolicy: re-solve failed: " + solved.status().toString());
      }
      return std::make_shared<const PolicySource>(std::move(solved.value()));
    });
  }
  resolves_.push_back(r);
}

bool AdaptivePolicy::swapIn() {
  std::shared_ptr<const PolicySource> next = pending_.get();  // rethrows a failed solve
  Resolve& r = resolves_.back();
  r.swapped_at_step = steps_;
  r.seconds = r.cached ? 0.0 : next->seconds;
  const std::uint64_t hash = next->model->hash();
  cache_.erase(std::remove_if(cache_.begin(), cache_.end(),
                              [hash](const auto& entry) { return entry.first == hash; }),
               cache_.end());
  cache_.emplace_back(hash, next);
  while (cache_.size() > static_cast<std::size_t>(options_.max_cached) + 1) {
    cache_.erase(cache_.begin());  // least recently used; never the one just swapped in
  }
  problem_ = pending_problem_;
  std::lock_guard<std::mutex> lock(mutex_);
  const bool changed = next != current_;
  current_ = std::move(next);
  return changed;
}

bool AdaptivePolicy::poll() {
  if (!pending_.valid() ||
      pending_.wait_for(std::chrono::seconds(0)) != std::future_status::ready) {
    return false;
  }
  return swapIn();
}

bool AdaptivePolicy::waitAndSwap() {
  if (!pending_.valid()) {
    return false;
  }
  return swapIn();
}

StepPairing::StepPairing(double delta_m) : delta_m_(delta_m) {
  if (!(delta_m > 0.0) || !std::isfinite(delta_m)) {
    throw std::invalid_argument("StepPairing: step length must be finite and > 0, got " +
                                std::to_string(delta_m));
  }
}

std::optional<ObservedStep> StepPairing::add(double inserted_length_m, const TipPose& pose,
                                             bool vouched) {
  /// A tip is at a step boundary when its inserted length is within this fraction of a step of
  /// a whole number of steps.
  constexpr double kAtRestFraction = 1e-3;
  const double steps = inserted_length_m / delta_m_;
  if (!(std::abs(steps - std::round(steps)) <= kAtRestFraction)) {
    return std::nullopt;  // mid-motion, stopped at a contact, or not finite
  }
  if (anchored_ && std::abs(steps - anchor_steps_) <= kAtRestFraction) {
    return std::nullopt;  // the same boundary: keep its first tip (before any flip)
  }
  const bool whole_step = anchored_ && vouched_ && vouched &&
                          anchor_steps_ >= 1.0 - kAtRestFraction &&
                          std::abs(steps - anchor_steps_ - 1.0) <= kAtRestFraction;
  ObservedStep step;
  step.before = anchor_;
  step.after = pose;
  step.control = pose.bevel != anchor_.bevel ? Control::kFlip : Control::kInsert;
  anchored_ = true;
  vouched_ = vouched;
  anchor_ = pose;
  anchor_steps_ = steps;
  if (!whole_step) {
    return std::nullopt;
  }
  return step;
}

Result<std::vector<TableUsed>> tablesUsed(const SteeringProblem& chosen,
                                          const std::vector<TrialNoise>& trials,
                                          const std::string& scene_name,
                                          const std::string& table_dir,
                                          const SelectionOptions& options) {
  std::vector<TableUsed> out;
  for (std::size_t i = 0; i < trials.size(); ++i) {
    const TrialNoise& n = trials[i];
    auto same = std::find_if(out.begin(), out.end(), [&n](const TableUsed& t) {
      return t.noise.sigma_insert_rad == n.sigma_insert_rad &&
             t.noise.sigma_flip_rad == n.sigma_flip_rad;
    });
    if (same == out.end()) {
      Result<PolicySource> solved = solveOrLoad(
          withNoise(chosen, n.sigma_insert_rad, n.sigma_flip_rad), scene_name, table_dir, options);
      if (!solved) {
        return solved.status();
      }
      TableUsed t;
      t.noise = n;
      t.policy = std::make_shared<const PolicySource>(std::move(solved.value()));
      out.push_back(std::move(t));
      same = out.end() - 1;
    }
    same->trials.push_back(static_cast<int>(i));
  }
  return out;
}

}  // namespace needle_guidance::steering
