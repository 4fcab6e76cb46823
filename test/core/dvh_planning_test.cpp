// Dose-volume indices and the dose-volume planner: the structure lattice keeps the volume,
// indices a structure cannot support are undefined with the reason, turning and moving the case
// changes no index, a structure along the dose grid's edge, a thin structure's index at the
// default lattice against the converged one, criteria that cannot all hold (the
// least-violating plan names what gives way), a single-catheter case, criterion parsing.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>

#include "needle_guidance/dose/dicom_case.h"
#include "needle_guidance/dose/dicom_rt.h"
#include "needle_guidance/dose/dose_indices.h"
#include "needle_guidance/dose/dvh_comparison.h"
#include "needle_guidance/dose/dvh_optimization.h"
#include "needle_guidance/dose/plan_robustness.h"

namespace needle_guidance::dose {
namespace {

constexpr double kVolumeRel = 1e-9;      // lattice volume against the contour volume
constexpr double kInvariance_Gy = 0.01;  // index change when the case is turned or moved
constexpr double kInvariance_pp = 0.05;  // same, volume indices [percentage points]
constexpr double kGridIndex_Gy = 0.3;    // RTDOSE-grid indices against direct TG-43 [Gy]
constexpr double kGridIndex_pp = 1.0;    // same [pp]
constexpr double kCriterion_Gy = 0.02;   // a met dose criterion on the evaluation lattice
constexpr double kCriterion_pp = 0.1;    // a met volume criterion
constexpr double kObjective = 1e-9;      // the planner's objective, same times and points
constexpr double kDescentGap = 1.0;      // descent above CBC's proven optimum [objective: V100 pp]

Structure cylinder(const std::string& name, StructureRole role, double cx, double cy, double radius,
                   double z0, double z1, double dz) {
  Structure s;
  s.name = name;
  s.role = role;
  for (double z = z0; z <= z1 + 1e-12; z += dz) {
    Contour k;
    k.z_m = z;
    for (int i = 0; i < 48; ++i) {
      const double a = 2 * M_PI * i / 48;
      k.xy_m.emplace_back(cx + radius * std::cos(a), cy + 0.8 * radius * std::sin(a));
    }
    s.contours.push_back(k);
  }
  s.normalise();
  return s;
}

/// A small prostate (about 11 cm^3) around a urethra, a 0.2 cm^3 rectum behind it and
/// `catheters` catheters on a ring (one: on the axis beside the urethra).
HdrCase smallCase(int catheters) {
  HdrCase c;
  c.name = "small";
  c.prescription_Gy = 10.0;
  c.structures = {
      cylinder("prostate", StructureRole::kTarget, 0, 0, 15e-3, -10e-3, 10e-3, 2e-3),
      cylinder("urethra", StructureRole::kOrganAtRisk, 0, 0, 2.5e-3, -12e-3, 12e-3, 2e-3),
      cylinder("rectum", StructureRole::kOrganAtRisk, 0, -19e-3, 3e-3, -4e-3, 4e-3, 2e-3)};
  for (int k = 0; k < catheters; ++k) {
    const double a = 2 * M_PI * k / catheters;
    const double r = catheters == 1 ? 6e-3 : 8e-3;
    const Point3 tip(r * std::cos(a), r * std::sin(a), 14e-3);
    c.catheters.push_back({"c" + std::to_string(k), {tip, tip - Point3(0, 0, 60e-3)}});
  }
  c.dwells = makeDwellPositions(c, 4e-3);
  return c;
}

std::vector<double> uniformTimes(const HdrCase& c, double t) {
  return std::vector<double>(c.dwells.size(), t);
}

class DvhPlanning : public ::testing::Test {
protected:
  DvhPlanning() : source_(loadSource("microselectron_v2_hdr")), case_(smallCase(8)) {}
  Tg43Source source_;
  HdrCase case_;
};

TEST_F(DvhPlanning, LatticeKeepsTheContourVolume) {
  for (const Structure& s : case_.structures) {
    for (const double spacing : {0.5e-3, 2.5e-3, 10e-3}) {
      const VolumeSample v = sampleStructure(s, spacing);
      double total = 0.0;
      for (double x : v.volume_m3)
        total += x;
      EXPECT_NEAR(total, s.volume_m3(), kVolumeRel * s.volume_m3()) << s.name << " " << spacing;
    }
  }
  // A structure thinner than the lattice keeps its volume in one sample per slab plane.
  const Structure thin =
      cylinder("thin", StructureRole::kOrganAtRisk, 0.1e-3, 0, 0.2e-3, 0, 4e-3, 2e-3);
  const VolumeSample v = sampleStructure(thin, 2e-3);
  ASSERT_EQ(v.points_m.size(), 3u);
  EXPECT_NEAR(v.volume_m3[0] + v.volume_m3[1] + v.volume_m3[2], thin.volume_m3(),
              kVolumeRel * thin.volume_m3());
  EXPECT_THROW(sampleStructure(thin, 0.0), std::invalid_argument);
}

TEST_F(DvhPlanning, IndexBeyondTheStructureIsUndefinedWithItsReason) {
  const auto set = comparisonIndexSet(
      structureDoses(case_, source_, uniformTimes(case_, 5.0), 0.5e-3), case_.prescription_Gy);
  ASSERT_EQ(set.count("rectum_D2cc"), 1u);
  EXPECT_FALSE(set.at("rectum_D2cc").defined);  // the rectum holds about 0.2 cm^3
  EXPECT_NE(set.at("rectum_D2cc").reason.find("less than the 2 cm3"), std::string::npos)
      << set.at("rectum_D2cc").reason;
  EXPECT_TRUE(set.at("rectum_D0.1cc").defined);
  EXPECT_TRUE(std::isfinite(set.at("rectum_D0.1cc").value));
  const auto numbers = comparisonIndices(
      structureDoses(case_, source_, uniformTimes(case_, 5.0), 0.5e-3), case_.prescription_Gy);
  EXPECT_EQ(numbers.count("rectum_D2cc"), 0u);  // never a number
  // ... and never a comparison: dominance looks only at indices defined in both.
  auto worse = set;
  worse["rectum_D2cc"].value = 1e9;
  EXPECT_TRUE(worseIndices(worse, set, "prostate").empty());
  EXPECT_THROW(doseVolumeIndex(StructureDose{}, "X10", 10.0), std::invalid_argument);
  EXPECT_THROW(doseVolumeIndex(StructureDose{}, "V1e", 10.0), std::invalid_argument);
}

TEST_F(DvhPlanning, TurningOrMovingTheCaseChangesNoIndex) {
  const std::vector<double> times = uniformTimes(case_, 4.0);
  const auto base = comparisonIndexSet(structureDoses(case_, source_, times, 0.5e-3), 10.0);
  std::vector<Eigen::Isometry3d> poses(5, Eigen::Isometry3d::Identity());
  poses[0].linear() = Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  poses[1].linear() = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitY()).toRotationMatrix();
  poses[2].translation() = Eigen::Vector3d(41.5e-3, -17.3e-3, 63e-3);
  poses[3].linear() = Eigen::AngleAxisd(0.6458, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  poses[4].linear() = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitX()).toRotationMatrix();
  poses[4].translation() = Eigen::Vector3d(-3.3e-3, 7.1e-3, -0.4e-3);
  for (std::size_t k = 0; k < poses.size(); ++k) {
    const HdrCase moved = transformedCase(case_, poses[k]);
    const auto got = comparisonIndexSet(structureDoses(moved, source_, times, 0.5e-3), 10.0);
    const IndexChange ch = indexChange(base, got);
    EXPECT_LE(ch.dose_Gy, kInvariance_Gy) << "pose " << k << ": " << ch.worst_dose;
    EXPECT_LE(ch.volume_pp, kInvariance_pp) << "pose " << k << ": " << ch.worst_volume;
  }
  Eigen::Isometry3d tilt = Eigen::Isometry3d::Identity();
  tilt.linear() = Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitX()).toRotationMatrix();
  EXPECT_THROW(transformedCase(case_, tilt), std::invalid_argument);  // contours not axial
}

