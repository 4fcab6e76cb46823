// SteerableNeedle: the continuous needle of dissertation 5.3 as the insertion robot's world —
// exact arcs, seeded deflections with the right sigma, contact against expanded obstacles and
// the workspace, exact retraction, refusals that change nothing, and the journal.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/math.h"
#include "needle_guidance/robot/steerable_needle.h"

namespace needle_guidance::robot {
namespace {

using needle_model::ArcOutcome;
using needle_model::Bevel;
using needle_model::Control;
using needle_model::TipPose;

constexpr double kDeg = kPi / 180.0;
constexpr double kExactTol_m = 1e-12;  // same formula, same inputs: rounding only
constexpr double kExactAngleTol_rad = 1e-12;
constexpr double kContactTol_m = 1e-5;  // chord tolerance of the contact check
constexpr double kBruteStep_m = 1e-6;   // brute-force search step along an arc
constexpr std::uint64_t kSeed = 7;
constexpr int kSamples = 2000;
constexpr int kOrientations = 40;  // control-circle arcs: one insertion step is 2 pi r / 40
// Sample statistics of n = 2000 normal draws: the mean has standard error sigma / sqrt(n), the
// standard deviation about sigma / sqrt(2 n); each is checked at 4 standard errors (two-sided
// 6e-5 per check for an unlucky stream; the seed is fixed anyway).
constexpr double kMeanTol = 0.0894427191;  // 4 / sqrt(2000), x sigma
constexpr double kStdTol = 0.0632455532;   // 4 / sqrt(2 * 2000), x sigma

/// A 10 x 10 cm workspace with one rectangular obstacle "block" (x 3..4 cm, y 0..6 cm, 1 mm
/// clearance) and r = 5 cm: fixed here so that edits of the scene files do not move
/// the contacts these tests expect.
needle_model::PlanarWorkspace blockProblem() {
  needle_model::PlanarWorkspace p;
  p.workspace_min = {0.0, 0.0};
  p.workspace_max = {0.1, 0.1};
  scene::Obstacle block;
  block.name = "block";
  block.polygon = geometry::Polygon({{0.03, 0.0}, {0.04, 0.0}, {0.04, 0.06}, {0.03, 0.06}});
  block.clearance_m = 0.001;
  p.obstacles.push_back(block);
  p.target.name = "target";
  p.target.position = {0.085, 0.05};
  p.target.radius_m = 0.005;
  p.radius_m = 0.05;
  return p;
}

SteerableNeedleConfig config(double sigma_insert_rad, double sigma_flip_rad,
                             std::uint64_t seed = kSeed) {
  SteerableNeedleConfig c;
  c.start_x_m = 0.0;
  c.min_height_m = 0.0;
  c.max_height_m = 0.1;
  c.sigma_insert_rad = sigma_insert_rad;
  c.sigma_flip_rad = sigma_flip_rad;
  c.seed = seed;
  return c;
}

EntryPose entry(double height_m, double angle_rad = 0.0, Bevel bevel = Bevel::kLeft) {
  EntryPose e;
  e.height_m = height_m;
  e.angle_rad = angle_rad;
  e.bevel = bevel;
  return e;
}

TipPose poseOf(const EntryPose& e, double start_x_m) {
  TipPose p;
  p.p_SceneTip = {start_x_m, e.height_m};
  p.theta_rad = e.angle_rad;
  p.bevel = e.bevel;
  return p;
}

void expectPose(const TipPose& actual, const TipPose& expected, double tol_m, double tol_rad) {
  EXPECT_NEAR(actual.p_SceneTip.x(), expected.p_SceneTip.x(), tol_m);
  EXPECT_NEAR(actual.p_SceneTip.y(), expected.p_SceneTip.y(), tol_m);
  EXPECT_NEAR(actual.theta_rad, expected.theta_rad, tol_rad);
  EXPECT_EQ(actual.bevel, expected.bevel);
}

/// Everything a refusal must leave unchanged.
struct Snapshot {
  double length_m;
  TipPose tip;
  std::size_t segments;
  EntryPose entry;
  bool contact;
  bool flip_pending;
  bool insertion_open;
  std::uint64_t draws;
};
Snapshot snapshot(const SteerableNeedle& n) {
  return {n.insertedLength_m(), n.tip(),         n.segments().size(), n.entry(),
          n.inContact(),        n.flipPending(), n.insertionOpen(),   n.deflectionsDrawn()};
}
void expectUnchanged(const Snapshot& a, const SteerableNeedle& n) {
  const Snapshot b = snapshot(n);
  EXPECT_EQ(a.length_m, b.length_m);
  EXPECT_EQ(a.tip.p_SceneTip, b.tip.p_SceneTip);
  EXPECT_EQ(a.tip.theta_rad, b.tip.theta_rad);
  EXPECT_EQ(a.tip.bevel, b.tip.bevel);
  EXPECT_EQ(a.segments, b.segments);
  EXPECT_EQ(a.entry.height_m, b.entry.height_m);
  EXPECT_EQ(a.entry.angle_rad, b.entry.angle_rad);
  EXPECT_EQ(a.entry.bevel, b.entry.bevel);
  EXPECT_EQ(a.contact, b.contact);
  EXPECT_EQ(a.flip_pending, b.flip_pending);
  EXPECT_EQ(a.insertion_open, b.insertion_open);
  EXPECT_EQ(a.draws, b.draws);
}

/// The first arc length at which the arc from `from` (bevel as given, no deflection) enters the
/// polygon, found by stepping kBruteStep_m; -1 if not within max_length_m.
double bruteForceEntry(const TipPose& from, double radius_m, const geometry::Polygon& polygon,
                       double max_length_m) {
  const auto steps = static_cast<long>(max_length_m / kBruteStep_m);
  for (long i = 0; i <= steps; ++i) {
    const double s = static_cast<double>(i) * kBruteStep_m;
    const TipPose p = needle_model::advanceTip(from, Control::kInsert, 0.0, s, radius_m);
    if (polygon.contains(p.p_SceneTip)) {
      return s;
    }
  }
  return -1.0;
}

class SteerableNeedleTest : public ::testing::Test {
protected:
  SteerableNeedleTest() : problem_(blockProblem()) {}
  double radius_m() const { return problem_.radius_m; }
  /// One insertion step: a 40th of the control circle (N_c = 40).
  double delta_m() const { return 2.0 * kPi * radius_m() / kOrientations; }

