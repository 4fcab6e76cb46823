// Online noise adaptation of the steering policy (issue 21; see adaptive_policy.h).
#include "needle_guidance/steering/adaptive_policy.h"

#include <chrono>
#include <stdexcept>
#include <utility>

namespace needle_guidance::steering {

AdaptivePolicy::AdaptivePolicy(SteeringProblem problem, std::shared_ptr<const PolicySource> initial,
                               AdaptationOptions options)
    : problem_(std::move(problem)),
      options_(options),
      estimator_(options.confidence),
      current_(std::move(initial)) {
  if (!current_ || !current_->model || !current_->table) {
    throw std::invalid_argument("AdaptivePolicy: no initial table");
  }
  if (options_.min_samples < 2) {
    throw std::invalid_argument("AdaptivePolicy: min_samples must be >= 2, got " +
                                std::to_string(options_.min_samples));
  }
  problem_.params = current_->model->params();
  cache_[current_->model->hash()] = current_;
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

bool AdaptivePolicy::solving() const {
  return pending_.valid();
}

void AdaptivePolicy::observe(const TipPose& before, const TipPose& after, Control control) {
  const double delta = current()->model->arcLength_m();
  estimator_.addStep(before, after, control, delta, problem_.params.radius_m);
  ++steps_;
  SigmaSample sample;
  sample.step = steps_;
  sample.insert = estimator_.estimate(Control::kInsert);
  sample.flip = estimator_.estimate(Control::kFlip);
  trajectory_.push_back(sample);
  if (!options_.adapt || pending_.valid()) {
    return;
  }
  bool left = false;
  for (Control u : {Control::kInsert, Control::kFlip}) {
    const SigmaEstimate e = u == Control::kInsert ? sample.insert : sample.flip;
    left = left || (e.samples >= options_.min_samples && !e.contains(assumedSigma(u)));
  }
  if (left) {
    startResolve();
  }
}

void AdaptivePolicy::startResolve() {
  pending_problem_ = problem_;
  for (Control u : {Control::kInsert, Control::kFlip}) {
    const SigmaEstimate e = estimator_.estimate(u);
    // A control never (or hardly) seen keeps its assumed sigma.
    if (e.samples >= options_.min_samples) {
      (u == Control::kInsert ? pending_problem_.params.sigma_insert_rad
                             : pending_problem_.params.sigma_flip_rad) = e.sigma_rad;
    }
  }
  pending_problem_.ps_tolerance = 0.0;  // the grid of the table in use
  Resolve r;
  r.requested_at_step = steps_;
  r.sigma_insert_rad = pending_problem_.params.sigma_insert_rad;
  r.sigma_flip_rad = pending_problem_.params.sigma_flip_rad;
  const std::uint64_t hash = problemHash(pending_problem_);
  const auto hit = cache_.find(hash);
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
      Result<PolicySource> solved = solveOrLoad(p, "", "", s);
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
  cache_[next->model->hash()] = next;
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

}  // namespace needle_guidance::steering
