// Model selection from a P_s tolerance and the solver's change-bounded skipping.
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <string>

#include "../steering_shapes.h"
#include "needle_guidance/math.h"
#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/model_selection.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/value_iteration.h"

namespace needle_guidance::steering {
namespace {

using test_shapes::entryLine;
/// A problem with uncertainty and a wall, small enough to solve many times in a test: the open
/// workspace with sigma_i = 5 deg, sigma_r = 10 deg and a block in front of the target.
SteeringProblem noisyProblem(double spacing_m) {
  SteeringProblem p = test_shapes::openProblem(spacing_m, 5.0 * kPi / 180.0, 10.0 * kPi / 180.0);
  p.obstacles.push_back(
      test_shapes::obstacle("block", test_shapes::rect(0.045, 0.04, 0.055, 0.06), 0.001));
  p.params.transition_model = TransitionModel::kInterpolated;
  p.params.orientation_subdivision = 2;
  return p;
}

TEST(SolverSkipping, ValuesWithinTheSkipBoundOfTheFullSweeps) {
  // Skipping a position moves its value by less than epsilon * skip_fraction per skip; after
  // convergence the two solves agree to a few epsilons.
  constexpr double kAgreementTol = 3e-3;  // 3 epsilon [P_s]
  const SteeringModel model(noisyProblem(2e-3), 2);
  SolverOptions all;
  all.skip_fraction = 0.0;
  SolverOptions skip;
  SolveStats stats_all, stats_skip;
  const PolicyTable a = solveValueIteration(model, all, &stats_all);
  const PolicyTable b = solveValueIteration(model, skip, &stats_skip);
  ASSERT_TRUE(a.converged());
  ASSERT_TRUE(b.converged());
  double worst = 0.0;
  for (StateId s = 0; s < model.numStates(); ++s) {
    worst = std::max(worst, double(std::abs(a.value(s) - b.value(s))));
  }
  EXPECT_LE(worst, kAgreementTol);
  std::int64_t updates_all = 0, updates_skip = 0;
  for (auto u : stats_all.updated_per_sweep)
    updates_all += u;
  for (auto u : stats_skip.updated_per_sweep)
    updates_skip += u;
  EXPECT_LT(updates_skip, updates_all) << "skipping saved no position update";
}

/// States whose value or control differs between a first sweep over every free position and
/// one that follows the front from the target (skip bound far below any change).
std::int64_t firstSweepDifferences(const SteeringModel& model, std::int64_t& updates_all,
                                   std::int64_t& updates_seeded) {
  SolverOptions all;
  all.skip_fraction = 0.0;
  all.max_sweeps = 1;
  SolverOptions seeded = all;
  seeded.skip_fraction = 1e-9;  // any change above 1e-12 makes its predecessors due
  SolveStats stats_all, stats_seeded;
  const PolicyTable a = solveValueIteration(model, all, &stats_all);
  const PolicyTable b = solveValueIteration(model, seeded, &stats_seeded);
  std::int64_t differing = 0;
  for (StateId s = 0; s < model.numStates(); ++s) {
    differing += a.value(s) != b.value(s) || a.control(s) != b.control(s) ? 1 : 0;
  }
  updates_all = stats_all.updated_per_sweep.at(0);
  updates_seeded = stats_seeded.updated_per_sweep.at(0);
  return differing;
}

TEST(SolverSkipping, FirstSweepFromTheTargetFrontEqualsAFullSweep) {
  // Before the first sweep only the target cells and the arcs ending in the target are non-zero;
  // a position none of whose successors has risen from 0 keeps its 0, so the first sweep may
  // skip it. The seeded sweep must give exactly the values and controls of a sweep over every
  // free position, with fewer updates.
  std::int64_t updates_all = 0, updates_seeded = 0;
  const SteeringModel model(noisyProblem(2e-3), 2);
  EXPECT_EQ(firstSweepDifferences(model, updates_all, updates_seeded), 0);
  EXPECT_LT(updates_seeded, updates_all) << "the first sweep recomputed every free position";

  // A target disc of radius 0.5 mm midway between four grid points (2 mm apart) holds no grid
  // point: only arcs whose exact end lies in it reach it, so the front starts from those arcs.
  SteeringProblem small = noisyProblem(2e-3);
  const GridSpec& g = model.grid();
  const int ix = g.nx * 85 / 100, iy = g.ny / 2;
  small.target.position = 0.5 * (g.point(ix, iy) + g.point(ix + 1, iy + 1));
  small.target.radius_m = 0.5e-3;
  const SteeringModel between(small, 2);
  ASSERT_EQ(std::count(between.cells().begin(), between.cells().end(),
                       static_cast<std::uint8_t>(Cell::kTarget)),
            0)
      << "the small target should hold no grid point";
  EXPECT_EQ(firstSweepDifferences(between, updates_all, updates_seeded), 0);
  EXPECT_GT(updates_seeded, 0) << "no position reaches the small target in the first sweep";
}

TEST(SolverSkipping, BadSkipFractionIsRefused) {
  const SteeringModel model(noisyProblem(4e-3), 1);
  SolverOptions o;
  o.skip_fraction = 1.5;
  EXPECT_THROW(solveValueIteration(model, o), std::invalid_argument);
}

TEST(ModelSelection, ChosenRungMeetsTheToleranceByItsOwnEstimate) {
  SelectionOptions o;
  o.ps_tolerance = 0.02;
  o.start = entryLine();
  const Result<ModelChoice> r = chooseModel(noisyProblem(4e-3), o);
  ASSERT_TRUE(r) << r.status().toString();
  const ModelChoice& c = r.value();
  ASSERT_GE(c.ladder.size(), 2u);
  EXPECT_LE(c.estimated_error, o.ps_tolerance);
  EXPECT_TRUE(std::isnan(c.ladder.front().estimated_error));
  for (std::size_t i = 1; i + 1 < c.ladder.size(); ++i) {
    EXPECT_TRUE(c.ladder[i].estimated_error > o.ps_tolerance ||
                (c.ladder[i].check.run && !c.ladder[i].check.passed))
        << "rung " << i << " already met it";
  }
  // The chosen rung was confirmed by the continuous needle, not only by its own estimate.
  EXPECT_TRUE(c.check.run);
  EXPECT_TRUE(c.check.passed) << c.check.toString();
  EXPECT_GT(c.check.entry_starts + c.check.top_starts, 0);
  EXPECT_EQ(c.check.trials_per_start, checkTrials(o.ps_tolerance));
  // Each rung halves the area of a grid cell.
  for (std::size_t i = 1; i < c.ladder.size(); ++i) {
    EXPECT_NEAR(c.ladder[i - 1].grid_spacing_m / c.ladder[i].grid_spacing_m, std::sqrt(2.0), 1e-12);
  }
  EXPECT_NEAR(c.problem.params.grid_spacing_m, c.ladder.back().grid_spacing_m, 1e-15);
  EXPECT_EQ(c.model->numStates(), c.ladder.back().states);
}

/// The rung of `params`' transitions at `spacing_m` in the ladder, or nullptr.
const ModelRung* rungAt(const ModelChoice& c, const SteeringParams& params, double spacing_m) {
  for (const ModelRung& r : c.ladder) {
    if (r.transition_model == params.transition_model &&
        r.orientation_subdivision == params.orientation_subdivision &&
        std::abs(r.grid_spacing_m / spacing_m - 1.0) < 1e-9) {
      return &r;
    }
  }
  return nullptr;
}

TEST(ModelSelection, NoCoarserGridOfTheChosenTransitionsMeetsTheTolerance) {
  // Rounded transitions on a coarse grid: the ladder refines the transitions on a finer grid,
  // then tries the coarser grids of the transitions it accepted, down to the problem's own.
  SteeringProblem p = noisyProblem(4e-3);
  p.params.transition_model = TransitionModel::kRounded;
  p.params.orientation_subdivision = 1;
  SelectionOptions o;
  o.ps_tolerance = 0.02;
  o.start = entryLine();
  const Result<ModelChoice> r = chooseModel(p, o);
  ASSERT_TRUE(r) << r.status().toString();
  const ModelChoice& c = r.value();
  const SteeringParams& chosen = c.model->params();
  const double coarser_m = chosen.grid_spacing_m * std::sqrt(2.0);
  const ModelRung* coarser = rungAt(c, chosen, coarser_m);
  if (coarser_m <= p.params.grid_spacing_m * (1.0 + 1e-9)) {
    ASSERT_NE(coarser, nullptr) << "the grid sqrt(2) coarser was never tried";
    EXPECT_TRUE(coarser->estimated_error > o.ps_tolerance ||
                (coarser->check.run && !coarser->check.passed))
        << "the coarser grid met the tolerance: " << coarser->check.toString();
  }
  // The transitions were refined on a grid finer than the problem's: after they passed, the
  // coarser grids of those transitions were solved, and every one coarser than the choice
  // failed its estimate or its check (the choice is the coarsest that passed).
  EXPECT_EQ(chosen.transition_model, TransitionModel::kInterpolated);
  int coarsened = 0;
  for (const ModelRung& rung : c.ladder) {
    if (rung.coarsened && rung.transition_model == chosen.transition_model &&
        rung.orientation_subdivision == chosen.orientation_subdivision) {
      ++coarsened;
      if (rung.grid_spacing_m > chosen.grid_spacing_m * 1.01) {
        EXPECT_TRUE(rung.estimated_error > o.ps_tolerance || (rung.check.run && !rung.check.passed))
            << "a coarser grid met the tolerance: " << rung.check.toString();
      }
    }
  }
  EXPECT_GT(coarsened, 0) << "no coarser grid of the accepted transitions was tried";
  const ModelRung* mine = rungAt(c, chosen, chosen.grid_spacing_m);
  ASSERT_NE(mine, nullptr);
  EXPECT_TRUE(mine->chosen);
  EXPECT_EQ(
      std::count_if(c.ladder.begin(), c.ladder.end(), [](const ModelRung& x) { return x.chosen; }),
      1);
  EXPECT_TRUE(c.check.run && c.check.passed) << c.check.toString();
}

TEST(ModelSelection, ToleranceBeyondTheMemoryLimitIsRefusedNamingIt) {
  SelectionOptions o;
  o.ps_tolerance = 1e-6;
  o.memory_limit_mb = 60.0;  // the coarse rungs fit, the fine ones do not
  o.start = entryLine();
  const Result<ModelChoice> r = chooseModel(noisyProblem(4e-3), o);
  ASSERT_FALSE(r);
  EXPECT_EQ(r.status().code(), StatusCode::kRefused);
  EXPECT_NE(r.status().toString().find("ps_tolerance 1e-06"), std::string::npos)
      << r.status().toString();
  EXPECT_NE(r.status().toString().find("memory limit of 60 MB"), std::string::npos)
      << r.status().toString();
  // The finest model that fits was checked and the refusal gives its measured figures.
  EXPECT_NE(r.status().toString().find("Monte Carlo check"), std::string::npos)
      << r.status().toString();
  EXPECT_NE(r.status().toString().find("FAILED"), std::string::npos) << r.status().toString();
}

TEST(ModelSelection, ChosenModelAgreesWithAnIndependentMonteCarloAtItsBestStart) {
  // Fresh seeds (not the check's): the prediction at the best start of the chosen model is
  // within the tolerance plus the binomial noise of kTrials trials.
  constexpr std::int64_t kTrials = 8000;
  constexpr double kZ = 3.0;  // a false alarm once in ~370 runs of a fixed seed: never
  SelectionOptions o;
  o.ps_tolerance = 0.02;
  o.start = entryLine();
  const Result<ModelChoice> r = chooseModel(noisyProblem(4e-3), o);
  ASSERT_TRUE(r) << r.status().toString();
  const ModelChoice& c = r.value();
  const BestStart best = c.table->bestStart(o.start);
  ASSERT_TRUE(best);
  const ContinuousWorkspace world(c.problem);
  const MonteCarloResult mc =
      runMonteCarlo(world, best.best.pose, tablePolicy(*c.table), kTrials, 977, 2);
  const double p = best.best.probability_of_success;
  EXPECT_LE(std::abs(p - mc.rate()),
            o.ps_tolerance + kZ * std::sqrt(p * (1.0 - p) / double(kTrials)))
      << "predicted " << p << ", Monte Carlo " << mc.rate();
}

TEST(ModelSelection, CheckTrialsFollowTheToleranceWithinBounds) {
  EXPECT_EQ(checkTrials(0.005), 10000);  // 0.25 / 0.005^2
  EXPECT_EQ(checkTrials(0.008), 3907);
  EXPECT_EQ(checkTrials(0.02), 2000);    // the lower bound
  EXPECT_EQ(checkTrials(0.001), 10000);  // the upper bound
}

TEST(ModelSelection, CheckWithoutTrialsThrows) {
  const SteeringModel model(noisyProblem(4e-3), 1);
  const PolicyTable table = solveValueIteration(model);
  EXPECT_THROW(checkModel(model, table, entryLine(), 0.01, 0, 1), std::invalid_argument);
}

TEST(ModelSelection, CheckThatClearlyFailsStopsAfterAQuarterOfItsTrials) {
  // The rounded model on a 4 mm grid is far from the continuous needle (gaps of several
  // hundredths): against a tolerance of 0.001 the first quarter decides.
  SteeringProblem p = noisyProblem(4e-3);
  p.params.transition_model = TransitionModel::kRounded;
  p.params.orientation_subdivision = 1;
  const SteeringModel model(p, 1);
  const PolicyTable table = solveValueIteration(model);
  const ModelCheck strict = checkModel(model, table, entryLine(), 0.001, 4000, 31);
  EXPECT_FALSE(strict.passed);
  EXPECT_TRUE(strict.clearlyFailed());
  EXPECT_EQ(strict.trials_per_start, 1000);
  EXPECT_EQ(strict.trials_requested, 4000);
  EXPECT_NE(strict.toString().find("stopped"), std::string::npos) << strict.toString();
  // Against a loose tolerance nothing is decided early: all trials run, and the figures are
  // those of one run of 4000 trials per start.
  const ModelCheck loose = checkModel(model, table, entryLine(), 0.5, 4000, 31);
  EXPECT_TRUE(loose.passed);
  EXPECT_FALSE(loose.clearlyFailed());
  EXPECT_EQ(loose.trials_per_start, 4000);
  EXPECT_GT(loose.gap_entry, strict.tolerance);  // the same model, far from 0.001
}

TEST(ModelSelection, BadToleranceThrows) {
  SelectionOptions o;
  o.ps_tolerance = 0.0;
  EXPECT_THROW(chooseModel(noisyProblem(4e-3), o), std::invalid_argument);
  o.ps_tolerance = std::nan("");
  EXPECT_THROW(chooseModel(noisyProblem(4e-3), o), std::invalid_argument);
}

TEST(SolveOrLoad, SecondCallLoadsTheChosenModelAndItsEstimate) {
  const std::string dir =
      (std::filesystem::temp_directory_path() / ("ng_select_" + std::to_string(::getpid())))
          .string();
  std::filesystem::remove_all(dir);
  SteeringProblem p = noisyProblem(4e-3);
  p.ps_tolerance = 0.02;
  SelectionOptions o;
  o.start = entryLine();
  const Result<PolicySource> first = solveOrLoad(p, "test", dir, o);
  ASSERT_TRUE(first) << first.status().toString();
  EXPECT_EQ(first.value().source, "solved");
  const Result<PolicySource> second = solveOrLoad(p, "test", dir, o);
  ASSERT_TRUE(second) << second.status().toString();
  EXPECT_EQ(second.value().source, "loaded");
  // The same model, transitions included (the selection may refine them).
  EXPECT_EQ(second.value().model->hash(), first.value().model->hash());
  EXPECT_EQ(second.value().model->params().orientation_subdivision,
            first.value().model->params().orientation_subdivision);
  EXPECT_DOUBLE_EQ(second.value().estimated_error, first.value().estimated_error);
  EXPECT_EQ(second.value().table->values(), first.value().table->values());
  const Result<PolicySource> forced = solveOrLoad(p, "test", dir, o, true);
  ASSERT_TRUE(forced);
  EXPECT_EQ(forced.value().source, "solved");
  // A choice recorded without the check's groups (made by another check) is not loaded.
  std::string record;
  for (const auto& entry : std::filesystem::directory_iterator(dir)) {
    if (entry.path().extension() == ".choice") {
      record = entry.path().string();
    }
  }
  ASSERT_FALSE(record.empty()) << "no .choice file in " << dir;
  EXPECT_NE(record.find("_check-"), std::string::npos) << record;
  {
    std::ifstream in(record);
    std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    const std::size_t check_line = text.find("model_check ");
    ASSERT_NE(check_line, std::string::npos) << text;
    in.close();
    std::ofstream(record) << text.substr(0, check_line);
  }
  const Result<PolicySource> other_check = solveOrLoad(p, "test", dir, o);
  ASSERT_TRUE(other_check) << other_check.status().toString();
  EXPECT_EQ(other_check.value().source, "solved");
  // Without a tolerance: the grid as given, no estimate.
  p.ps_tolerance = 0.0;
  const Result<PolicySource> fixed = solveOrLoad(p, "test", "", o);
  ASSERT_TRUE(fixed);
  EXPECT_NEAR(fixed.value().model->params().grid_spacing_m, 4e-3, 1e-15);
  EXPECT_TRUE(std::isnan(fixed.value().estimated_error));
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace needle_guidance::steering

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}

namespace needle_guidance::steering {
namespace {

TEST(NearBoundaryStarts, WithinFiveMillimetresOfEveryBoundaryInsideTheFreeSpace) {
  // Every start lies in the free space within kNearMax_m of a workspace edge or an expanded
  // obstacle edge; both ends of the entry line and every face of the block facing the free space
  // have starts.
  constexpr double kNearMax_m = 5e-3;
  constexpr double kOnBoundary_m = 1e-9;
  const SteeringProblem p = noisyProblem(2e-3);
  const SteeringModel model(p, 2);
  const PolicyTable table = solveValueIteration(model);
  const ContinuousWorkspace world(p);
  const StartOptions start = entryLine();
  const std::vector<NearBoundaryStart> starts = nearBoundaryStarts(start, table, world);
  ASSERT_FALSE(starts.empty());
  int low_end = 0, high_end = 0;
  int face[4] = {0, 0, 0, 0};  // the block's faces: left, right, below, above
  for (const NearBoundaryStart& s : starts) {
    const Point2 q = s.pose.p_SceneTip;
    EXPECT_TRUE(world.inWorkspace(q)) << q.transpose();
    EXPECT_LT(world.obstacleAt(q), 0) << q.transpose();
    EXPECT_FALSE(world.inTarget(q)) << q.transpose();
    double nearest = std::min({q.x() - p.workspace_min.x(), p.workspace_max.x() - q.x(),
                               q.y() - p.workspace_min.y(), p.workspace_max.y() - q.y()});
    double to_obstacle = std::numeric_limits<double>::infinity();
    for (const geometry::Polygon& poly : world.expandedObstacles()) {
      to_obstacle = std::min(to_obstacle, poly.distanceToBoundary(q));
    }
    nearest = std::min(nearest, to_obstacle);
    EXPECT_LE(nearest, kNearMax_m) << s.group << " start at " << q.transpose();
    EXPECT_TRUE(s.group == "edge" || s.group == "obstacle") << s.group;
    if (s.group == "obstacle") {
      EXPECT_LE(to_obstacle, kNearMax_m) << q.transpose();
      EXPECT_GT(to_obstacle, kOnBoundary_m) << q.transpose();
      face[0] += q.x() < 0.045 ? 1 : 0;
      face[1] += q.x() > 0.055 ? 1 : 0;
      face[2] += q.y() < 0.04 ? 1 : 0;
      face[3] += q.y() > 0.06 ? 1 : 0;
    }
    if (std::abs(q.x() - start.start_x_m) < kOnBoundary_m) {
      low_end += q.y() - start.min_height_m <= kNearMax_m ? 1 : 0;
      high_end += start.max_height_m - q.y() <= kNearMax_m ? 1 : 0;
    }
  }
  // 2 heights x 3 angles x 2 bevels at each end of the entry line.
  EXPECT_EQ(low_end, 12);
  EXPECT_EQ(high_end, 12);
  // Each face of the block (the one facing the target included: P_s > 0.01 there).
  for (int f = 0; f < 4; ++f) {
    EXPECT_GE(face[f], 1) << "no start beside face " << f << " of the block";
  }
}

TEST(NearBoundaryStarts, InteriorStartTakesTheBestStateOfItsGridPoint) {
  const SteeringProblem p = noisyProblem(2e-3);
  const SteeringModel model(p, 2);
  const PolicyTable table = solveValueIteration(model);
  const ContinuousWorkspace world(p);
  for (const NearBoundaryStart& s : nearBoundaryStarts(entryLine(), table, world)) {
    if (s.pose.p_SceneTip.x() < 1e-9) {
      continue;  // the entry line: fixed angles
    }
    const double best = table.lookup(s.pose).probability_of_success;
    EXPECT_GE(best, 0.01);
    for (double turn : {0.3, 1.0, 2.0}) {
      TipPose other = s.pose;
      other.theta_rad += turn;
      EXPECT_GE(best, table.lookup(other).probability_of_success) << s.pose.p_SceneTip.transpose();
    }
  }
}

TEST(ModelSelection, BoundaryGroupFailureEscalatesARoundedModelTheOtherGroupsAccept) {
  // The rounded model on a 2.83 mm grid meets the tolerance on the entry line and at the best
  // starts, but next to the block and the edges its gaps are larger: the near-boundary group
  // fails the check, so the selection goes on (here to a finer grid, as the grid's own change
  // explains the gap) and the model it chooses meets the tolerance in every group.
  constexpr double kTolerance = 0.08;  // mean |P_s error| [-]; the 2.83 mm gaps: 0.05 / 0.09
  SteeringProblem p = noisyProblem(4e-3);
  p.params.transition_model = TransitionModel::kRounded;
  p.params.orientation_subdivision = 1;
  SelectionOptions o;
  o.ps_tolerance = kTolerance;
  o.start = entryLine();
  const Result<ModelChoice> r = chooseModel(p, o);
  ASSERT_TRUE(r) << r.status().toString();
  const std::vector<ModelRung>& ladder = r.value().ladder;
  ASSERT_GE(ladder.size(), 3u);
  const ModelRung& rounded = ladder[1];
  EXPECT_EQ(rounded.transition_model, TransitionModel::kRounded);
  ASSERT_TRUE(rounded.check.run) << "its estimate should have made it a candidate";
  EXPECT_LE(rounded.check.gap_entry, kTolerance) << rounded.check.toString();
  EXPECT_LE(rounded.check.gap_top, kTolerance) << rounded.check.toString();
  EXPECT_GT(rounded.check.gap_boundary, kTolerance) << rounded.check.toString();
  EXPECT_GT(rounded.check.boundary_starts, 0);
  EXPECT_FALSE(rounded.check.passed);
  EXPECT_FALSE(rounded.chosen);
  const ModelCheck& chosen = r.value().check;
  ASSERT_TRUE(chosen.run);
  EXPECT_TRUE(chosen.passed) << chosen.toString();
  EXPECT_LE(chosen.gap_boundary, kTolerance) << chosen.toString();
  EXPECT_LT(r.value().problem.params.grid_spacing_m, rounded.grid_spacing_m);
  EXPECT_NE(chosen.toString().find("near boundaries"), std::string::npos) << chosen.toString();
}

/// A checked rung of the ladder with the given group gaps.
ModelRung checkedRung(double grid_m, TransitionModel transitions, double entry, double top,
                      double boundary, double tolerance) {
  ModelRung r;
  r.grid_spacing_m = grid_m;
  r.transition_model = transitions;
  r.check.run = true;
  r.check.tolerance = tolerance;
  r.check.gap_entry = entry;
  r.check.gap_top = top;
  r.check.gap_boundary = boundary;
  r.check.passed = entry <= tolerance && top <= tolerance && boundary <= tolerance;
  return r;
}

TEST(ModelSelection, FinerGridThatDoesNotShrinkAFailingGroupDoesNotExplainIt) {
  constexpr double kTol = 0.01;  // [P_s]
  const TransitionModel kR = TransitionModel::kRounded;
  std::vector<ModelRung> ladder;
  EXPECT_FALSE(finerGridDidNotHelp(ladder));
  ladder.push_back(checkedRung(6e-4, kR, 0.005, 0.0, 0.011, kTol));
  EXPECT_FALSE(finerGridDidNotHelp(ladder)) << "no earlier rung to compare with";
  ModelRung unchecked;  // a rung whose estimate did not make it a candidate is passed over
  unchecked.grid_spacing_m = 5e-4;
  unchecked.transition_model = kR;
  ladder.push_back(unchecked);
  ladder.push_back(checkedRung(4.2e-4, kR, 0.0068, 0.0145, 0.0134, kTol));
  EXPECT_TRUE(finerGridDidNotHelp(ladder)) << "the near-boundary gap grew from 0.011 to 0.0134";
  ladder.back() = checkedRung(4.2e-4, kR, 0.0068, 0.0145, 0.0105, kTol);
  EXPECT_FALSE(finerGridDidNotHelp(ladder)) << "the near-boundary gap shrank";
  // Another group failing only on the finer grid does not count (nothing to compare).
  EXPECT_GT(ladder.back().check.gap_top, kTol);
  // A coarser rung of other transitions is no comparison.
  ladder.back() = checkedRung(4.2e-4, TransitionModel::kInterpolated, 0.0, 0.0, 0.02, kTol);
  EXPECT_FALSE(finerGridDidNotHelp(ladder));
}

}  // namespace
}  // namespace needle_guidance::steering
