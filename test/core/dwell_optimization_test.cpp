// HDR dwell-time optimisation (dissertation ch. 6): a hand-solved LP, LP <= SA, the dual and
// ranged-row formulations agree, MPS and case-folder round trips, indices, and the hard cases
// (D_min > D_max, no dose points, catheter outside the body, no dwell positions,
// duplicate dwell positions, a dose point on a dwell position).
#include <gtest/gtest.h>

#include <ClpSimplex.hpp>
#include <cmath>
#include <filesystem>
#include <fstream>

#include "needle_guidance/dose/case_folder.h"
#include "needle_guidance/dose/dose_indices.h"
#include "needle_guidance/dose/dwell_optimization.h"
#include "needle_guidance/dose/prostate_case.h"

namespace needle_guidance::dose {
namespace {

constexpr double kTime_s = 1e-6;        // LP dwell-time tolerance
constexpr double kObjectiveRel = 1e-6;  // LP objective agreement between formulations

/// One dwell, two points: a target point (dose rate 1 Gy/s, [10, 15] Gy, weights 100/100) and
/// an OAR point (0.6 Gy/s, max 5 Gy, weight 20). E(t) = 100 max(0, 10 - t) + 100 max(0, t - 15)
/// + 20 max(0, 0.6 t - 5): slopes -100 + 12 below t = 10, +12 above, so t* = 10 s and
/// E* = 20 (0.6 * 10 - 5) = 20.
struct TinyCase {
  HdrCase c;
  Eigen::MatrixXd d;
  TinyCase() {
    c.name = "tiny";
    c.structures = {{"target", StructureRole::kTarget, {}},
                    {"oar", StructureRole::kOrganAtRisk, {}}};
    c.catheters = {{"c1", {Point3(0, 0, 0.01), Point3(0, 0, -0.05)}}};
    c.dwells = {{0, 0, Point3::Zero(), Point3::UnitZ()}};
    c.points = {{0, PointKind::kVolume, Point3(0.01, 0, 0)},
                {1, PointKind::kVolume, Point3(0.02, 0, 0)}};
    c.criteria = {{"target", PointKind::kVolume, 10.0, 15.0, 100.0, 100.0},
                  {"oar", PointKind::kVolume, 0.0, 5.0, 0.0, 20.0}};
    d.resize(2, 1);
    d << 1.0, 0.6;
  }
};

TEST(DwellOptimization, LpSolvesTheHandComputedCase) {
  TinyCase t;
  for (bool dual : {true, false}) {
    LpOptions o;
    o.dual_formulation = dual;
    const DwellResult r = optimizeLp(t.c, t.d, o);
    ASSERT_TRUE(r.ok()) << r.status;
    EXPECT_NEAR(r.times_s.at(0), 10.0, kTime_s) << "dual " << dual;
    EXPECT_NEAR(r.objective, 20.0, 1e-6);
    EXPECT_NEAR(r.lower_bound, 20.0, 1e-6);
  }
  AnnealingOptions sa;
  sa.iterations = 20000;
  const DwellResult s = optimizeAnnealing(t.c, t.d, sa);
  EXPECT_GE(s.objective, 20.0 - 1e-9);  // nothing beats the optimum
  EXPECT_NEAR(s.times_s.at(0), 10.0, 0.05);
}

class SyntheticCaseTest : public ::testing::Test {
protected:
  SyntheticCaseTest() : source_(loadSource("microselectron_v2_hdr")) {
    SyntheticCaseOptions o;
    o.seed = 3;
    c_ = syntheticProstateCase(o);
    d_ = doseRateMatrix(c_, source_);
  }
  Tg43Source source_;
  HdrCase c_;
  Eigen::MatrixXd d_;
};

TEST_F(SyntheticCaseTest, CaseSpansTheCohortAndLpBeatsAnnealing) {
  EXPECT_GE(1e6 * c_.structures.front().volume_m3(), 20.0);  // cc, cohort 23-103 (slices: +-10 %)
  EXPECT_LE(1e6 * c_.structures.front().volume_m3(), 110.0);
  EXPECT_GE(c_.catheters.size(), 14U);
  EXPECT_LE(c_.catheters.size(), 18U);
  EXPECT_GE(c_.points.size(), 1781U);
  EXPECT_LE(c_.points.size(), 3510U);
  ASSERT_TRUE(d_.allFinite());
  const DwellResult lp = optimizeLp(c_, d_);
  ASSERT_TRUE(lp.ok()) << lp.status;
  EXPECT_NEAR(lp.objective, lp.lower_bound, kObjectiveRel * lp.objective);  // optimal: no gap
  LpOptions primal;
  primal.dual_formulation = false;
  const DwellResult lp2 = optimizeLp(c_, d_, primal);
  EXPECT_NEAR(lp.objective, lp2.objective, kObjectiveRel * lp.objective);
  const DwellResult sa = optimizeAnnealing(c_, d_);
  EXPECT_LE(lp.objective, sa.objective);
  EXPECT_TRUE(std::isfinite(sa.objective));
}

TEST_F(SyntheticCaseTest, MpsAndCaseFolderRoundTrips) {
  const auto dir = std::filesystem::temp_directory_path() / "ng_dwell_test";
  std::filesystem::create_directories(dir);
  const DwellResult lp = optimizeLp(c_, d_);
  writeLpMps(c_, d_, (dir / "case.mps").string());
  ClpSimplex model;
  model.setLogLevel(0);
  ASSERT_EQ(model.readMps((dir / "case.mps").string().c_str()), 0);
  EXPECT_EQ(model.numberRows(), static_cast<int>(c_.points.size()));
  model.dual();
  EXPECT_NEAR(model.objectiveValue(), lp.objective, kObjectiveRel * lp.objective);
  HdrCase planned = c_;
  planned.dwell_times_s = lp.times_s;
  writeCaseFolder(planned, (dir / "folder").string());
  const HdrCase back = readCaseFolder((dir / "folder").string());
  ASSERT_EQ(back.points.size(), c_.points.size());
  ASSERT_EQ(back.dwells.size(), c_.dwells.size());
  EXPECT_NEAR(penaltyModel(back)(doseRateMatrix(back, source_) *
                                 Eigen::Map<const Eigen::VectorXd>(
                                     back.dwell_times_s.data(),
                                     static_cast<Eigen::Index>(back.dwell_times_s.size()))),
              lp.objective, 1e-6 * lp.objective);  // 10 significant digits in the files
  // A malformed file names itself and the line.
  std::ofstream((dir / "folder" / "points.csv").string())
      << "structure,kind,x_mm,y_mm,z_mm\nprostate,volume,1,2,abc\n";
  try {
    readCaseFolder((dir / "folder").string());
    FAIL() << "no error for a bad number";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("points.csv:2"), std::string::npos) << e.what();
  }
}

TEST(DwellOptimizationHardCases, RefusalsAndCorrectAnswers) {
  TinyCase t;
  // D_min > D_max: a clear error naming the criterion.
  HdrCase bad = t.c;
  bad.criteria[0].min_Gy = 20.0;
  try {
    penaltyModel(bad);
    FAIL() << "no error for D_min > D_max";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("D_min"), std::string::npos) << e.what();
  }
  // A structure with no dose points: its criterion is noted and contributes nothing.
  HdrCase empty = t.c;
  empty.structures.push_back({"bladder", StructureRole::kOrganAtRisk, {}});
  empty.criteria.push_back({"bladder", PointKind::kSurface, 0.0, 5.0, 0.0, 20.0});
  const PenaltyModel pm = penaltyModel(empty);
  EXPECT_EQ(pm.notes.size(), 1U);
  const DwellResult r = optimizeLp(empty, t.d);
  EXPECT_NEAR(r.objective, 20.0, 1e-6);
  // Zero active dwell positions (e.g. every catheter outside the body): refused.
  HdrCase none = t.c;
  none.catheters = {{"outside", {Point3(0.5, 0.5, 0.5), Point3(0.5, 0.5, 0.4)}}};
  none.structures[0].contours = {
      {-0.01, {{-0.01, -0.01}, {0.01, -0.01}, {0.01, 0.01}, {-0.01, 0.01}}},
      {0.01, {{-0.01, -0.01}, {0.01, -0.01}, {0.01, 0.01}, {-0.01, 0.01}}}};
  none.dwells = makeDwellPositions(none, 5e-3);
  EXPECT_TRUE(none.dwells.empty());
  EXPECT_THROW(optimizeLp(none, Eigen::MatrixXd(2, 0)), std::invalid_argument);
  EXPECT_THROW(optimizeAnnealing(none, Eigen::MatrixXd(2, 0)), std::invalid_argument);
  // Duplicate dwell positions: the same optimum, split between the copies.
  HdrCase twice = t.c;
  twice.dwells.push_back(twice.dwells.front());
  Eigen::MatrixXd d2(2, 2);
  d2 << t.d, t.d;
  const DwellResult r2 = optimizeLp(twice, d2);
  EXPECT_NEAR(r2.objective, 20.0, 1e-6);
  EXPECT_NEAR(r2.times_s[0] + r2.times_s[1], 10.0, kTime_s);
  // A dose point exactly on a dwell position: finite (TG-43 taken 1 mm off the source).
  const Tg43Source source = loadSource("microselectron_v2_hdr");
  HdrCase on = t.c;
  on.points[0].position_m = on.dwells[0].position_m;
  const Eigen::MatrixXd d_on = doseRateMatrix(on, source);
  EXPECT_TRUE(d_on.allFinite());
  EXPECT_GT(d_on(0, 0), d_on(1, 0));
  // Wrong matrix size: refused with the sizes.
  EXPECT_THROW(optimizeLp(t.c, Eigen::MatrixXd::Ones(3, 1)), std::invalid_argument);
}