/// A dose grid over [lo, hi] (1 mm voxels) holding the TG-43 dose of `times`.
DoseGrid gridOver(const HdrCase& c, const Tg43Source& source, const std::vector<double>& times,
                  const Point3& lo, const Point3& hi) {
  DoseGrid g;
  g.spacing_m = Eigen::Vector3d::Constant(1e-3);
  g.origin_m = lo;
  for (int a = 0; a < 3; ++a)
    g.sizes[a] = static_cast<int>(std::round((hi[a] - lo[a]) / 1e-3)) + 1;
  for (int k = 0; k < g.sizes[2]; ++k)
    g.z_offsets_m.push_back(k * 1e-3);
  g.dose_Gy.resize(static_cast<std::size_t>(g.sizes[0]) * g.sizes[1] * g.sizes[2]);
  for (int k = 0; k < g.sizes[2]; ++k)
    for (int j = 0; j < g.sizes[1]; ++j)
      for (int i = 0; i < g.sizes[0]; ++i)
        g.at(i, j, k) = doseAt(c, source, times, g.position(i, j, k));
  return g;
}

TEST_F(DvhPlanning, StructureAlongTheDoseGridsEdge) {
  const std::vector<double> times = uniformTimes(case_, 4.0);
  Point3 lo, hi;
  case_.structures[0].bounds(lo, hi);  // the prostate's contour bounds; slabs reach 1 mm more
  // Outermost voxel centres 0.6 mm inside the slab ends and the contours: within half a voxel.
  const Point3 margin(-0.4e-3, -0.4e-3, 0.4e-3);
  const DoseGrid edge = gridOver(case_, source_, times, lo - margin, hi + margin);
  const auto from_grid = comparisonIndexSet(structureDosesFromGrid(case_, edge, 0.5e-3), 10.0);
  const auto direct = comparisonIndexSet(structureDoses(case_, source_, times, 0.5e-3), 10.0);
  ASSERT_TRUE(from_grid.at("prostate_V100").defined) << from_grid.at("prostate_V100").reason;
  EXPECT_NEAR(from_grid.at("prostate_V100").value, direct.at("prostate_V100").value, kGridIndex_pp);
  EXPECT_NEAR(from_grid.at("prostate_D90").value, direct.at("prostate_D90").value, kGridIndex_Gy);
  // A grid that cuts 3 mm off the prostate: its indices are undefined, with the volume outside.
  const DoseGrid cut =
      gridOver(case_, source_, times, lo - margin + Point3(3e-3, 0, 0), hi + margin);
  const auto partial = comparisonIndexSet(structureDosesFromGrid(case_, cut, 0.5e-3), 10.0);
  EXPECT_FALSE(partial.at("prostate_V100").defined);
  EXPECT_NE(partial.at("prostate_V100").reason.find("outside the dose grid"), std::string::npos);
}

