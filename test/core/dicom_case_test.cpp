// Planning cases from DICOM-RT folders (dicom_case.h) and their hard cases. Fixtures are
// small DICOM-RT folders written in the test with DCMTK (the dicom_rt.h writers, and DCMTK
// directly to break a prescription), from a synthetic prostate case whose values are set here;
// the shared data is not needed.
#include <gtest/gtest.h>

#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <string>

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wall"
#pragma GCC diagnostic ignored "-Wextra"
#include <dcmtk/config/osconfig.h>
#include <dcmtk/dcmdata/dctk.h>
#pragma GCC diagnostic pop

#include "../error_of.h"
#include "needle_guidance/dose/dicom_case.h"
#include "needle_guidance/dose/dwell_optimization.h"

namespace dose = needle_guidance::dose;
namespace fs = std::filesystem;

namespace {

constexpr double kTimeTol_s = 0.01;       // dwell-time round-trip tolerance
constexpr double kLatticeTol_m = 0.1e-3;  // candidate vs clinical position
constexpr double kRxTol_Gy = 1e-9;

class TempDir {
public:
  TempDir() {
    std::string templ = (fs::temp_directory_path() / "dicom_case_test_XXXXXX").string();
    if (mkdtemp(templ.data()) == nullptr)
      throw std::runtime_error("mkdtemp failed");
    path_ = templ;
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  std::string dir() const { return path_.string(); }

private:
  fs::path path_;
};

/// Synthetic case 3 (Rx 9.5 Gy) with ROI names as a clinic might write them and 2 s per dwell.
dose::HdrCase clinicalCase() {
  dose::SyntheticCaseOptions o;
  o.seed = 3;
  o.dose_points = 600;
  dose::HdrCase c = dose::syntheticProstateCase(o);
  const char* names[] = {"Prostate", "Urethra", "Rectum", "Bladder"};
  for (std::size_t s = 0; s < c.structures.size(); ++s)
    c.structures[s].name = names[s];
  c.dwell_times_s.assign(c.dwells.size(), 2.0);
  return c;
}

void writeFolder(const dose::HdrCase& c, const std::string& dir,
                 dose::DwellTimeEncoding encoding = dose::DwellTimeEncoding::kStandardCumulative) {
  dose::writeRtStruct(c, dir + "/RS.dcm");
  dose::writeRtPlan(c, dir + "/RP.dcm", encoding);
}

/// Sets (or with value nullptr deletes) a prescription tag in the plan, with DCMTK.
void editPrescription(const std::string& plan, const char* value) {
  DcmFileFormat ff;
  ASSERT_TRUE(ff.loadFile(plan.c_str()).good());
  DcmDataset* ds = ff.getDataset();
  DcmItem* fg = nullptr;
  DcmItem* setup = nullptr;
  DcmItem* ref = nullptr;
  ASSERT_TRUE(ds->findAndGetSequenceItem(DCM_FractionGroupSequence, fg, 0).good());
  ASSERT_TRUE(
      fg->findAndGetSequenceItem(DCM_ReferencedBrachyApplicationSetupSequence, setup, 0).good());
  ASSERT_TRUE(ds->findAndGetSequenceItem(DCM_DoseReferenceSequence, ref, 0).good());
  for (auto [item, key] : {std::pair{setup, DCM_BrachyApplicationSetupDose},
                           std::pair{ref, DCM_TargetPrescriptionDose}}) {
    if (value) {
      ASSERT_TRUE(item->putAndInsertString(key, value).good());
    } else {
      item->findAndDeleteElement(key);
    }
  }
  ASSERT_TRUE(ff.saveFile(plan.c_str(), EXS_LittleEndianExplicit).good());
}

}  // namespace

TEST(DicomCase, DefaultMappingCandidatesOnTheClinicalLatticeAndScaledCriteria) {
  TempDir t;
  const dose::HdrCase c = clinicalCase();
  writeFolder(c, t.dir());
  const dose::DicomCase dc = dose::loadDicomCase(t.dir());
  ASSERT_EQ(dc.planning.structures.size(), 4u);
  EXPECT_EQ(dc.planning.structures[0].name, "prostate");
  EXPECT_EQ(dc.planning.structures[0].role, dose::StructureRole::kTarget);
  EXPECT_EQ(dc.planning.structures[3].name, "bladder");
  EXPECT_NEAR(dc.step_m, 5e-3, 1e-4);
  // The clinical dwells were made by the same rule (inside the target + 2.5 mm, 5 mm steps from
  // the tip), so every one of them must be a candidate.
  EXPECT_EQ(dc.clinical_active, static_cast<int>(c.dwells.size()));
  EXPECT_EQ(dc.clinical_active_on_candidates, dc.clinical_active);
  EXPECT_LE(dc.clinical_max_offset_m, kLatticeTol_m);
  EXPECT_NEAR(dc.planning.prescription_Gy, 9.5, kRxTol_Gy);
  ASSERT_FALSE(dc.planning.criteria.empty());
  EXPECT_NEAR(dc.planning.criteria[0].min_Gy, 9.5, kRxTol_Gy);
  EXPECT_GT(dc.planning.points.size(), 500u);
  EXPECT_EQ(dc.clinical.dwell_times_s.size(), dc.clinical.dwells.size());
}

TEST(DicomCase, UnusualNamesWithoutMappingListTheNamesFound) {
  TempDir t;
  dose::HdrCase c = clinicalCase();
  const char* names[] = {"GTV_p", "U_wall", "R_ant", "BL"};
  for (std::size_t s = 0; s < c.structures.size(); ++s)
    c.structures[s].name = names[s];
  writeFolder(c, t.dir());
  const std::string err = errorOf([&] { dose::loadDicomCase(t.dir()); });
  EXPECT_NE(err.find("no ROI maps to the target 'prostate'"), std::string::npos) << err;
  for (const char* n : names)
    EXPECT_NE(err.find(std::string("'") + n + "'"), std::string::npos) << err;
  // With a mapping the same folder loads, under the canonical names.
  dose::DicomCaseSettings s;
  s.structures = {{"prostate", {"gtv_p"}}, {"urethra", {"U_wall"}}, {"rectum", {"R_ANT"}}};
  const dose::DicomCase dc = dose::loadDicomCase(t.dir(), s);
  ASSERT_EQ(dc.planning.structures.size(), 3u);
  EXPECT_EQ(dc.planning.structures[1].name, "urethra");
  ASSERT_EQ(dc.ignored_rois.size(), 1u);
  EXPECT_EQ(dc.ignored_rois[0], "BL");
}

TEST(DicomCase, CatheterOutsideTheTargetGetsNoCandidatesAndANote) {
  TempDir t;
  dose::HdrCase c = clinicalCase();
  dose::Catheter far;
  far.name = "far";
  far.points_m = {{0.08, 0.0, 0.02}, {0.08, 0.0, -0.08}};  // 8 cm lateral of the gland
  c.catheters.push_back(far);
  dose::DwellPosition d;
  d.catheter = static_cast<int>(c.catheters.size()) - 1;
  d.position_m = {0.08, 0.0, 0.0};
  d.axis = dose::Point3::UnitZ();
  c.dwells.push_back(d);
  c.dwell_times_s.push_back(0.0);
  writeFolder(c, t.dir());
  const dose::DicomCase dc = dose::loadDicomCase(t.dir());
  const int far_index = static_cast<int>(dc.planning.catheters.size()) - 1;
  EXPECT_EQ(dc.planning.catheters.back().name, "far");
  for (const auto& dw : dc.planning.dwells)
    EXPECT_NE(dw.catheter, far_index);
  bool noted = false;
  for (const auto& n : dc.notes)
    noted = noted || n.find("catheter 'far'") != std::string::npos;
  EXPECT_TRUE(noted);
}

TEST(DicomCase, DoseGridMissingAStructureIsNoted) {
  TempDir t;
  const dose::HdrCase c = clinicalCase();
  writeFolder(c, t.dir());
  dose::DoseGrid g;  // covers the prostate only
  dose::Point3 lo, hi;
  c.structures[0].bounds(lo, hi);
  g.origin_m = lo;
  g.spacing_m = Eigen::Vector3d::Constant(2e-3);
  for (int a = 0; a < 3; ++a)
    g.sizes[a] = static_cast<int>(std::ceil((hi[a] - lo[a]) / 2e-3)) + 1;
  for (int k = 0; k < g.sizes[2]; ++k)
    g.z_offsets_m.push_back(k * 2e-3);
  g.dose_Gy.assign(static_cast<std::size_t>(g.sizes[0]) * g.sizes[1] * g.sizes[2], 1.0);
  dose::writeRtDose(g, t.dir() + "/RD.dcm");
  const dose::DicomCase dc = dose::loadDicomCase(t.dir());
  bool rectum = false, prostate = false;
  for (const auto& n : dc.notes) {
    rectum =
        rectum || n.find("structure 'rectum' extends outside the RTDOSE grid") != std::string::npos;
    prostate = prostate || n.find("structure 'prostate'") != std::string::npos;
  }
  EXPECT_TRUE(rectum);
  EXPECT_FALSE(prostate);
}

TEST(DicomCase, PerPairRtPlanEncodingGivesTheSameClinicalTimes) {
  TempDir t;
  dose::HdrCase c = clinicalCase();
  for (std::size_t j = 0; j < c.dwell_times_s.size(); ++j)
    c.dwell_times_s[j] = 0.5 + 0.1 * (j % 7);
  writeFolder(c, t.dir(), dose::DwellTimeEncoding::kPerPairNonCumulative);
  const dose::DicomCase dc = dose::loadDicomCase(t.dir());
  EXPECT_EQ(dc.import_report.encoding, dose::DwellTimeEncoding::kPerPairNonCumulative);
  ASSERT_EQ(dc.clinical.dwell_times_s.size(), c.dwell_times_s.size());
  for (std::size_t j = 0; j < c.dwell_times_s.size(); ++j) {
    EXPECT_NEAR(dc.clinical.dwell_times_s[j], c.dwell_times_s[j], 1e-9) << j;
  }
}

TEST(DicomCase, NoOrganAtRiskPlansTheTargetAlone) {
  TempDir t;
  dose::HdrCase c = clinicalCase();
  c.structures.resize(1);
  writeFolder(c, t.dir());
  const dose::DicomCase dc = dose::loadDicomCase(t.dir());
  ASSERT_EQ(dc.planning.structures.size(), 1u);
  for (const auto& k : dc.planning.criteria)
    EXPECT_EQ(k.structure, "prostate");
  const dose::Tg43Source source = dose::loadSource(dc.planning.source);
  const dose::ClinicalComparison cmp = dose::compareWithClinical(dc, source, {1.0}, 2e-3);
  ASSERT_TRUE(cmp.lp.ok());
  EXPECT_GT(cmp.ours.indices.at("prostate_V100"), 50.0);
  EXPECT_EQ(cmp.ours.indices.count("urethra_D10"), 0u);
}

TEST(DicomCase, PrescriptionZeroOrMissingIsRefused) {
  TempDir t;
  writeFolder(clinicalCase(), t.dir());
  editPrescription(t.dir() + "/RP.dcm", "0");
  std::string err = errorOf([&] { dose::loadDicomCase(t.dir()); });
  EXPECT_NE(err.find("prescription dose 0 Gy must be > 0"), std::string::npos) << err;
  EXPECT_NE(err.find("RP.dcm"), std::string::npos) << err;
  editPrescription(t.dir() + "/RP.dcm", nullptr);
  err = errorOf([&] { dose::loadDicomCase(t.dir()); });
  EXPECT_NE(err.find("no prescription"), std::string::npos) << err;
  EXPECT_NE(err.find("(300a,00a4)"), std::string::npos) << err;
}

TEST(DicomCase, ExportRoundTripKeepsDwellTimes) {
  TempDir t;
  const dose::HdrCase c = clinicalCase();
  writeFolder(c, t.dir());
  const dose::DicomCase dc = dose::loadDicomCase(t.dir());
  dose::HdrCase plan = dc.planning;
  plan.dwell_times_s.resize(plan.dwells.size());
  for (std::size_t j = 0; j < plan.dwell_times_s.size(); ++j)
    plan.dwell_times_s[j] = 0.123 * (j % 11);
  const std::string out = t.dir() + "/export";
  const dose::Tg43Source source = dose::loadSource(plan.source);
  dose::exportDicomRtPlan(plan, source, nullptr, out, dc.files.structure_set);
  const dose::HdrCase back = dose::importDicomRt(out + "/RP.dcm", out + "/RS.dcm");
  ASSERT_EQ(back.dwells.size(), plan.dwells.size());
  for (std::size_t j = 0; j < plan.dwells.size(); ++j) {
    EXPECT_LE((back.dwells[j].position_m - plan.dwells[j].position_m).norm(), 1e-6) << j;
    EXPECT_NEAR(back.dwell_times_s[j], plan.dwell_times_s[j], kTimeTol_s) << j;
  }
}

TEST(DicomCase, ShippedCaseFileIsTheDefault) {
  const dose::DicomCaseSettings s =
      dose::readDicomCaseSettings(std::string(NG_SOURCE_DIR) + "/config/hdr/dicom_case.yaml");
  const dose::DicomCaseSettings d;
  ASSERT_EQ(s.structures.size(), d.structures.size());
  EXPECT_EQ(s.structures[0].first, "prostate");
  EXPECT_DOUBLE_EQ(s.margin_m, d.margin_m);
  EXPECT_EQ(s.points.volume_points, d.points.volume_points);
  EXPECT_EQ(s.source, d.source);
  EXPECT_TRUE(s.criteria.empty());
  const std::string err = errorOf([] { dose::readDicomCaseSettings("/nonexistent/case.yaml"); });
  EXPECT_NE(err.find("/nonexistent/case.yaml"), std::string::npos);
}
// Found on the real plan (1 mm slices, 2 mm evaluation grid): a point exactly half-way between
// two slices used to be tested against both slices' contours, which cancel in the even-odd rule.
TEST(DicomCase, PointHalfWayBetweenSlicesIsInside) {
  dose::Structure s;
  s.name = "prostate";
  for (const double z : {0.0, 1e-3, 2e-3}) {
    s.contours.push_back({z, {{-5e-3, -5e-3}, {5e-3, -5e-3}, {5e-3, 5e-3}, {-5e-3, 5e-3}}});
  }
  s.normalise();
  EXPECT_TRUE(s.contains({0.0, 0.0, 0.5e-3}));
  EXPECT_TRUE(s.contains({0.0, 0.0, 1.5e-3}));
  EXPECT_FALSE(s.contains({6e-3, 0.0, 0.5e-3}));
  EXPECT_FALSE(s.contains({0.0, 0.0, 2.6e-3}));
}

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
