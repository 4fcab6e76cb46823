// DICOM-RT import / export, RTDOSE reading and the gamma index (dicom_rt.h).
// The synthetic tests write tiny RTSTRUCT / RTPLAN / RTDOSE files (DCMTK, through the writers of
// dicom_rt.h) into a temporary folder and check the import against values set by hand. The
// real-data tests cross-check the importer against the CSV exports of the example plans
// (written with pydicom, an independent reader); they are skipped when the shared data
// ($NG_SHARED_DATA, default /work/shared/data) is absent.
#include <gtest/gtest.h>

#include "../csv_rows.h"

#include <unistd.h>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "../error_of.h"
#include "needle_guidance/dose/dicom_rt.h"

namespace dose = needle_guidance::dose;
namespace fs = std::filesystem;

namespace {

constexpr double kPositionTol_m = 1e-9;  // DS text keeps 10 significant digits of mm values
constexpr double kTimeTol_s = 1e-9;
constexpr double kDoseRelTol = 1e-6;  // uint32 quantisation + 10-digit DoseGridScaling

/// A fresh temporary folder, removed at the end of the test.
class TempDir {
public:
  TempDir() {
    std::string templ = (fs::temp_directory_path() / "dicom_rt_test_XXXXXX").string();
    if (mkdtemp(templ.data()) == nullptr) {
      throw std::runtime_error("mkdtemp failed");
    }
    path_ = templ;
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  std::string file(const std::string& name) const { return (path_ / name).string(); }
  std::string dir() const { return path_.string(); }
  std::string subdir(const std::string& name) const {
    fs::create_directories(path_ / name);
    return (path_ / name).string();
  }

private:
  fs::path path_;
};

dose::Contour square(double z_m, double cx_m, double cy_m, double half_m) {
  dose::Contour c;
  c.z_m = z_m;
  c.xy_m = {{cx_m - half_m, cy_m - half_m},
            {cx_m + half_m, cy_m - half_m},
            {cx_m + half_m, cy_m + half_m},
            {cx_m - half_m, cy_m + half_m}};
  return c;
}

/// Prostate (target) and rectum (OAR) squares on 3 slices; one catheter along -z with its tip at
/// z = +10 mm and 3 dwell positions 5 mm apart; S_K 40000 U; Rx 12 Gy.
dose::HdrCase syntheticCase() {
  dose::HdrCase c;
  c.name = "synthetic";
  c.air_kerma_strength_U = 40000.0;
  c.prescription_Gy = 12.0;
  dose::Structure prostate;
  prostate.name = "Prostate";
  prostate.role = dose::StructureRole::kTarget;
  dose::Structure rectum;
  rectum.name = "Rectum";
  rectum.role = dose::StructureRole::kOrganAtRisk;
  for (const double z_mm : {5.0, -5.0, 0.0}) {  // deliberately unsorted
    prostate.contours.push_back(square(z_mm * 1e-3, 0.0, 0.0, 10e-3));
    rectum.contours.push_back(square(z_mm * 1e-3, 0.0, -25e-3, 5e-3));
  }
  c.structures = {prostate, rectum};
  dose::Catheter cat;
  cat.name = "c1";
  cat.points_m = {{1e-3, 2e-3, 10e-3}, {1e-3, 2e-3, -30e-3}};  // tip first
  c.catheters = {cat};
  for (int k = 0; k < 3; ++k) {
    dose::DwellPosition d;
    d.catheter = 0;
    d.index = k;
    d.position_m = dose::Point3(1e-3, 2e-3, (5.0 - 5.0 * k) * 1e-3);
    d.axis = dose::Point3::UnitZ();  // towards the tip
    c.dwells.push_back(d);
  }
  c.dwell_times_s = {2.5, 4.0, 1.5};
  return c;
}

/// 4 x 4 x 3 grid, origin (-10, -20, 30) mm, spacing 2 mm (x) x 3 mm (y), frames at z offsets
/// 0, -5, -10 mm; dose(i, j, k) = 1 + i + 10 j + 100 k Gy (linear, so trilinear interpolation is
/// exact).
dose::DoseGrid syntheticGrid() {
  dose::DoseGrid g;
  g.origin_m = dose::Point3(-10e-3, -20e-3, 30e-3);
  g.spacing_m = Eigen::Vector3d(2e-3, 3e-3, 5e-3);
  g.sizes = {4, 4, 3};
  g.z_offsets_m = {0.0, -5e-3, -10e-3};
  g.dose_Gy.resize(48);
  for (int k = 0; k < 3; ++k) {
    for (int j = 0; j < 4; ++j) {
      for (int i = 0; i < 4; ++i) {
        g.at(i, j, k) = 1.0 + i + 10.0 * j + 100.0 * k;
      }
    }
  }
  return g;
}

/// Writes the synthetic case as RTSTRUCT + RTPLAN into `dir`.
void writeCase(const dose::HdrCase& c, const std::string& dir, dose::DwellTimeEncoding encoding) {
  dose::writeRtStruct(c, dir + "/SS.dcm");
  dose::writeRtPlan(c, dir + "/PL.dcm", encoding);
}

}  // namespace

TEST(DicomRt, ImportsSyntheticPlanInMetresAndSeconds) {
  TempDir tmp;
  const dose::HdrCase written = syntheticCase();
  writeCase(written, tmp.dir(), dose::DwellTimeEncoding::kStandardCumulative);
  dose::DicomRtImportReport rep;
  const dose::HdrCase c = dose::importDicomRt(tmp.dir(), &rep);

  EXPECT_EQ(rep.encoding, dose::DwellTimeEncoding::kStandardCumulative);
  EXPECT_NEAR(rep.total_dwell_time_s, 8.0, kTimeTol_s);
  EXPECT_NEAR(c.air_kerma_strength_U, 40000.0, 1e-9);
  EXPECT_NEAR(c.prescription_Gy, 12.0, 1e-12);
  EXPECT_TRUE(rep.warnings.empty()) << rep.warnings.front();

  ASSERT_EQ(c.structures.size(), 2u);
  EXPECT_EQ(c.structures[0].name, "Prostate");
  EXPECT_EQ(c.structures[0].role, dose::StructureRole::kTarget);
  EXPECT_EQ(c.structures[1].name, "Rectum");
  EXPECT_EQ(c.structures[1].role, dose::StructureRole::kOrganAtRisk);
  ASSERT_EQ(c.structures[0].contours.size(), 3u);
  EXPECT_NEAR(c.structures[0].contours[0].z_m, -5e-3, kPositionTol_m);  // normalised: sorted by z
  EXPECT_NEAR(c.structures[0].contours[2].z_m, 5e-3, kPositionTol_m);
  ASSERT_EQ(c.structures[0].contours[0].xy_m.size(), 4u);
  EXPECT_NEAR(c.structures[0].contours[0].xy_m[0].x(), -10e-3, kPositionTol_m);
  EXPECT_NEAR(c.structures[1].contours[0].xy_m[0].y(), -30e-3, kPositionTol_m);
  EXPECT_NEAR(c.structures[0].volume_m3(), 3 * 20e-3 * 20e-3 * 5e-3, 1e-12);

  ASSERT_EQ(c.catheters.size(), 1u);
  EXPECT_EQ(c.catheters[0].name, "c1");
  ASSERT_EQ(c.catheters[0].points_m.size(), 2u);
  EXPECT_NEAR((c.catheters[0].points_m[0] - dose::Point3(1e-3, 2e-3, 10e-3)).norm(), 0.0,
              kPositionTol_m);

  ASSERT_EQ(c.dwells.size(), 3u);
  ASSERT_EQ(c.dwell_times_s.size(), 3u);
  const double times[3] = {2.5, 4.0, 1.5};
  for (int k = 0; k < 3; ++k) {
    const dose::DwellPosition& d = c.dwells[static_cast<std::size_t>(k)];
    EXPECT_EQ(d.catheter, 0);
    EXPECT_EQ(d.index, k);
    EXPECT_NEAR((d.position_m - dose::Point3(1e-3, 2e-3, (5.0 - 5.0 * k) * 1e-3)).norm(), 0.0,
                kPositionTol_m);
    EXPECT_NEAR((d.axis - dose::Point3::UnitZ()).norm(), 0.0, 1e-6);  // towards the tip
    EXPECT_NEAR(c.dwell_times_s[static_cast<std::size_t>(k)], times[k], kTimeTol_s);
  }
  EXPECT_NEAR(*rep.total_reference_air_kerma_uGy, 40000.0 * 8.0 / 3600.0, 1e-6);
}

TEST(DicomRt, DecodesPerPairNonCumulativeTimeWeights) {
  TempDir tmp;
  const dose::HdrCase written = syntheticCase();
  writeCase(written, tmp.dir(), dose::DwellTimeEncoding::kPerPairNonCumulative);
  dose::DicomRtImportReport rep;
  const dose::HdrCase c = dose::importDicomRt(tmp.file("PL.dcm"), tmp.file("SS.dcm"), &rep);
  EXPECT_EQ(rep.encoding, dose::DwellTimeEncoding::kPerPairNonCumulative);
  ASSERT_EQ(c.dwell_times_s.size(), 3u);
  EXPECT_NEAR(c.dwell_times_s[0], 2.5, kTimeTol_s);
  EXPECT_NEAR(c.dwell_times_s[1], 4.0, kTimeTol_s);
  EXPECT_NEAR(c.dwell_times_s[2], 1.5, kTimeTol_s);

  // Only the last pair has weight (0, 0, 0, 0, 0, 3): both readings agree and the importer says so.
  dose::HdrCase last_only = written;
  last_only.dwell_times_s = {0.0, 0.0, 3.0};
  const std::string dir = tmp.subdir("last_only");
  writeCase(last_only, dir, dose::DwellTimeEncoding::kStandardCumulative);
  const dose::HdrCase c2 = dose::importDicomRt(dir, &rep);
  EXPECT_EQ(rep.encoding, dose::DwellTimeEncoding::kIndistinguishable);
  EXPECT_NEAR(c2.dwell_times_s[2], 3.0, kTimeTol_s);
  EXPECT_NEAR(c2.dwell_times_s[0], 0.0, kTimeTol_s);

  // Only the first position active, standard encoding: (0, 3, 3, 3, 3, 3) is not per-pair.
  dose::HdrCase first_only = written;
  first_only.dwell_times_s = {3.0, 0.0, 0.0};
  const std::string dir2 = tmp.subdir("first_only");
  writeCase(first_only, dir2, dose::DwellTimeEncoding::kStandardCumulative);
  const dose::HdrCase c3 = dose::importDicomRt(dir2, &rep);
  EXPECT_EQ(rep.encoding, dose::DwellTimeEncoding::kStandardCumulative);
  EXPECT_NEAR(c3.dwell_times_s[0], 3.0, kTimeTol_s);
}

TEST(DicomRt, CatheterFromControlPointsWithoutStructureSet) {
  TempDir tmp;
  writeCase(syntheticCase(), tmp.dir(), dose::DwellTimeEncoding::kStandardCumulative);
  const dose::HdrCase c = dose::importDicomRt(tmp.file("PL.dcm"), "");
  EXPECT_TRUE(c.structures.empty());
  ASSERT_EQ(c.catheters.size(), 1u);
  ASSERT_EQ(c.catheters[0].points_m.size(), 3u);  // the dwell positions, tip-most first
  EXPECT_NEAR(c.catheters[0].points_m[0].z(), 5e-3, kPositionTol_m);
  EXPECT_NEAR((c.dwells[1].axis - dose::Point3::UnitZ()).norm(), 0.0, 1e-6);
}

TEST(DicomRt, ReadsDoseGridPositionsAndValues) {
  TempDir tmp;
  dose::writeRtDose(syntheticGrid(), tmp.file("DO.dcm"));
  const dose::DoseGrid g = dose::readRtDose(tmp.file("DO.dcm"));
  ASSERT_EQ(g.sizes[0], 4);
  ASSERT_EQ(g.sizes[1], 4);
  ASSERT_EQ(g.sizes[2], 3);
  EXPECT_NEAR((g.origin_m - dose::Point3(-10e-3, -20e-3, 30e-3)).norm(), 0.0, kPositionTol_m);
  EXPECT_NEAR(g.spacing_m.x(), 2e-3, kPositionTol_m);
  EXPECT_NEAR(g.spacing_m.y(), 3e-3, kPositionTol_m);
  EXPECT_NEAR(g.spacing_m.z(), 5e-3, kPositionTol_m);
  EXPECT_NEAR((g.position(3, 2, 1) - dose::Point3(-4e-3, -14e-3, 25e-3)).norm(), 0.0,
              kPositionTol_m);
  for (int k = 0; k < 3; ++k) {
    for (int j = 0; j < 4; ++j) {
      for (int i = 0; i < 4; ++i) {
        const double expected = 1.0 + i + 10.0 * j + 100.0 * k;
        EXPECT_NEAR(g.at(i, j, k), expected, kDoseRelTol * expected) << i << "," << j << "," << k;
      }
    }
  }
  double d = 0.0;
  // Between voxels (1,1,0) and (2,2,1): half a step in x and y, 2.5 mm of the 5 mm frame step.
  ASSERT_TRUE(g.interpolate(g.position(1, 1, 0) + dose::Point3(1e-3, 1.5e-3, -2.5e-3), &d));
  EXPECT_NEAR(d, 1.0 + 1.5 + 15.0 + 50.0, 1e-4);
  EXPECT_FALSE(g.interpolate(g.position(0, 0, 0) - dose::Point3(0.1e-3, 0.0, 0.0), &d));
  EXPECT_FALSE(g.interpolate(g.position(3, 3, 2) - dose::Point3(0.0, 0.0, 0.1e-3), &d));
  EXPECT_NEAR(g.maxDose(), 1.0 + 3 + 30 + 200, 1e-3);
}

TEST(DicomRt, GammaIsOneForIdenticalDosesAndFailsForAShiftedGrid) {
  const dose::DoseGrid g = syntheticGrid();
  std::vector<dose::Point3> points;
  std::vector<double> same;
  for (const dose::VoxelIndex& v : dose::voxelsAtOrAbove(g, 0.0)) {
    points.push_back(g.position(v.i, v.j, v.k));
    same.push_back(g.at(v.i, v.j, v.k));
  }
  dose::GammaCriteria cr;
  cr.dose_fraction = 0.01;
  cr.dta_m = 1e-3;
  cr.normalisation_Gy = 100.0;  // dD = 1 Gy; the dose gradient is 0.5 Gy/mm in x, 3.3 in y, 20 in z
  const dose::GammaResult same_result = dose::gammaIndex(g, points, same, cr);
  EXPECT_EQ(same_result.points, 48);
  EXPECT_DOUBLE_EQ(same_result.pass_rate, 1.0);
  EXPECT_NEAR(same_result.median_relative_difference, 0.0, 1e-12);
  EXPECT_NEAR(same_result.max_gamma, 0.0, 1e-12);

  // Evaluated dose = the grid shifted by 2 voxels (4 mm) along x: 2 Gy off, beyond 1 %/1 mm.
  std::vector<dose::Point3> p2;
  std::vector<double> shifted;
  for (int k = 0; k < 3; ++k) {
    for (int j = 0; j < 4; ++j) {
      for (int i = 0; i < 2; ++i) {
        p2.push_back(g.position(i, j, k));
        shifted.push_back(g.at(i + 2, j, k));
      }
    }
  }
  const dose::GammaResult shifted_result = dose::gammaIndex(g, p2, shifted, cr);
  EXPECT_LT(shifted_result.pass_rate, 1.0);
  EXPECT_GT(shifted_result.max_gamma, 1.0);
  EXPECT_GT(shifted_result.median_relative_difference, 0.0);

  // Sub-voxel: a 0.5 mm shift along x is found by the search (gamma ~ 0.5 <= 1).
  std::vector<double> half;
  for (const dose::Point3& p : points) {
    double d = 0.0;
    half.push_back(g.interpolate(p + dose::Point3(0.5e-3, 0.0, 0.0), &d) ? d
                   : g.interpolate(p, &d)                                ? d
                                                                         : 0.0);
  }
  EXPECT_DOUBLE_EQ(dose::gammaIndex(g, points, half, cr).pass_rate, 1.0);

  // A point outside the reference grid counts as failing.
  const dose::GammaResult outside = dose::gammaIndex(g, {dose::Point3(1.0, 1.0, 1.0)}, {1.0}, cr);
  EXPECT_EQ(outside.points_outside, 1);
  EXPECT_DOUBLE_EQ(outside.pass_rate, 0.0);
}

TEST(DicomRt, SampleIsReproducibleAndBounded) {
  const dose::DoseGrid g = syntheticGrid();
  const auto all = dose::voxelsAtOrAbove(g, 100.0);  // frames 1 and 2
  EXPECT_EQ(all.size(), 32u);
  const auto a = dose::sampleVoxels(all, 10, 7);
  const auto b = dose::sampleVoxels(all, 10, 7);
  ASSERT_EQ(a.size(), 10u);
  for (std::size_t n = 0; n < a.size(); ++n) {
    EXPECT_EQ(a[n].i, b[n].i);
    EXPECT_EQ(a[n].j, b[n].j);
    EXPECT_EQ(a[n].k, b[n].k);
    EXPECT_GE(a[n].k, 1);
  }
  EXPECT_EQ(dose::sampleVoxels(all, 0, 7).size(), 32u);
}

TEST(DicomRt, BadInputNamesTheFile) {
  TempDir tmp;
  const std::string missing = tmp.file("nope/PL001.dcm");
  std::string msg = errorOf([&] { dose::importDicomRt(missing, ""); });
  EXPECT_NE(msg.find(missing), std::string::npos) << msg;

  dose::writeRtDose(syntheticGrid(), tmp.file("DO.dcm"));
  msg = errorOf([&] { dose::importDicomRt(tmp.file("DO.dcm"), ""); });  // an RTDOSE given as plan
  EXPECT_NE(msg.find(tmp.file("DO.dcm")), std::string::npos) << msg;
  EXPECT_NE(msg.find("RTPLAN"), std::string::npos) << msg;

  writeCase(syntheticCase(), tmp.dir(), dose::DwellTimeEncoding::kStandardCumulative);
  msg = errorOf([&] { dose::readRtDose(tmp.file("PL.dcm")); });  // a plan given as dose
  EXPECT_NE(msg.find(tmp.file("PL.dcm")), std::string::npos) << msg;
  msg = errorOf(
      [&] { dose::importDicomRt(tmp.file("PL.dcm"), tmp.file("PL.dcm")); });  // plan as RTSTRUCT
  EXPECT_NE(msg.find("RTSTRUCT"), std::string::npos) << msg;

  { std::ofstream(tmp.file("junk.dcm")) << "this is not DICOM\n"; }
  msg = errorOf([&] { dose::readRtDose(tmp.file("junk.dcm")); });
  EXPECT_NE(msg.find(tmp.file("junk.dcm")), std::string::npos) << msg;

  const std::string empty = tmp.subdir("empty");
  msg = errorOf([&] { dose::importDicomRt(empty); });
  EXPECT_NE(msg.find("no RTPLAN"), std::string::npos) << msg;

  dose::DoseGrid bad = syntheticGrid();
  bad.dose_Gy.pop_back();  // inconsistent sizes
  EXPECT_THROW(dose::writeRtDose(bad, tmp.file("bad.dcm")), std::invalid_argument);
  EXPECT_THROW(dose::gammaIndex(syntheticGrid(), {dose::Point3::Zero()}, {}, dose::GammaCriteria{}),
               std::invalid_argument);
  dose::HdrCase wrong_times = syntheticCase();
  wrong_times.dwell_times_s.pop_back();
  EXPECT_THROW(dose::writeRtPlan(wrong_times, tmp.file("x.dcm")), std::invalid_argument);
}

TEST(DicomRt, ValidationPassesOwnDoseAndFlagsAOneSliceShift) {
  const dose::HdrCase c = syntheticCase();
  const dose::Tg43Source source = dose::loadSource("gammamed_plus_hdr");
  // 1 mm grid, 24 x 24 x 24 voxels around the catheter (x, y in -11.5..11.5 mm, z 12..-11 mm).
  dose::DoseGrid geometry;
  geometry.origin_m = dose::Point3(-11.5e-3, -11.5e-3, 12e-3);
  geometry.spacing_m = Eigen::Vector3d(1e-3, 1e-3, 1e-3);
  geometry.sizes = {24, 24, 24};
  for (int k = 0; k < 24; ++k) {
    geometry.z_offsets_m.push_back(-1e-3 * k);
  }
  geometry.dose_Gy.assign(std::size_t{24} * 24 * 24, 0.0);
  geometry.summation_type = "PLAN";
  const dose::DoseGrid own = dose::computeDoseOnGrid(c, source, geometry);
  const dose::RtDoseValidation same = dose::validateAgainstRtDose(c, source, own, 1);
  EXPECT_TRUE(same.pass);
  EXPECT_DOUBLE_EQ(same.gamma3pct3mm(), 1.0);
  EXPECT_NEAR(same.median_relative_difference, 0.0, 1e-12);
  EXPECT_GT(same.voxels, 100u);

  // Frame k holds the dose of frame k + 1 (1 mm lower), the last one that of frame 0: the
  // misregistration of the shared example, which the verdict must catch.
  dose::DoseGrid shifted = own;
  for (int k = 0; k < 24; ++k) {
    for (int j = 0; j < 24; ++j) {
      for (int i = 0; i < 24; ++i) {
        shifted.at(i, j, k) = own.at(i, j, (k + 1) % 24);
      }
    }
  }
  const dose::RtDoseValidation bad = dose::validateAgainstRtDose(c, source, shifted, 1);
  EXPECT_FALSE(bad.pass);
  EXPECT_GT(bad.p95_abs_relative_difference, 0.02);
  EXPECT_NEAR(bad.best_shift_m.z(), -1e-3, 1e-9);
  EXPECT_FALSE(bad.reasons.empty());
}

// ---- real data (skipped without the shared data set) ------------------------------------------

namespace {

std::string sharedData() {
  const char* env = std::getenv("NG_SHARED_DATA");
  return env != nullptr && *env != '\0' ? env : "/work/shared/data";
}

/// Dwell positions, times and orientations against dwell_positions.csv (pydicom export).
void checkAgainstCsv(const std::string& dir, dose::DwellTimeEncoding expected_encoding,
                     double expected_total_s) {
  dose::DicomRtImportReport rep;
  const dose::HdrCase c = dose::importDicomRt(dir, &rep);
  EXPECT_EQ(rep.encoding, expected_encoding);
  EXPECT_NEAR(rep.total_dwell_time_s, expected_total_s, 1e-6);
  EXPECT_NEAR(c.air_kerma_strength_U, 40700.0, 1e-9);
  EXPECT_NEAR(c.prescription_Gy, 16.0, 1e-12);
  ASSERT_EQ(c.catheters.size(), 14u);
  const auto rows = readCsvRows(dir + "/dwell_positions.csv");
  ASSERT_EQ(rows.size(), c.dwells.size());
  for (const auto& row : rows) {
    const int catheter = std::stoi(row.at("channel")) - 1;
    const int index = std::stoi(row.at("index"));
    std::size_t found = c.dwells.size();
    for (std::size_t d = 0; d < c.dwells.size(); ++d) {
      if (c.dwells[d].catheter == catheter && c.dwells[d].index == index) {
        found = d;
      }
    }
    ASSERT_LT(found, c.dwells.size()) << "channel " << catheter + 1 << " index " << index;
    const dose::Point3 p(std::stod(row.at("x_mm")), std::stod(row.at("y_mm")),
                         std::stod(row.at("z_mm")));
    EXPECT_NEAR((c.dwells[found].position_m - p * 1e-3).norm(), 0.0, 1e-8);
    EXPECT_NEAR(c.dwell_times_s[found], std::stod(row.at("dwell_time_s")), 1e-9);
    const dose::Point3 o(std::stod(row.at("orient_x")), std::stod(row.at("orient_y")),
                         std::stod(row.at("orient_z")));
    EXPECT_GT(c.dwells[found].axis.dot(o.normalized()),
              0.9999);  // the CSV orientation points to the tip
  }
  // The tip (first catheter point) is superior to every dwell position of its catheter here.
  for (const dose::DwellPosition& d : c.dwells) {
    EXPECT_GT(c.catheters[static_cast<std::size_t>(d.catheter)].points_m.front().z(),
              d.position_m.z());
  }
}

}  // namespace

TEST(DicomRtRealData, ExamplePlanMatchesCsvExport) {
  const std::string dir = sharedData() + "/hdr_example_plan";
  if (!fs::exists(dir + "/PL001.dcm")) {
    GTEST_SKIP() << dir << " absent";
  }
  checkAgainstCsv(dir, dose::DwellTimeEncoding::kStandardCumulative, 151.5);
  const dose::HdrCase c = dose::importDicomRt(dir);
  ASSERT_EQ(c.structures.size(), 3u);
  EXPECT_EQ(c.structures[0].name, "Prostate");
  EXPECT_EQ(c.structures[0].role, dose::StructureRole::kTarget);
  EXPECT_EQ(c.structures[0].contours.size(), 39u);
  EXPECT_EQ(c.structures[2].role, dose::StructureRole::kOrganAtRisk);
  EXPECT_NEAR(c.structures[0].volume_m3() * 1e6, 6.2, 0.3);  // the data set: about 6.2 cm^3

  // RTDOSE against the exported sample voxels.
  const dose::DoseGrid g = dose::readRtDose(dir + "/DO001.dcm");
  EXPECT_EQ(g.sizes[0], 80);
  EXPECT_EQ(g.sizes[1], 80);
  EXPECT_EQ(g.sizes[2], 56);
  const auto rows = readCsvRows(dir + "/rtdose_sample_points.csv");
  ASSERT_GT(rows.size(), 1000u);
  for (const auto& row : rows) {
    const int k = std::stoi(row.at("frame"));
    const int j = std::stoi(row.at("row"));
    const int i = std::stoi(row.at("col"));
    const dose::Point3 p(std::stod(row.at("x_mm")), std::stod(row.at("y_mm")),
                         std::stod(row.at("z_mm")));
    EXPECT_NEAR((g.position(i, j, k) - p * 1e-3).norm(), 0.0, 1e-7);
    const double expected = std::stod(row.at("dose_Gy"));
    EXPECT_NEAR(g.at(i, j, k), expected, 1e-5 * expected + 1e-5);
  }
}

TEST(DicomRtRealData, MisregisteredPlanUsesPerPairTimeWeights) {
  const std::string dir = sharedData() + "/hdr_example_plan_misregistered_dose";
  if (!fs::exists(dir + "/PL001.dcm")) {
    GTEST_SKIP() << dir << " absent";
  }
  checkAgainstCsv(dir, dose::DwellTimeEncoding::kPerPairNonCumulative, 550.4);
}

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