TEST_F(DvhPlanning, ThinStructureIndexMatchesTheConvergedLattice) {
  // A 23 mm^2 section extruded over 21 planes 1 mm apart (as the shared plan's rectum): at a
  // lattice of 0.5 mm its few columns of samples alias with the isodose lines. The default
  // lattice (latticeSpacing: at least 400 samples per plane) reads V within 1 pp and D0.1cc
  // within 0.3 Gy of a 0.05 mm lattice with 8 planes per slice.
  constexpr double kConverged_pp = 1.0, kConverged_Gy = 0.3;
  HdrCase c = case_;
  c.structures = {
      cylinder("wall", StructureRole::kOrganAtRisk, 0, -12e-3, 3e-3, -10e-3, 10e-3, 1e-3)};
  EXPECT_LE(latticeSpacing(c.structures[0], 0.5e-3), 0.27e-3);
  Point3 lo, hi;
  c.structures[0].bounds(lo, hi);
  const std::vector<double> times = uniformTimes(case_, 4.0);
  const DoseGrid g =
      gridOver(c, source_, times, lo - Point3(2e-3, 2e-3, 2e-3), hi + Point3(2e-3, 2e-3, 2e-3));
  const StructureDose fine = structureDosesFromGrid(c, g, 0.05e-3, 0.125e-3, false).front();
  const StructureDose ours = structureDosesFromGrid(c, g, 0.5e-3).front();
  for (const double pct : {3.0, 6.0, 12.0, 50.0}) {
    const double level = doseCoveringPercent(fine, pct);
    EXPECT_NEAR(volumePercentAbove(ours, level), volumePercentAbove(fine, level), kConverged_pp)
        << "V at the dose covering " << pct << " %";
  }
  EXPECT_NEAR(doseCoveringVolume(ours, 0.1e-6), doseCoveringVolume(fine, 0.1e-6), kConverged_Gy);
}

