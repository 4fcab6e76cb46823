// The start state chosen so that its prediction can be trusted (start_verification.h) and the
// discrete chain from starts that are not grid points: exactly between two grid points, on the
// workspace's edge, beyond the last grid row.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <random>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/start_verification.h"
#include "needle_guidance/steering/value_iteration.h"

#include "../steering_shapes.h"

namespace needle_guidance::steering {
namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kDeg = kPi / 180.0;
/// Spacing whose grid does not fit the 10 cm workspace: 34 rows at 0 .. 95.7 mm [m].
constexpr double kOddSpacing_m = 2.9e-3;
constexpr std::int64_t kChainTrials = 400;
constexpr std::uint64_t kSeed = 7;

/// The open workspace with noise (sigma_i 5 deg, sigma_r 10 deg) and a wall in front of the
/// target, on the odd grid: a small problem with a P_s surface that is neither 0 nor 1.
SteeringProblem noisyProblem(double spacing_m = kOddSpacing_m) {
  SteeringProblem p = test_shapes::openProblem(spacing_m, 5 * kDeg, 10 * kDeg, 0.085);
  p.obstacles.push_back(
      test_shapes::obstacle("wall", test_shapes::rect(0.05, 0.035, 0.056, 0.065), 1e-3));
  return p;
}

/// Trials of the long Monte Carlo that stands for the true P_s at a start (its own seed).
constexpr std::int64_t kTruthTrials = 40000;
constexpr std::uint64_t kTruthSeed = 97;
/// The verification tolerance of the tests on the staged verification: a small problem's
/// verification costs a few thousand trials at it.
constexpr double kTolerance = 0.03;
/// A prediction this many tolerances off the truth must not be confirmed.
constexpr double kBiasInTolerances = 1.5;
/// Simulated verifications per case of the staged rule, and their seed.
constexpr int kSimulatedVerifications = 4000;
constexpr std::uint64_t kRuleSeed = 2027;
/// The rule's bound: a prediction off by the tolerance confirmed in at most 2.5 % (about 1.5 %
/// expected; its binomial SE over 4,000 is 0.2 %).
constexpr double kFalseConfirmationBound = 0.025;
/// A reported P_s more than the tolerance off: at most 0.25 % of verifications (the verified
/// rate's z SE <= tolerance / 2 makes it about 0.01 %).
constexpr double kReportedOffBound = 0.0025;
/// An exact prediction is confirmed in about 89 % (at P_s 0.5, tolerance 0.01): at least 80 %.
constexpr double kExactConfirmedAtLeast = 0.8;
/// The last look's trials are sized at the rate of the look before it, so at its own rate z SE
/// may exceed tolerance / 2 by the change of sqrt(r (1 - r)) between the two: within 5 % here.
constexpr double kCapRateSlack = 1.05;

/// `table` with the P_s of some states replaced (the controls unchanged, so its policy and
/// every Monte Carlo under it are those of `table`).
PolicyTable withValues(const PolicyTable& table,
                       const std::vector<std::pair<StateId, float>>& replaced) {
  std::vector<float> values = table.values();
  for (const auto& [state, value] : replaced) {
    values[std::size_t(state)] = value;
  }
  std::vector<std::uint64_t> bits((values.size() + 63) / 64, 0);
  for (StateId s = 0; s < StateId(values.size()); ++s) {
    bits[std::size_t(s) >> 6] |= std::uint64_t(table.control(s) == Control::kFlip) << (s & 63);
  }
  std::vector<std::uint8_t> cells(std::size_t(table.grid().numPositions()));
  for (std::size_t i = 0; i < cells.size(); ++i) {
    cells[i] = static_cast<std::uint8_t>(table.cell(std::int64_t(i)));
  }
  return PolicyTable(table.grid(), table.problemHash(), values, bits, cells, table.epsilon(),
                     table.sweeps(), table.converged());
}
PolicyTable withValue(const PolicyTable& table, StateId state, float value) {
  return withValues(table, {{state, value}});
}

class StartVerificationTest : public ::testing::Test {
protected:
  static void SetUpTestSuite() {
    problem_ = new SteeringProblem(noisyProblem());
    model_ = new SteeringModel(*problem_);
    table_ = new PolicyTable(solveValueIteration(*model_));
    world_ = new ContinuousWorkspace(*problem_);
  }
  static void TearDownTestSuite() {
    delete world_;
    delete table_;
    delete model_;
    delete problem_;
  }
  static SteeringProblem* problem_;
  static SteeringModel* model_;
  static PolicyTable* table_;
  static ContinuousWorkspace* world_;
};
SteeringProblem* StartVerificationTest::problem_ = nullptr;
SteeringModel* StartVerificationTest::model_ = nullptr;
PolicyTable* StartVerificationTest::table_ = nullptr;
ContinuousWorkspace* StartVerificationTest::world_ = nullptr;

TEST_F(StartVerificationTest, StartExactlyBetweenGridPointsTakesANeighbour) {
  const GridSpec& g = model_->grid();
  TipPose between;
  between.p_SceneTip = Point2(0.0, g.point(0, 12).y() + 0.5 * g.spacing_m);
  const StateId s = g.nearestState(between);
  int ix = 0, iy = 0, k = 0;
  Bevel b = Bevel::kLeft;
  ASSERT_GE(s, 0);
  g.decode(s, ix, iy, k, b);
  // One of its two neighbours (12.5 rounds up, unless the sum rounds below 12.5 in binary).
  EXPECT_TRUE(iy == 12 || iy == 13) << iy;
  EXPECT_EQ(ix, 0);
  TipPose on_point = between;
  on_point.p_SceneTip = g.point(0, iy);
  const ChainResult a = runDiscreteChain(*model_, *table_, between, kChainTrials, kSeed);
  const ChainResult c = runDiscreteChain(*model_, *table_, on_point, kChainTrials, kSeed);
  EXPECT_EQ(a.successes, c.successes);  // the same state, the same seeds
  EXPECT_EQ(a.trials, kChainTrials);
}

TEST_F(StartVerificationTest, StartOnTheWorkspaceEdgeBeyondTheLastRowIsOnTheGrid) {
  const GridSpec& g = model_->grid();
  // 10 cm / 2.9 mm: 34 rows, the last at 95.7 mm; the edge at 100 mm is 1.5 spacings past it.
  ASSERT_EQ(g.ny, 34);
  for (double y : {problem_->workspace_max.y(), problem_->workspace_min.y(), 0.0985}) {
    SCOPED_TRACE("y = " + std::to_string(y));
    TipPose edge;
    edge.p_SceneTip = Point2(0.0, y);
    edge.theta_rad = y > 0.05 ? -20 * kDeg : 20 * kDeg;
    const StateId s = g.nearestState(edge);
    ASSERT_GE(s, 0);
    EXPECT_TRUE(table_->lookup(edge)) << table_->lookup(edge).toString();
    EXPECT_NO_THROW(runDiscreteChain(*model_, *table_, edge, kChainTrials, kSeed));
  }
  TipPose top;
  top.p_SceneTip = problem_->workspace_max;
  int ix = 0, iy = 0, k = 0;
  Bevel b = Bevel::kLeft;
  g.decode(g.nearestState(top), ix, iy, k, b);
  EXPECT_EQ(ix, g.nx - 1);
  EXPECT_EQ(iy, g.ny - 1);
  // Far outside (1 cm) is still refused, with the reason.
  TipPose outside;
  outside.p_SceneTip = Point2(-0.01, 0.05);
  EXPECT_EQ(g.nearestState(outside), -1);
  try {
    runDiscreteChain(*model_, *table_, outside, kChainTrials, kSeed);
    ADD_FAILURE() << "a start 1 cm outside the grid was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("off the grid"), std::string::npos) << e.what();
  }
}

TEST_F(StartVerificationTest, ChosenStartIsVerifiedWithFreshSeedsAndDeterministic) {
  StartVerificationOptions options;
  options.screen_trials = 500;
  options.verify_trials = 2000;
  options.tolerance = kTolerance;
  const VerifiedStart a = verifyBestStart(*world_, *table_, test_shapes::entryLine(), options);
  ASSERT_TRUE(a) << a.message;
  EXPECT_EQ(a.first_look_trials, options.verify_trials);
  EXPECT_GE(a.verification.trials, options.verify_trials);
  EXPECT_FALSE(a.screened.empty());
  EXPECT_LE(a.screened.size(), std::size_t(options.candidates));
  // The chosen start is one of the screened, and the screen's best prediction is the table's.
  EXPECT_EQ(a.screened.front().candidate.state,
            table_->bestStart(test_shapes::entryLine()).best.state);
  EXPECT_EQ(a.start.state, a.screened[std::size_t(a.rank_by_prediction)].candidate.state);
  EXPECT_EQ(a.confirmed, verificationConfirms(a.predicted(), a.verification, options.tolerance,
                                              options.confirm_z));
  EXPECT_EQ(a.reported(), a.confirmed ? a.predicted() : a.verification.rate());
  const VerifiedStart b = verifyBestStart(*world_, *table_, test_shapes::entryLine(), options);
  EXPECT_EQ(a.start.state, b.start.state);
  EXPECT_EQ(a.verification.successes, b.verification.successes);
  EXPECT_EQ(a.verification.trials, b.verification.trials);
  EXPECT_NE(a.toString().find("P_s"), std::string::npos) << a.toString();
}

TEST_F(StartVerificationTest, VerificationTrialsFollowTheToleranceAndTheStartsPs) {
  // First look (verify_trials 0): max(16,000, 1 / tolerance^2) x 4 v, v the larger binomial
  // variance of the prediction and the screen's rate. An unconfirmed verification ends where
  // z SE <= tolerance / 2 at its own rate (or at max_verify_trials).
  StartVerificationOptions options;
  options.candidates = 1;
  options.screen_trials = 200;
  for (const double tolerance : {0.005, 0.02}) {
    options.tolerance = tolerance;
    const VerifiedStart v = verifyBestStart(*world_, *table_, test_shapes::entryLine(), options);
    ASSERT_TRUE(v) << v.message;
    const ScreenedStart& s = v.screened.at(std::size_t(v.rank_by_prediction));
    const double p = s.candidate.probability_of_success;
    const double r = s.screen.rate();
    const double variance = std::max(p * (1.0 - p), r * (1.0 - r));
    const double at_half = tolerance == 0.005 ? 40000.0 : 16000.0;
    EXPECT_EQ(v.first_look_trials,
              std::max<std::int64_t>(200, std::int64_t(std::ceil(at_half * 4.0 * variance))))
        << "tolerance " << tolerance << ", p " << p << ", screen " << r;
    EXPECT_LE(v.verification.trials, options.max_verify_trials);
    if (!v.confirmed && v.verification.trials < options.max_verify_trials) {
      EXPECT_LE(options.z * v.standardError(), 0.5 * tolerance * kCapRateSlack) << v.toString();
    }
  }
}

TEST(VerificationRule, ConfirmsOnlyBeyondItsNoise) {
  // 38,415 trials at rate 0.5: SE = 0.00255, confirm_z SE = 0.0061, so a gap up to 0.0039 is
  // confirmed within 0.01 (up to 0.0050 with z = 1.96).
  MonteCarloResult mc;
  mc.trials = 38415;
  mc.successes = 19208;
  const double r = mc.rate();
  EXPECT_TRUE(verificationConfirms(r + 0.0038, mc, 0.01));
  EXPECT_TRUE(verificationConfirms(r - 0.0038, mc, 0.01));
  EXPECT_FALSE(verificationConfirms(r + 0.0040, mc, 0.01));
  EXPECT_TRUE(verificationConfirms(r + 0.0049, mc, 0.01, 1.959963984540054));
  EXPECT_FALSE(verificationConfirms(r + 0.0052, mc, 0.01, 1.959963984540054));
  EXPECT_FALSE(verificationConfirms(std::nan(""), mc, 0.01));
  EXPECT_FALSE(verificationConfirms(r, MonteCarloResult{}, 0.01));
  // The cap: z^2 r (1 - r) / (tolerance / 2)^2, within [first, max].
  EXPECT_EQ(verificationCap(0.5, 0.01, 1.959963984540054, 16000, 100000), 38415);
  EXPECT_EQ(verificationCap(0.5, 0.005, 1.959963984540054, 16000, 100000), 100000);
  EXPECT_EQ(verificationCap(0.01, 0.01, 1.959963984540054, 16000, 100000), 16000);
}

/// The table's best start with its P_s from a long Monte Carlo, and start options that offer
/// only its pose.
struct TruthAtBest {
  StartCandidate start;
  StartOptions only;
  double ps = 0.0;
};
TruthAtBest truthAtBest(const ContinuousWorkspace& world, const PolicyTable& table) {
  TruthAtBest out;
  out.start = table.bestStart(test_shapes::entryLine()).best;
  out.only = test_shapes::entryLine();
  out.only.min_height_m = out.only.max_height_m = out.start.pose.p_SceneTip.y();
  out.only.min_theta_rad = out.only.max_theta_rad = out.start.pose.theta_rad;
  out.ps =
      runMonteCarlo(world, out.start.pose, tablePolicy(table), kTruthTrials, kTruthSeed, 2).rate();
  return out;
}

/// `table` with the start's P_s set to `value` and every other state of `truth.only` (the other
/// bevel) to 0, so the start is the one verified.
PolicyTable predicting(const PolicyTable& table, const TruthAtBest& truth, double value) {
  std::vector<std::pair<StateId, float>> replaced;
  for (const StartCandidate& c : table.startCandidates(truth.only)) {
    replaced.emplace_back(c.state, c.state == truth.start.state ? float(value) : 0.0f);
  }
  return withValues(table, replaced);
}

/// One candidate, the tolerance of these tests and a first look of 1,000 trials (the cap at
/// kTolerance is about 4,300 at P_s 0.5).
StartVerificationOptions stagedOptions() {
  StartVerificationOptions options;
  options.candidates = 1;
  options.screen_trials = 500;
  options.verify_trials = 1000;
  options.tolerance = kTolerance;
  return options;
}

TEST_F(StartVerificationTest, BiasedPredictionIsNotConfirmedAndItsVerifiedRateIsReported) {
  const TruthAtBest truth = truthAtBest(*world_, *table_);
  ASSERT_LT(truth.ps + kBiasInTolerances * kTolerance, 1.0);
  const double biased = truth.ps + kBiasInTolerances * kTolerance;
  const StartVerificationOptions options = stagedOptions();
  const VerifiedStart v =
      verifyBestStart(*world_, predicting(*table_, truth, biased), truth.only, options);
  ASSERT_TRUE(v) << v.message;
  ASSERT_EQ(v.start.state, truth.start.state);
  EXPECT_FLOAT_EQ(v.predicted(), float(biased));
  EXPECT_FALSE(v.confirmed) << v.toString();
  EXPECT_EQ(v.reported(), v.verification.rate());
  EXPECT_LE(std::abs(v.reported() - truth.ps), kTolerance) << v.toString();
  // It ran to z SE <= tolerance / 2 at its own rate, over several looks of one run.
  EXPECT_LE(options.z * v.standardError(), 0.5 * kTolerance * kCapRateSlack) << v.toString();
  EXPECT_GT(v.looks, 1);
  EXPECT_NE(v.toString().find("NOT confirmed"), std::string::npos) << v.toString();
  EXPECT_NE(v.toString().find("the verified rate"), std::string::npos) << v.toString();
}

TEST_F(StartVerificationTest, CorrectPredictionIsConfirmedAndReported) {
  const TruthAtBest truth = truthAtBest(*world_, *table_);
  const VerifiedStart v =
      verifyBestStart(*world_, predicting(*table_, truth, truth.ps), truth.only, stagedOptions());
  ASSERT_TRUE(v) << v.message;
  ASSERT_EQ(v.start.state, truth.start.state);
  EXPECT_TRUE(v.confirmed) << v.toString();
  EXPECT_EQ(v.reported(), v.predicted());
  EXPECT_LE(std::abs(v.reported() - truth.ps), kTolerance);
  EXPECT_NE(v.toString().find("the model's prediction, confirmed"), std::string::npos)
      << v.toString();
}

TEST_F(StartVerificationTest, StagedVerificationStopsAtTheFirstConfidentAgreement) {
  // A prediction equal to the first look's own rate: |gap| 0 + confirm_z SE <= tolerance after
  // 2,000 trials, while an unconfirmed verification would run on to z SE <= tolerance / 2.
  StartVerificationOptions options = stagedOptions();
  options.verify_trials = 2000;
  const TruthAtBest truth = truthAtBest(*world_, *table_);
  TrialOptions trial;
  trial.max_steps = options.max_steps;
  const double first_look = runMonteCarlo(*world_, truth.start.pose, tablePolicy(*table_),
                                          options.verify_trials, options.seed + 1, 2, trial)
                                .rate();
  const std::int64_t cap = verificationCap(first_look, kTolerance, options.z, options.verify_trials,
                                           options.max_verify_trials);
  ASSERT_GT(cap, options.verify_trials) << "P_s " << first_look;
  const VerifiedStart v =
      verifyBestStart(*world_, predicting(*table_, truth, first_look), truth.only, options);
  ASSERT_TRUE(v) << v.message;
  EXPECT_TRUE(v.confirmed) << v.toString();
  EXPECT_EQ(v.looks, 1);
  EXPECT_EQ(v.verification.trials, options.verify_trials);
  // The same start predicted 1.5 tolerances higher is not confirmed and runs on to its cap, the
  // trials where z SE <= tolerance / 2 at its rate.
  const VerifiedStart u = verifyBestStart(
      *world_, predicting(*table_, truth, first_look + kBiasInTolerances * kTolerance), truth.only,
      options);
  EXPECT_FALSE(u.confirmed) << u.toString();
  EXPECT_GT(u.looks, 1);
  EXPECT_EQ(u.looks, 3);  // the first, twice its trials, the cap
  EXPECT_LE(options.z * u.standardError(), 0.5 * kTolerance * kCapRateSlack) << u.toString();
}

TEST_F(StartVerificationTest, StartTheTableOverratesIsNotChosen) {
  // Raise one mediocre start state's prediction to 0.99: the table's own best start is then
  // that state, which the continuous needle does not confirm.
  const StartOptions entry = test_shapes::entryLine();
  std::vector<StartCandidate> all = table_->startCandidates(entry);
  const StartCandidate* mediocre = nullptr;
  for (const StartCandidate& c : all) {
    if (c.probability_of_success > 0.2f && c.probability_of_success < 0.5f) {
      mediocre = &c;
      break;
    }
  }
  ASSERT_NE(mediocre, nullptr);
  const PolicyTable optimistic = withValue(*table_, mediocre->state, 0.99f);
  ASSERT_EQ(optimistic.bestStart(entry).best.state, mediocre->state);
  StartVerificationOptions options;
  options.screen_trials = 500;
  options.verify_trials = 2000;
  options.tolerance = kTolerance;
  const VerifiedStart v = verifyBestStart(*world_, optimistic, entry, options);
  ASSERT_TRUE(v) << v.message;
  EXPECT_NE(v.start.state, mediocre->state) << v.toString();
  EXPECT_FALSE(v.screened.front().confirmed);  // the overrated state was screened and refused
  EXPECT_EQ(v.reported(), v.confirmed ? v.predicted() : v.verification.rate()) << v.toString();
  EXPECT_LT(v.reported(), 0.99 - kTolerance) << v.toString();
  EXPECT_GT(v.rank_by_prediction, 0);
}

TEST_F(StartVerificationTest, DistinctStartsAreSeparated) {
  StartVerificationOptions options;
  options.candidates = 6;
  options.separation_m = 5e-3;
  options.separation_rad = 20 * kDeg;
  const std::vector<StartCandidate> starts =
      distinctBestStarts(*table_, test_shapes::entryLine(), options);
  ASSERT_FALSE(starts.empty());
  EXPECT_LE(starts.size(), 6u);
  for (std::size_t i = 0; i < starts.size(); ++i) {
    for (std::size_t j = 0; j < i; ++j) {
      EXPECT_GE(starts[j].probability_of_success, starts[i].probability_of_success);
      const bool apart =
          starts[i].pose.bevel != starts[j].pose.bevel ||
          std::abs(starts[i].pose.p_SceneTip.y() - starts[j].pose.p_SceneTip.y()) >
              options.separation_m ||
          std::abs(std::remainder(starts[i].pose.theta_rad - starts[j].pose.theta_rad, 2 * kPi)) >
              options.separation_rad;
      EXPECT_TRUE(apart) << i << " and " << j;
    }
  }
}

TEST_F(StartVerificationTest, UnreachableTargetIsReportedNotChosen) {
  StartOptions nowhere = test_shapes::entryLine();
  nowhere.min_theta_rad = nowhere.max_theta_rad = kPi;  // pointing away: P_s = 0 everywhere
  nowhere.min_height_m = nowhere.max_height_m = 0.0;
  const VerifiedStart v = verifyBestStart(*world_, *table_, nowhere);
  EXPECT_FALSE(v);
  EXPECT_FALSE(v.message.empty());
  EXPECT_EQ(v.toString(), v.message);
}

TEST_F(StartVerificationTest, BadOptionsAreRefusedByName) {
  StartVerificationOptions bad;
  bad.screen_trials = 0;
  try {
    verifyBestStart(*world_, *table_, test_shapes::entryLine(), bad);
    ADD_FAILURE() << "screen_trials 0 accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("screen_trials"), std::string::npos) << e.what();
  }
  bad = {};
  bad.tolerance = -0.1;
  EXPECT_THROW(verifyBestStart(*world_, *table_, test_shapes::entryLine(), bad),
               std::invalid_argument);
  StartVerificationOptions no_trials;
  no_trials.max_verify_trials = 0;
  StartVerificationOptions no_z;
  no_z.confirm_z = std::nan("");
  for (const auto& [name, options] :
       {std::pair{"max_verify_trials", no_trials}, std::pair{"confirm_z", no_z}}) {
    try {
      verifyBestStart(*world_, *table_, test_shapes::entryLine(), options);
      ADD_FAILURE() << name << " out of range accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(name), std::string::npos) << e.what();
    }
  }
}

/// Simulated verifications of the staged rule: binomial draws at a known P_s stand for the
/// continuous needle's trials.
struct RuleFigures {
  double confirmed = 0.0;     ///< fraction confirmed
  double reported_off = 0.0;  ///< fraction whose reported P_s is more than the tolerance off
  double mean_trials = 0.0;
  int max_looks = 0;
};
RuleFigures simulateRule(double truth, double predicted, double tolerance, std::int64_t first) {
  std::mt19937_64 rng(kRuleSeed);
  StartVerificationOptions options;
  options.tolerance = tolerance;
  RuleFigures out;
  for (int i = 0; i < kSimulatedVerifications; ++i) {
    const TrialSampler sample = [&](std::int64_t, std::int64_t trials) {
      MonteCarloResult mc;
      mc.trials = trials;
      mc.successes = std::binomial_distribution<std::int64_t>(trials, truth)(rng);
      return mc;
    };
    const StagedVerification v = verifyInLooks(predicted, first, options, sample);
    const double reported = v.confirmed ? predicted : v.mc.rate();
    out.confirmed += v.confirmed ? 1.0 : 0.0;
    out.reported_off += std::abs(reported - truth) > tolerance ? 1.0 : 0.0;
    out.mean_trials += double(v.mc.trials);
    out.max_looks = std::max(out.max_looks, v.looks);
  }
  out.confirmed /= kSimulatedVerifications;
  out.reported_off /= kSimulatedVerifications;
  out.mean_trials /= kSimulatedVerifications;
  return out;
}

TEST(VerificationRule, StagedLooksConfirmAPredictionOffByTheToleranceRarely) {
  // (P_s, tolerance, the default first look there: max(16,000, 1 / tol^2) x 4 p (1 - p)).
  const struct {
    double truth, tolerance;
    std::int64_t first;
  } cases[] = {{0.5, 0.01, 16000}, {0.85, 0.005, 20400}, {0.2, 0.01, 10240}};
  for (const auto& c : cases) {
    SCOPED_TRACE("P_s " + std::to_string(c.truth) + ", tolerance " + std::to_string(c.tolerance));
    // Off by exactly the tolerance: confirmed in at most 2.5 % over all looks (Bonferroni).
    const RuleFigures off = simulateRule(c.truth, c.truth + c.tolerance, c.tolerance, c.first);
    EXPECT_LE(off.confirmed, kFalseConfirmationBound);
    EXPECT_LE(off.max_looks, 3);
    // Off by 1.5 tolerances: reported by its verified rate, which is within the tolerance.
    const RuleFigures far =
        simulateRule(c.truth, c.truth + kBiasInTolerances * c.tolerance, c.tolerance, c.first);
    EXPECT_LE(far.reported_off, kReportedOffBound);
    // Exact: mostly confirmed, and then before the cap on average.
    const RuleFigures exact = simulateRule(c.truth, c.truth, c.tolerance, c.first);
    EXPECT_GE(exact.confirmed, kExactConfirmedAtLeast);
    EXPECT_LE(exact.reported_off, kReportedOffBound);
    EXPECT_LT(exact.mean_trials,
              double(verificationCap(c.truth, c.tolerance, 1.959963984540054, c.first, 100000)));
    std::cout << "P_s " << c.truth << ", tolerance " << c.tolerance << ": confirmed off by tol "
              << off.confirmed << ", exact " << exact.confirmed << " (mean trials "
              << exact.mean_trials << "), off by 1.5 tol " << far.confirmed << " (mean trials "
              << far.mean_trials << "); reported more than tol off: " << off.reported_off << ", "
              << exact.reported_off << ", " << far.reported_off << "\n";
  }
}

TEST(PredictionConfirmed, ToleranceAndBinomialNoise) {
  // 10,000 trials at p = 0.5: z * SE = 0.0098.
  EXPECT_TRUE(predictionConfirmed(0.5, 0.5 - 0.0150, 10000, 0.01));
  EXPECT_FALSE(predictionConfirmed(0.5, 0.5 - 0.0250, 10000, 0.01));
  EXPECT_TRUE(predictionConfirmed(0.344, 0.344, 1, 0.0));
  EXPECT_FALSE(predictionConfirmed(0.344, 0.250, 10000, 0.01));  // 0.094 apart
  EXPECT_FALSE(predictionConfirmed(std::nan(""), 0.3, 10000, 0.01));
  EXPECT_FALSE(predictionConfirmed(0.3, 0.3, 0, 0.01));
}

}  // namespace
}  // namespace needle_guidance::steering

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
