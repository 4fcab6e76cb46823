// AdaptivePolicy (issue 21): re-solves when the learned noise leaves the assumed interval,
// without a gap in the answers, and never when adaptation is off.
#include <gtest/gtest.h>

#include <cmath>
#include <memory>
#include <random>

#include "../steering_shapes.h"
#include "needle_guidance/steering/adaptive_policy.h"

namespace needle_guidance::steering {
namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kSigmaI = 5.0 * kPi / 180.0;
constexpr double kSigmaR = 10.0 * kPi / 180.0;
constexpr unsigned kSeed = 21;

SteeringProblem problem() {
  SteeringProblem p = test_shapes::openProblem(2e-3, kSigmaI, kSigmaR);
  p.params.transition_model = TransitionModel::kInterpolated;
  return p;
}

std::shared_ptr<const PolicySource> solved(const SteeringProblem& p) {
  Result<PolicySource> r = solveOrLoad(p, "", "", SelectionOptions{});
  EXPECT_TRUE(r) << r.status().toString();
  return std::make_shared<const PolicySource>(std::move(r.value()));
}

/// Feeds `steps` insertions whose deflections have standard deviation `sigma_rad`.
void feed(AdaptivePolicy& policy, double sigma_rad, int steps, std::mt19937_64& rng) {
  std::normal_distribution<double> beta(0.0, sigma_rad);
  const double delta = policy.current()->model->arcLength_m();
  for (int i = 0; i < steps; ++i) {
    TipPose before;
    before.p_SceneTip = Point2(0.02, 0.05);
    const TipPose after = advanceTip(before, Control::kInsert, beta(rng), delta, 0.05);
    policy.observe(before, after, Control::kInsert);
  }
}

TEST(AdaptivePolicy, ReSolvesForTwiceTheNoiseWithoutAGapInTheAnswers) {
  const SteeringProblem p = problem();
  const auto initial = solved(p);
  AdaptationOptions o;
  AdaptivePolicy policy(p, initial, o);
  std::mt19937_64 rng(kSeed);
  int fed = 0;
  while (!policy.solving() && fed < 200) {
    feed(policy, 2.0 * kSigmaI, 1, rng);
    ++fed;
  }
  ASSERT_TRUE(policy.solving()) << "no re-solve after " << fed << " steps at 2 sigma_i";
  // While the new table is solved, every tip still gets an answer from the old one.
  TipPose tip;
  tip.p_SceneTip = Point2(0.01, 0.05);
  int answered = 0;
  while (policy.solving() && !policy.poll()) {
    const ControlLookup l = policy.lookup(tip);
    ASSERT_TRUE(l) << l.toString();
    EXPECT_EQ(policy.current()->model->hash(), initial->model->hash());
    ++answered;
  }
  policy.waitAndSwap();
  EXPECT_GT(answered, 0) << "the solve finished before any look-up: no gap to test";
  const auto now = policy.current();
  EXPECT_NE(now->model->hash(), initial->model->hash());
  ASSERT_EQ(policy.resolves().size(), 1u);
  const Resolve& r = policy.resolves().front();
  EXPECT_GE(r.swapped_at_step, r.requested_at_step);
  EXPECT_NEAR(policy.assumedSigma(Control::kInsert),
              policy.estimator().estimate(Control::kInsert).sigma_rad, 1e-12);
  EXPECT_NEAR(policy.assumedSigma(Control::kFlip), kSigmaR, 1e-12) << "no flips seen: kept";
  EXPECT_TRUE(policy.lookup(tip));
  EXPECT_EQ(policy.trajectory().size(), static_cast<std::size_t>(fed));
}

TEST(AdaptivePolicy, OffNeverReSolves) {
  const SteeringProblem p = problem();
  AdaptationOptions o;
  o.adapt = false;
  AdaptivePolicy policy(p, solved(p), o);
  std::mt19937_64 rng(kSeed);
  feed(policy, 3.0 * kSigmaI, 100, rng);
  EXPECT_FALSE(policy.solving());
  EXPECT_FALSE(policy.poll());
  EXPECT_TRUE(policy.resolves().empty());
  EXPECT_EQ(policy.trajectory().size(), 100u);  // still estimated and reported
}

TEST(AdaptivePolicy, MatchingNoiseRarelyReSolves) {
  // The interval holds the true sigma 95 % of the time, but it is checked after every step.
  const SteeringProblem p = problem();
  AdaptivePolicy policy(p, solved(p), AdaptationOptions{});
  std::mt19937_64 rng(kSeed);
  feed(policy, kSigmaI, 100, rng);
  policy.waitAndSwap();
  EXPECT_LE(policy.resolves().size(), 1u);
}

TEST(AdaptivePolicy, BadOptionsAreRefused) {
  const SteeringProblem p = problem();
  AdaptationOptions o;
  o.min_samples = 1;
  EXPECT_THROW(AdaptivePolicy(p, solved(p), o), std::invalid_argument);
  EXPECT_THROW(AdaptivePolicy(p, nullptr, AdaptationOptions{}), std::invalid_argument);
}

}  // namespace
}  // namespace needle_guidance::steering

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