TEST_F(DvhPlanning, DoseGridPixelsSampleAsDicompylerDoes) {
  // dicompyler-core's discretisation: 1 mm voxel centres inside each contour at its plane, each
  // voxel area x slice thickness. The volume is the voxel count's (within a ring of voxels of
  // the contour volume), every dose is a voxel's, and the prostate indices stay near ours.
  const std::vector<double> times = uniformTimes(case_, 4.0);
  Point3 lo, hi;
  case_.structures[0].bounds(lo, hi);
  const Point3 margin = Point3::Constant(3e-3);  // the grid covers the prostate
  const DoseGrid grid = gridOver(case_, source_, times, lo - margin, hi + margin);
  const auto pixels = structureDosesOnGridPixels(case_, grid);
  ASSERT_EQ(pixels.size(), case_.structures.size());
  const Structure& prostate = case_.structures[0];
  const double ring_m3 = 15e-3 * 2 * M_PI * 1e-3 * (hi.z() - lo.z() + 2e-3);  // 1 mm ring
  EXPECT_NEAR(pixels[0].volume(), prostate.volume_m3(), ring_m3);
  EXPECT_EQ(pixels[0].outside_m3, 0.0);
  const double max_grid = grid.maxDose();
  for (double d : pixels[0].dose_Gy)
    ASSERT_LE(d, max_grid + 1e-12);
  const auto on_pixels = comparisonIndexSet(pixels, 10.0);
  const auto direct = comparisonIndexSet(structureDoses(case_, source_, times, 0.5e-3), 10.0);
  EXPECT_NEAR(on_pixels.at("prostate_D90").value, direct.at("prostate_D90").value, kGridIndex_Gy);
}

TEST_F(DvhPlanning, CriteriaThatCannotAllHoldGiveTheLeastViolatingPlan) {
  // The urethra runs through the target: 95 % coverage at Rx and urethra D10 <= 50 % of Rx
  // cannot hold together.
  const std::vector<DvhCriterion> criteria = {parseDvhCriterion("prostate V100 >= 95", 10.0),
                                              parseDvhCriterion("urethra D10 <= 50%", 10.0)};
  DvhPlanOptions o;
  o.max_seconds = 6.0;
  const DvhPlanResult r = optimizeDvh(case_, source_, criteria, o);
  ASSERT_TRUE(r.ok()) << r.status;
  ASSERT_FALSE(r.violated.empty());
  bool named = false;
  for (const std::string& v : r.violated)
    named = named || v.find("prostate V100") != std::string::npos ||
            v.find("urethra D10") != std::string::npos;
  EXPECT_TRUE(named) << r.violated.front();
  EXPECT_TRUE(std::isfinite(r.v100_pct));
}

TEST_F(DvhPlanning, EveryCriterionIsMetOrNamedAsGivingWay) {
  const auto criteria = defaultDvhCriteria(10.0);
  DvhPlanOptions o;
  o.max_seconds = 8.0;
  const DvhPlanResult r = optimizeDvh(case_, source_, criteria, o);
  ASSERT_TRUE(r.ok()) << r.status;
  for (const DvhCriterion& k : criteria) {
    const auto it = r.indices.find(k.structure + "_" + k.index);
    if (k.structure == "bladder") {
      EXPECT_EQ(it, r.indices.end());  // no bladder in this case
      continue;
    }
    ASSERT_NE(it, r.indices.end()) << describe(k);
    if (!it->second.defined)
      continue;  // rectum D2cc of a 0.2 cm^3 rectum: skipped with a note
    const double tol = k.index[0] == 'V' ? kCriterion_pp : kCriterion_Gy;
    const bool met =
        k.at_most ? it->second.value <= k.limit + tol : it->second.value >= k.limit - tol;
    bool named = false;
    for (const auto& v : r.violated)
      named = named || v.rfind(describe(k), 0) == 0;
    EXPECT_TRUE(met || named) << describe(k) << ": " << it->second.value;
  }
  bool noted = false;
  for (const auto& n : r.notes)
    noted = noted || n.find("rectum D2cc") != std::string::npos;
  EXPECT_TRUE(noted);
  EXPECT_GT(r.v100_pct, 0.0);
}