TEST(DoseIndices, HandComputedValues) {
  StructureDose s;
  s.name = "prostate";
  s.voxel_volume_m3 = 1e-6;  // 1 cc voxels
  for (int i = 1; i <= 10; ++i)
    s.dose_Gy.push_back(i);                             // 1..10 Gy
  EXPECT_DOUBLE_EQ(volumePercentAbove(s, 5.0), 60.0);   // 5..10: 6 of 10
  EXPECT_DOUBLE_EQ(doseCoveringPercent(s, 90.0), 2.0);  // hottest 9 voxels: min 2 Gy
  EXPECT_DOUBLE_EQ(doseCoveringVolume(s, 2e-6), 9.0);   // hottest 2 cc: min 9 Gy
  const auto idx = dosimetricIndices({s}, 5.0);
  EXPECT_DOUBLE_EQ(idx.at("prostate_V100"), 60.0);
  EXPECT_DOUBLE_EQ(idx.at("prostate_V150"), 30.0);  // >= 7.5 Gy: 8, 9, 10
  StructureDose none;
  none.name = "rectum";
  none.voxel_volume_m3 = 1e-6;
  EXPECT_DOUBLE_EQ(volumePercentAbove(none, 1.0), 0.0);
  EXPECT_DOUBLE_EQ(doseCoveringVolume(none, 2e-6), 0.0);
}

}  // namespace
}  // namespace needle_guidance::dose

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