  needle_model::PlanarWorkspace problem_;
};

TEST_F(SteerableNeedleTest, WithoutDeflectionTheTipFollowsAdvanceTipExactly) {
  const SteerableNeedleConfig c = config(0.0, 0.0);
  const EntryPose e = entry(0.02);
  SteerableNeedle needle(problem_, c, e);
  const TipPose w0 = poseOf(e, c.start_x_m);
  expectPose(needle.tip(), w0, 0.0, 0.0);

  ASSERT_TRUE(needle.insertTo(delta_m()));
  const TipPose w1 = needle_model::advanceTip(w0, Control::kInsert, 0.0, delta_m(), radius_m());
  expectPose(needle.tip(), w1, kExactTol_m, kExactAngleTol_rad);
  EXPECT_DOUBLE_EQ(needle.insertedLength_m(), delta_m());

  ASSERT_TRUE(needle.flip());
  EXPECT_EQ(needle.bevel(), Bevel::kRight);
  EXPECT_TRUE(needle.flipPending());
  ASSERT_TRUE(needle.insertTo(2.0 * delta_m()));
  const TipPose w2 = needle_model::advanceTip(w1, Control::kFlip, 0.0, delta_m(), radius_m());
  expectPose(needle.tip(), w2, kExactTol_m, kExactAngleTol_rad);
  EXPECT_FALSE(needle.flipPending());
  ASSERT_EQ(needle.segments().size(), 2u);
  EXPECT_EQ(needle.segments()[1].control, Control::kFlip);

  // Advancing in many small steps (as the robot's control loop does) ends at the same pose.
  ASSERT_TRUE(needle.beginInsertion());
  for (int i = 1; i <= 100; ++i) {
    ASSERT_TRUE(needle.advanceTo(2.0 * delta_m() + 0.5 * delta_m() * i / 100));
  }
  const TipPose w3 =
      needle_model::advanceTip(w2, Control::kInsert, 0.0, 0.5 * delta_m(), radius_m());
  expectPose(needle.tip(), w3, kExactTol_m, kExactAngleTol_rad);
  // tipAt follows the path: the end of each command and the middle of the first arc.
  expectPose(needle.tipAt(delta_m()), w1, kExactTol_m, kExactAngleTol_rad);
  expectPose(needle.tipAt(0.5 * delta_m()),
             needle_model::advanceTip(w0, Control::kInsert, 0.0, 0.5 * delta_m(), radius_m()),
             kExactTol_m, kExactAngleTol_rad);
  EXPECT_THROW(needle.tipAt(3.0 * delta_m()), std::out_of_range);
  const auto points = needle.pathPoints(1e-3);
  EXPECT_EQ(points.front(), w0.p_SceneTip);
  EXPECT_NEAR((points.back() - w3.p_SceneTip).norm(), 0.0, kExactTol_m);
  EXPECT_GE(points.size(), 20u);  // 2.5 delta = 19.6 mm at <= 1 mm spacing
}

TEST_F(SteerableNeedleTest, DeflectionsTurnTheStartOfEachInsertion) {
  const SteerableNeedleConfig c = config(5 * kDeg, 10 * kDeg);
  SteerableNeedle needle(problem_, c, entry(0.05));
  const TipPose w0 = needle.tip();
  ASSERT_TRUE(needle.insertTo(delta_m()));
  const NeedleSegment& s = needle.segments().front();
  EXPECT_NE(s.beta_rad, 0.0);
  EXPECT_EQ(s.sigma_rad, c.sigma_insert_rad);
  expectPose(needle.tip(),
             needle_model::advanceTip(w0, Control::kInsert, s.beta_rad, delta_m(), radius_m()),
             kExactTol_m, kExactAngleTol_rad);
  const TipPose w1 = needle.tip();
  needle.flip();
  ASSERT_TRUE(needle.insertTo(2.0 * delta_m()));
  const NeedleSegment& f = needle.segments().back();
  EXPECT_EQ(f.sigma_rad, c.sigma_flip_rad);
  EXPECT_EQ(f.draw_index, 1u);
  expectPose(needle.tip(),
             needle_model::advanceTip(w1, Control::kFlip, f.beta_rad, delta_m(), radius_m()),
             kExactTol_m, kExactAngleTol_rad);
}

std::vector<double> drawBetas(const needle_model::PlanarWorkspace& problem,
                              const SteerableNeedleConfig& c, int n, bool flip_each) {
  SteerableNeedle needle(problem, c, entry(0.05));
  std::vector<double> betas;
  for (int i = 0; i < n; ++i) {
    if (flip_each) {
      needle.flip();
    }
    EXPECT_TRUE(needle.beginInsertion());
    betas.push_back(needle.segments().back().beta_rad);
    EXPECT_EQ(needle.segments().back().sigma_rad,
              flip_each ? c.sigma_flip_rad : c.sigma_insert_rad);
    EXPECT_TRUE(needle.retractTo(0.0));
  }
  return betas;
}

TEST_F(SteerableNeedleTest, SameSeedSameDeflectionsOtherSeedOthers) {
  const auto a = drawBetas(problem_, config(5 * kDeg, 10 * kDeg, 11), 50, false);
  const auto b = drawBetas(problem_, config(5 * kDeg, 10 * kDeg, 11), 50, false);
  const auto other = drawBetas(problem_, config(5 * kDeg, 10 * kDeg, 12), 50, false);
  EXPECT_EQ(a, b);
  int equal = 0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    equal += a[i] == other[i] ? 1 : 0;
  }
  EXPECT_EQ(equal, 0);
  // The stream does not depend on the sigmas: the same z, scaled.
  const auto doubled = drawBetas(problem_, config(10 * kDeg, 10 * kDeg, 11), 50, false);
  for (std::size_t i = 0; i < a.size(); ++i) {
    EXPECT_NEAR(doubled[i], 2.0 * a[i], 1e-15);
  }
}

void expectNormal(const std::vector<double>& betas, double sigma) {
  double mean = 0.0;
  for (double b : betas) {
    mean += b;
  }
  mean /= betas.size();
  double var = 0.0;
  for (double b : betas) {
    var += (b - mean) * (b - mean);
  }
  const double std_dev = std::sqrt(var / (betas.size() - 1));
  EXPECT_NEAR(mean, 0.0, kMeanTol * sigma);
  EXPECT_NEAR(std_dev, sigma, kStdTol * sigma);
  // And the shape: about 68.3 % within one sigma (binomial standard error, 4 SE).
  int within = 0;
  for (double b : betas) {
    within += std::abs(b) <= sigma ? 1 : 0;
  }
  const double p = 0.6826894921370859;
  EXPECT_NEAR(double(within) / betas.size(), p, 4.0 * std::sqrt(p * (1 - p) / betas.size()));
}

TEST_F(SteerableNeedleTest, DeflectionsAreNormalWithSigmaInsertOrSigmaFlip) {
  const SteerableNeedleConfig c = config(5 * kDeg, 10 * kDeg);
  expectNormal(drawBetas(problem_, c, kSamples, false), c.sigma_insert_rad);
  expectNormal(drawBetas(problem_, c, kSamples, true), c.sigma_flip_rad);
  // Two flips in a row still mark the next insertion as following a direction change.
  SteerableNeedle needle(problem_, c, entry(0.05));
  needle.flip();
  needle.flip();
  EXPECT_EQ(needle.bevel(), Bevel::kLeft);
  ASSERT_TRUE(needle.beginInsertion());
  EXPECT_EQ(needle.segments().back().sigma_rad, c.sigma_flip_rad);
  // A retraction does not cancel a pending flip; a new entry does.
  needle.flip();
  ASSERT_TRUE(needle.retractTo(0.0));
  EXPECT_TRUE(needle.flipPending());
  ASSERT_TRUE(needle.setEntry(entry(0.04)));
  EXPECT_FALSE(needle.flipPending());
}

TEST_F(SteerableNeedleTest, InsertionIntoAnObstacleStopsAtTheContactAndIsRefusedAfterwards) {
  const SteerableNeedleConfig c = config(0.0, 0.0);
  const EntryPose e = entry(0.02);
  SteerableNeedle needle(problem_, c, e);
  ASSERT_TRUE(needle.insertTo(delta_m()));
  needle.flip();
  ASSERT_TRUE(needle.insertTo(2.0 * delta_m()));
  // Bevel right from (1.57 cm, 2.12 cm) heading +x: the arc bends down and meets the block's
  // expanded left side x = 2.9 cm at y = 1.94 cm.
  const TipPose before = needle.tip();
  const double target_m = 2.0 * delta_m() + 0.03;
  const MotionStatus status = needle.insertTo(target_m);
  ASSERT_EQ(status.outcome(), MotionOutcome::kContact) << status.toString();
  EXPECT_FALSE(status);
  EXPECT_NE(status.toString().find("'block'"), std::string::npos) << status.toString();
  ASSERT_TRUE(needle.inContact());
  const NeedleContact contact = needle.contact();
  EXPECT_EQ(contact.outcome, ArcOutcome::kObstacle);
  EXPECT_EQ(contact.obstacle, "block");
  EXPECT_LT(needle.insertedLength_m(), target_m);
  EXPECT_EQ(contact.length_m, needle.insertedLength_m());
  EXPECT_EQ(contact.pose.p_SceneTip, needle.tip().p_SceneTip);

  // The contact point lies on the expanded obstacle's boundary, and it is the first one.
  const geometry::Polygon& expanded = needle.world().expandedObstacles().front();
  EXPECT_NEAR(contact.pose.p_SceneTip.x(), 0.029, kContactTol_m);
  EXPECT_LT(expanded.distanceToBoundary(contact.pose.p_SceneTip), kContactTol_m);
  const double brute_m = bruteForceEntry(before, radius_m(), expanded, 0.03);
  ASSERT_GT(brute_m, 0.0);
  EXPECT_NEAR(needle.insertedLength_m() - 2.0 * delta_m(), brute_m, 2.0 * kContactTol_m);
  // The tip is still on its arc (no deflection: sigma = 0).
  expectPose(needle.tip(),
             needle_model::advanceTip(before, Control::kInsert, 0.0,
                                      needle.insertedLength_m() - 2.0 * delta_m(), radius_m()),
             kExactTol_m, kExactAngleTol_rad);

  // Further insertion is refused and changes nothing (no deflection drawn either).
  const Snapshot stuck = snapshot(needle);
  EXPECT_EQ(needle.insertTo(target_m).outcome(), MotionOutcome::kRefused);
  EXPECT_FALSE(needle.beginInsertion());
  EXPECT_EQ(needle.advanceTo(target_m).outcome(), MotionOutcome::kRefused);
  expectUnchanged(stuck, needle);
  // Retracting to the contact length itself keeps the contact...
  ASSERT_TRUE(needle.retractTo(needle.insertedLength_m()));
  EXPECT_TRUE(needle.inContact());
  // ...retracting past it clears it, and the tip is back on its own path.
  const double back_m = contact.length_m - 0.002;
  ASSERT_TRUE(needle.retractTo(back_m));
  EXPECT_FALSE(needle.inContact());
  expectPose(
      needle.tip(),
      needle_model::advanceTip(before, Control::kInsert, 0.0, back_m - 2.0 * delta_m(), radius_m()),
      kExactTol_m, kExactAngleTol_rad);
  EXPECT_TRUE(needle.insertTo(back_m + 0.001));  // free again
  // Retracting to 0 restores the entry pose exactly (the bevel stays where it was turned).
  ASSERT_TRUE(needle.retractTo(0.0));
  EXPECT_EQ(needle.insertedLength_m(), 0.0);
  EXPECT_TRUE(needle.segments().empty());
  TipPose expected = poseOf(e, c.start_x_m);
  expected.bevel = Bevel::kRight;
  expectPose(needle.tip(), expected, 0.0, 0.0);
  needle.flip();
  expectPose(needle.tip(), poseOf(e, c.start_x_m), 0.0, 0.0);
}

TEST_F(SteerableNeedleTest, LeavingTheWorkspaceStopsOnItsBoundary) {
  const SteerableNeedleConfig c = config(0.0, 0.0);
  SteerableNeedle needle(problem_, c, entry(0.09));
  // Bevel left from (0, 9 cm) heading +x: y = 9 + 5 (1 - cos phi) cm reaches 10 cm at
  // cos phi = 0.8, after r phi = 3.22 cm, at x = r sin phi = 3 cm.
  const MotionStatus status = needle.insertTo(0.05);
  ASSERT_EQ(status.outcome(), MotionOutcome::kContact) << status.toString();
  EXPECT_NE(status.toString().find("left the workspace"), std::string::npos) << status.toString();
  EXPECT_EQ(needle.contact().outcome, ArcOutcome::kLeftWorkspace);
  EXPECT_NEAR(needle.insertedLength_m(), radius_m() * std::acos(0.8), 2.0 * kContactTol_m);
  EXPECT_NEAR(needle.tip().p_SceneTip.x(), 0.03, 2.0 * kContactTol_m);
  EXPECT_NEAR(needle.tip().p_SceneTip.y(), 0.10, kContactTol_m);
  EXPECT_EQ(needle.insertTo(0.06).outcome(), MotionOutcome::kRefused);
}

TEST_F(SteerableNeedleTest, SetEntryIsRefusedInTissueAndForBadValuesChangingNothing) {
  const SteerableNeedleConfig c = config(5 * kDeg, 10 * kDeg);
  SteerableNeedle needle(problem_, c, entry(0.05));
  ASSERT_TRUE(needle.setEntry(entry(0.03, 0.2, Bevel::kRight)));
  EXPECT_EQ(needle.tip().bevel, Bevel::kRight);
  EXPECT_EQ(needle.tip().theta_rad, 0.2);
  ASSERT_TRUE(needle.insertTo(0.005));
  ASSERT_TRUE(needle.retractTo(0.005));  // ends the open insertion, moves nothing
  const double nan = std::numeric_limits<double>::quiet_NaN();

  Snapshot before = snapshot(needle);
  const CommandStatus in_tissue = needle.setEntry(entry(0.04));
  EXPECT_FALSE(in_tissue);
  EXPECT_NE(in_tissue.toString().find("in tissue"), std::string::npos) << in_tissue.toString();
  expectUnchanged(before, needle);
  EXPECT_EQ(needle.retractTo(-0.001).outcome(), MotionOutcome::kRefused);
  EXPECT_EQ(needle.retractTo(0.006).outcome(), MotionOutcome::kRefused);
  EXPECT_EQ(needle.retractTo(nan).outcome(), MotionOutcome::kRefused);
  EXPECT_EQ(needle.advanceTo(0.006).outcome(), MotionOutcome::kRefused);  // no open insertion
  EXPECT_EQ(needle.insertTo(0.004).outcome(), MotionOutcome::kRefused);   // backwards
  EXPECT_EQ(needle.insertTo(nan).outcome(), MotionOutcome::kRefused);
  expectUnchanged(before, needle);

  ASSERT_TRUE(needle.retractTo(0.0));
  before = snapshot(needle);
  EXPECT_FALSE(needle.setEntry(entry(0.04, 1.6)));   // angle > pi/2
  EXPECT_FALSE(needle.setEntry(entry(0.04, -1.6)));  // angle < -pi/2
  EXPECT_FALSE(needle.setEntry(entry(nan)));
  EXPECT_FALSE(needle.setEntry(entry(0.04, nan)));
  EXPECT_FALSE(needle.setEntry(entry(0.04, std::numeric_limits<double>::infinity())));
  const CommandStatus too_high = needle.setEntry(entry(0.11));  // heights 0..10 cm
  EXPECT_FALSE(too_high);
  EXPECT_NE(too_high.toString().find("height range"), std::string::npos) << too_high.toString();
  EXPECT_FALSE(needle.setEntry(entry(-0.001)));
  expectUnchanged(before, needle);
  EXPECT_TRUE(needle.setEntry(entry(0.0, -kPi / 2)));  // the bounds themselves are allowed
  EXPECT_TRUE(needle.setEntry(entry(0.1, kPi / 2)));

  EXPECT_THROW(SteerableNeedle(problem_, c, entry(0.2)), std::invalid_argument);
  EXPECT_THROW(SteerableNeedle(problem_, config(-1.0, 0.0), entry(0.05)), std::invalid_argument);
  EXPECT_THROW(SteerableNeedle(problem_, config(0.0, nan), entry(0.05)), std::invalid_argument);
}

TEST_F(SteerableNeedleTest, JournalRecordsEveryCommandAndDeflection) {
  const std::string path = ::testing::TempDir() + "steerable_needle_journal_test.csv";
  std::remove(path.c_str());
  const SteerableNeedleConfig c = config(5 * kDeg, 10 * kDeg);
  SteerableNeedle needle(problem_, c, entry(0.05));
  {
    NeedleJournalFile file(path);
    needle.setJournalSink([&file](const NeedleJournalEntry& e) { file.write(e, 1.5); });
    needle.setEntry(entry(0.04));
    needle.insertTo(0.01);
    needle.flip();
    needle.insertTo(0.02);
    needle.setEntry(entry(0.03));  // refused: in tissue
    needle.retractTo(0.0);
  }
  const auto& j = needle.journal();
  std::vector<std::string> events;
  events.reserve(j.size());
  for (const auto& e : j) {
    events.push_back(e.event + (e.accepted ? "" : "!"));
  }
  EXPECT_EQ(events, (std::vector<std::string>{"set_entry", "insert", "advance", "flip", "insert",
                                              "advance", "set_entry!", "retract"}));
  for (std::size_t i = 0; i < j.size(); ++i) {
    EXPECT_EQ(j[i].sequence, i);
  }
  EXPECT_EQ(j[1].draw_index, 0);
  EXPECT_EQ(j[1].sigma_rad, c.sigma_insert_rad);
  EXPECT_EQ(j[1].beta_rad, needle.journal()[1].beta_rad);
  EXPECT_EQ(j[4].draw_index, 1);
  EXPECT_EQ(j[4].sigma_rad, c.sigma_flip_rad);
  EXPECT_EQ(j[2].draw_index, -1);
  EXPECT_NEAR(j[5].length_m, 0.02, 1e-15);

  std::ifstream in(path);
  std::vector<std::string> lines;
  for (std::string line; std::getline(in, line);) {
    lines.push_back(line);
  }
  ASSERT_EQ(lines.size(), j.size() + 1);
  EXPECT_EQ(lines[0], NeedleJournalFile::header());
  EXPECT_NE(lines[2].find(",insert,1,"), std::string::npos) << lines[2];
  EXPECT_NE(lines[7].find(",set_entry,0,"), std::string::npos) << lines[7];
  EXPECT_NE(lines[7].find("in tissue"), std::string::npos) << lines[7];
  EXPECT_THROW(NeedleJournalFile("/nonexistent_dir/x.csv"), std::runtime_error);
  std::remove(path.c_str());
}

}  // namespace
}  // namespace needle_guidance::robot

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