TEST_F(DvhPlanning, SingleCatheterCase) {
  const HdrCase one = smallCase(1);
  ASSERT_FALSE(one.dwells.empty());
  const DvhPlanResult r = optimizeDvh(one, source_, defaultDvhCriteria(10.0));
  ASSERT_TRUE(r.ok()) << r.status;
  EXPECT_GT(r.v100_pct, 0.0);
  EXPECT_LE(r.v100_pct, 100.0);
  // One catheter cannot cover the target to 90 % within the hot-spot limits: coverage gives
  // way and is named.
  bool coverage_named = false;
  for (const auto& v : r.violated)
    coverage_named = coverage_named || v.find("prostate V100") != std::string::npos;
  EXPECT_TRUE(coverage_named || r.v100_pct >= 90.0);
}

TEST_F(DvhPlanning, ScoresTheCasesOwnTimesOnThePlannersModel) {
  // A plan's score on the planner's dose points is what the planner reported for it, so a
  // clinical plan carried by the case is compared with ours on the same model.
  const std::vector<DvhCriterion> criteria = defaultDvhCriteria(10.0);
  DvhPlanOptions o;
  o.max_seconds = 3.0;
  const DvhPlanResult first = optimizeDvh(case_, source_, criteria, o);
  ASSERT_TRUE(first.ok()) << first.status;
  EXPECT_TRUE(std::isnan(first.case_times_objective));  // the case carries no times
  HdrCase carried = case_;
  carried.dwell_times_s = first.times_s;
  const DvhPlanResult second = optimizeDvh(carried, source_, criteria, o);
  ASSERT_TRUE(std::isfinite(second.case_times_objective));
  EXPECT_NEAR(second.case_times_objective, first.objective, kObjective);
  EXPECT_NEAR(second.case_times_v100_pct, first.mip_v100_pct, kCriterion_pp);
  // Started from those times, the planner never returns a worse plan on its model.
  EXPECT_LE(second.objective, second.case_times_objective + kObjective);
}

TEST_F(DvhPlanning, DescentReachesTheBruteForceOptimumWithinItsGap) {
  // Three dwells, one per catheter at mid-gland: the planner's objective (minus target V100,
  // plus 100 per percentage point over a criterion) searched over a 41^3 grid of dwell times on
  // the same lattice. The descent is within kDescentGap of the grid's optimum, or better.
  HdrCase three = smallCase(3);
  std::vector<DwellPosition> mid;
  for (const DwellPosition& d : three.dwells) {
    if (std::abs(d.position_m.z()) < 2.1e-3 && (mid.empty() || mid.back().catheter != d.catheter))
      mid.push_back(d);
  }
  ASSERT_EQ(mid.size(), 3u);
  three.dwells = mid;
  const std::vector<DvhCriterion> criteria = {parseDvhCriterion("urethra V120 <= 10", 10.0),
                                              parseDvhCriterion("rectum V60 <= 5", 10.0)};
  DvhPlanOptions o;
  o.eval_spacing_m = 2e-3;
  o.max_seconds = 5.0;
  const DvhPlanResult r = optimizeDvh(three, source_, criteria, o);
  ASSERT_TRUE(r.ok()) << r.status;
  // Dose per second of each dwell on the lattice; doses are linear in the times.
  std::vector<std::vector<StructureDose>> unit;
  for (std::size_t j = 0; j < 3; ++j) {
    std::vector<double> t(3, 0.0);
    t[j] = 1.0;
    unit.push_back(structureDoses(three, source_, t, o.eval_spacing_m));
  }
  const double t_max = 2.0 * *std::max_element(r.times_s.begin(), r.times_s.end());
  double best = 1e300;
  std::vector<StructureDose> sd = unit[0];
  for (int a = 0; a <= 40; ++a)
    for (int b = 0; b <= 40; ++b)
      for (int c = 0; c <= 40; ++c) {
        const double t[3] = {a * t_max / 40, b * t_max / 40, c * t_max / 40};
        for (std::size_t s = 0; s < sd.size(); ++s)
          for (std::size_t i = 0; i < sd[s].dose_Gy.size(); ++i)
            sd[s].dose_Gy[i] = t[0] * unit[0][s].dose_Gy[i] + t[1] * unit[1][s].dose_Gy[i] +
                               t[2] * unit[2][s].dose_Gy[i];
        const double value = -volumePercentAbove(sd[0], 10.0) +
                             100.0 * std::max(0.0, volumePercentAbove(sd[1], 12.0) - 10.0) +
                             100.0 * std::max(0.0, volumePercentAbove(sd[2], 6.0) - 5.0);
        best = std::min(best, value);
      }
  EXPECT_LE(r.objective, best + kDescentGap) << "V100 " << r.v100_pct;
  EXPECT_GT(-best, 0.0);  // the grid covers some of the target
}

TEST_F(DvhPlanning, CbcBoundsTheDescentOnItsOwnPoints) {
  // With cbc_seconds, CBC starts from the descent's plan on the same points: it never returns
  // a worse plan, and its bound is known.
  const std::vector<DvhCriterion> criteria = {parseDvhCriterion("urethra D10 <= 110%", 10.0)};
  DvhPlanOptions o;
  o.eval_spacing_m = 5e-3;
  o.max_seconds = 2.0;
  o.cbc_seconds = 2.0;
  const DvhPlanResult r = optimizeDvh(smallCase(3), source_, criteria, o);
  ASSERT_TRUE(r.ok()) << r.status;
  EXPECT_TRUE(r.mip_bound_known);
  EXPECT_GE(r.mip_gap_pct, 0.0);
  EXPECT_LE(r.objective, r.descent_objective + kObjective);
}

TEST_F(DvhPlanning, DominatesAPlanOnItsOwnDwells) {
  // A reference plan on the same dwells is a feasible point of the dominance problem: the
  // planner, started there, finds a plan at least as good on every defined index.
  const std::vector<double> reference_times = uniformTimes(case_, 3.0);  // D90 near Rx
  const auto reference = comparisonIndexSet(structureDoses(case_, source_, reference_times, 1e-3),
                                            case_.prescription_Gy);
  HdrCase carried = case_;
  carried.dwell_times_s = reference_times;
  DvhPlanOptions o;
  o.eval_spacing_m = 1e-3;
  o.max_seconds = 3.0;
  const Dominance d = dominate(carried, source_, reference, "prostate", o);
  ASSERT_TRUE(d.plan.ok()) << d.plan.status;
  EXPECT_TRUE(d.dominated) << (d.worse.empty() ? "" : d.worse.front());
  EXPECT_GE(d.indices.at("prostate_V100").value, reference.at("prostate_V100").value);
}

TEST(DvhCriteria, ParsesUnitsAndRefusesBadText) {
  const DvhCriterion k = parseDvhCriterion("Urethra D10 <= 115%", 16.0);
  EXPECT_EQ(k.structure, "urethra");
  EXPECT_DOUBLE_EQ(k.limit, 18.4);
  EXPECT_TRUE(k.at_most);
  EXPECT_DOUBLE_EQ(parseDvhCriterion("rectum D2cc <= 12Gy", 16.0).limit, 12.0);
  EXPECT_DOUBLE_EQ(parseDvhCriterion("prostate V100 >= 90", 16.0).limit, 90.0);
  EXPECT_THROW(parseDvhCriterion("rectum V75 <= 5Gy", 16.0), std::invalid_argument);
  EXPECT_THROW(parseDvhCriterion("rectum D2cc < 12Gy", 16.0), std::invalid_argument);
  EXPECT_THROW(parseDvhCriterion("rectum Dx <= 12Gy", 16.0), std::invalid_argument);
  EXPECT_THROW(parseDvhCriterion("rectum", 16.0), std::invalid_argument);
}

}  // namespace
}  // namespace needle_guidance::dose

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
