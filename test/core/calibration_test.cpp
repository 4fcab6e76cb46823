// Calibration of the needle–tissue interaction to measured forces: the CSV reader's refusals,
// recovery of known parameters from synthetic curves, the reduced curve against the FEM, and the
// shipped liver preset on held-out trials it was never fitted to.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <random>
#include <string>

#include "needle_guidance/calibration/calibration.h"
#include "needle_guidance/scene/interaction_preset.h"

namespace cal = needle_guidance::calibration;
namespace fs = std::filesystem;

namespace {

// Tolerances: parameter recovery from noisy synthetic curves, and agreement of the reduced
// curve with the FEM it stands for.
constexpr double kCuttingForceTol_N = 0.01;
constexpr double kFrictionTol_N_per_m = 0.3;
constexpr double kPunctureDepthTol_m = 0.1e-3;
// The FEM force jitters by a few hundredths of a newton about its trend as the tip cuts and
// nodes join the shaft; the reduced curve follows the trend.
constexpr double kReducedVsFemTol_N = 0.04;
constexpr double kFemParameterTol = 0.05;  // relative, FEM parameters found from FEM curves

class TempDir {
public:
  TempDir() {
    path_ = fs::temp_directory_path() /
            ("ng_calibration_" + std::to_string(::testing::UnitTest::GetInstance()->random_seed()) +
             "_" + ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(path_);
    fs::create_directories(path_);
  }
  ~TempDir() { fs::remove_all(path_); }
  std::string write(const std::string& name, const std::string& text) const {
    const fs::path p = path_ / name;
    std::ofstream(p) << text;
    return p.string();
  }
  std::string str() const { return path_.string(); }

private:
  fs::path path_;
};

/// The reader's message for a file, or "" when it reads.
std::string readError(const std::string& path) {
  try {
    cal::readForceTrial(path);
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "";
}

/// A trial sampled from a curve at 5 mm/s, 100 Hz, with Gaussian noise (fixed seed).
std::string syntheticTrial(const cal::ForceCurveParams& p, double depth_mm, double noise_N,
                           unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> noise(0.0, noise_N);
  std::string text = "t_s,depth_mm,force_N\n";
  for (int i = 0; 0.05 * i <= depth_mm; ++i) {
    const double d_mm = 0.05 * i;
    const double f = cal::reducedInsertionForce(p, {d_mm * 1e-3}).front() + noise(rng);
    text += std::to_string(0.01 * i) + "," + std::to_string(d_mm) + "," + std::to_string(f) + "\n";
  }
  return text;
}

}  // namespace

TEST(ForceTrialReader, ReadsTrialsWithBlankLinesAndWindowsLineEnds) {
  TempDir dir;
  const std::string path =
      dir.write("a.csv", "t_s,depth_mm,force_N\r\n0,0,0\r\n\r\n0.01,0.5,0.1\r\n0.02,1.0,0.2\r\n");
  const cal::ForceTrial trial = cal::readForceTrial(path);
  ASSERT_EQ(trial.t_s.size(), 3u);
  EXPECT_EQ(trial.name, "a");
  EXPECT_DOUBLE_EQ(trial.depth_m[2], 1e-3);
  EXPECT_DOUBLE_EQ(trial.force_N[1], 0.1);
}

TEST(ForceTrialReader, RefusesBadInputNamingFileAndLine) {
  TempDir dir;
  struct Case {
    std::string text, expected;
  };
  const std::vector<Case> cases{
      {"time,depth,force\n0,0,0\n", "a.csv:1: header"},
      {"t_s,depth_mm,force_N\n0,0\n", "a.csv:2: expected 3 fields"},
      {"t_s,depth_mm,force_N\n0,0,0\n0.1,x,0\n", "a.csv:3: depth_mm 'x' is not a number"},
      {"t_s,depth_mm,force_N\n0,0,0\n0.1,1,nan\n", "a.csv:3: force_N 'nan' is not finite"},
      {"t_s,depth_mm,force_N\n0,0,0\n0,1,0\n", "a.csv:3: time 0 s does not increase"},
      {"t_s,depth_mm,force_N\n0,0,0\n", "fewer than two samples"},
      {"", "a.csv:1: empty file"},
      {"t_s,depth_mm,force_N\n0,0,0\n0.1,1,2 N\n", "a.csv:3: force_N '2 N' is not a number"},
  };
  for (const Case& c : cases) {
    const std::string message = readError(dir.write("a.csv", c.text));
    EXPECT_NE(message.find(c.expected), std::string::npos) << "got: " << message;
  }
  EXPECT_NE(readError(dir.str() + "/missing.csv").find("missing.csv: cannot open"),
            std::string::npos);
  EXPECT_THROW(cal::readForceTrials(dir.str() + "/no_such_folder"), std::invalid_argument);
  TempDir empty;
  EXPECT_THROW(cal::readForceTrials(empty.str()), std::invalid_argument);
}

TEST(ForceTrialReader, RefusesATrialTooShallowForTheGrid) {
  TempDir dir;
  dir.write("deep.csv", "t_s,depth_mm,force_N\n0,0,0\n1,10,1\n");
  dir.write("shallow.csv", "t_s,depth_mm,force_N\n0,0,0\n1,0.8,1\n");
  const auto trials = cal::readForceTrials(dir.str());
  try {
    cal::compareDepths(trials, cal::CompareGrid{});
    FAIL() << "a trial 0.8 mm deep cannot be compared from 0.5 mm to 0.5 mm short of its end";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("shallow.csv"), std::string::npos) << e.what();
  }
  EXPECT_THROW(cal::insertionForceAt(trials[1], {1e-3, 5e-3}), std::invalid_argument);
}

TEST(InsertionForceFit, RecoversKnownParametersFromNoisySyntheticTrials) {
  TempDir dir;
  const cal::ForceCurveParams truth{0.42, 13.5, 1.6e-3};
  for (unsigned seed = 1; seed <= 8; ++seed) {
    dir.write("trial_" + std::to_string(seed) + ".csv", syntheticTrial(truth, 60.0, 0.05, seed));
  }
  const cal::CompareGrid grid{0.25e-3, 0.25e-3, 0.0};  // fine enough to place the puncture
  const cal::CrossValidation cv = cal::crossValidate(cal::readForceTrials(dir.str()), grid, 4, 7);
  const cal::ForceCurveParams& fit = cv.full_fit.params;
  EXPECT_NEAR(fit.cutting_force_N, truth.cutting_force_N, kCuttingForceTol_N);
  EXPECT_NEAR(fit.friction_N_per_m, truth.friction_N_per_m, kFrictionTol_N_per_m);
  EXPECT_NEAR(fit.puncture_depth_m, truth.puncture_depth_m, kPunctureDepthTol_m);
  // Held out, the model's error is the noise (0.05 N), as is the spread between trials.
  const cal::ScoreSummary s = cal::summarise(cv.scores);
  EXPECT_NEAR(s.rmse_median_N, 0.05, 0.01);
  EXPECT_LE(s.rmse_median_N, s.spread_median_N);
  ASSERT_EQ(cv.scores.size(), 8u);
  for (const auto& score : cv.scores) {
    EXPECT_GE(score.fold, 0);
  }
}

TEST(InsertionForceFit, ReducedCurveMatchesTheFem) {
  // The FEM with the parameters the reduced curve maps onto gives the reduced curve.
  const cal::ForceCurveParams curve{0.35, 15.0, 1.2e-3};
  cal::InteractionModel base;
  base.needle.cut_length_m = 1e-4;
  base.needle.tip_radius_m = 0.635e-3;
  base.needle.stick_velocity_m_s = 5e-4;
  const std::vector<double> depths = cal::depthGrid(0.5e-3, 40e-3, 0.5e-3);
  const cal::InteractionModel model = cal::interactionFromCurve(curve, base, 1.5, depths);
  EXPECT_NEAR(cal::prePunctureStiffness(model), 0.35 / 1.2e-3, 0.35 / 1.2e-3 * 1e-6);
  const std::vector<double> fem = cal::femInsertionForce(model.block, model.needle, depths);
  EXPECT_LE(cal::rmse(fem, cal::reducedInsertionForce(curve, depths)), kReducedVsFemTol_N);
}

TEST(InsertionForceFit, RecoversFemParametersFromFemCurves) {
  // Synthetic measurements made by the FEM itself (plus fixed-seed noise) give back its
  // cutting force and friction.
  cal::InteractionModel model;
  model.needle.cutting_force_N = 0.3;
  model.needle.kinetic_friction_N_per_m = 18.0;
  model.needle.static_friction_N_per_m = 27.0;
  model.needle.cut_length_m = 1e-4;
  model.needle.tip_radius_m = 0.635e-3;
  const std::vector<double> depths = cal::depthGrid(0.5e-3, 40e-3, 0.5e-3);
  const std::vector<double> fem = cal::femInsertionForce(model.block, model.needle, depths);
  std::mt19937 rng(3);
  std::normal_distribution<double> noise(0.0, 0.02);
  std::vector<std::vector<double>> curves(5, fem);
  for (auto& c : curves) {
    for (double& f : c) {
      f += noise(rng);
    }
  }
  const cal::ForceFit fit = cal::fitInsertionForce(curves, depths);
  cal::InteractionModel base = model;
  base.block.young_modulus_Pa = 50e3;  // the calibration has to find 20 kPa
  const cal::InteractionModel found = cal::interactionFromCurve(fit.params, base, 1.5, depths);
  EXPECT_NEAR(found.needle.cutting_force_N, 0.3, 0.3 * kFemParameterTol);
  EXPECT_NEAR(found.needle.kinetic_friction_N_per_m, 18.0, 18.0 * kFemParameterTol);
  EXPECT_NEAR(found.block.young_modulus_Pa, 20e3, 20e3 * kFemParameterTol);
}

TEST(InteractionPreset, ShippedLiverPresetPredictsHeldOutTrialsWithinTheirSpread) {
  const cal::InteractionModel model = cal::loadPreset("liver_de_jong_2017");
  std::string source;
  const std::vector<cal::ForceTrial> trials = cal::liverHeldOutTrials(&source);
  ASSERT_EQ(trials.size(), 6u) << source;
  const cal::PresetCheck check = cal::checkPreset(model, trials);
  for (double f : check.simulated_N) {
    ASSERT_TRUE(std::isfinite(f));
  }
  EXPECT_LE(check.summary.rmse_median_N, check.summary.spread_median_N) << source;
  EXPECT_LT(check.summary.rmse_median_N, 0.3) << source;
}

TEST(InteractionPreset, SceneLoadsPresetAndItsOwnKeysOverride) {
  const cal::InteractionModel preset = cal::loadPreset("liver_de_jong_2017");
  const std::string base =
      "scene: {name: s}\nworkspace: {min_cm: [0, 0], max_cm: [4, 4], background_material: t}\n"
      "models: {tissue: quasi_static}\nmaterials:\n  - {name: t, young_modulus_kPa: 20, "
      "poisson_ratio: 0.45}\nneedle:\n  min_height_cm: 1\n  max_height_cm: 3\n  max_depth_cm: 3\n"
      "  interaction: liver_de_jong_2017\n";
  const auto s = needle_guidance::scene::parseScene(base, "<test>");
  EXPECT_DOUBLE_EQ(s.needle.cutting_force_N, preset.needle.cutting_force_N);
  EXPECT_DOUBLE_EQ(s.needle.kinetic_friction_N_per_m, preset.needle.kinetic_friction_N_per_m);
  const auto o = needle_guidance::scene::parseScene(base + "  cutting_force_N: 0.7\n", "<test>");
  EXPECT_DOUBLE_EQ(o.needle.cutting_force_N, 0.7);
  EXPECT_DOUBLE_EQ(o.needle.static_friction_N_per_m, preset.needle.static_friction_N_per_m);
  // A scene's own kinetic friction above the preset's static friction is refused.
  EXPECT_THROW(
      needle_guidance::scene::parseScene(base + "  kinetic_friction_N_per_cm: 5\n", "<test>"),
      needle_guidance::scene::SceneError);
  try {
    needle_guidance::scene::parseScene(
        base.substr(0, base.find("liver_de_jong_2017")) + "liver_2099\n", "<unknown>");
    FAIL() << "an unknown preset must be refused";
  } catch (const needle_guidance::scene::SceneError& e) {
    const std::string m = e.what();
    EXPECT_NE(m.find("<unknown>"), std::string::npos) << m;
    EXPECT_NE(m.find("needle.interaction"), std::string::npos) << m;
    EXPECT_NE(m.find("liver_de_jong_2017"), std::string::npos) << m;  // lists what there is
  }
}

TEST(InteractionPreset, RefusesBadPresetsNamingTheFile) {
  TempDir dir;
  const std::string bad_key =
      dir.write("bad_key.yaml",
                "needle: {cutting_force_N: 0.3, kinetic_friction_N_per_cm: 0.1, "
                "static_friction_N_per_cm: 0.2, cutting_speed_N: 1}\n");
  const std::string negative = dir.write("negative.yaml", "needle: {cutting_force_N: -0.3}\n");
  const std::string inverted = dir.write(
      "inverted.yaml", "needle: {kinetic_friction_N_per_cm: 0.3, static_friction_N_per_cm: 0.2}\n");
  for (const std::string& path : {bad_key, negative, inverted}) {
    try {
      needle_guidance::scene::loadInteractionPreset(path);
      FAIL() << path << " must be refused";
    } catch (const needle_guidance::scene::SceneError& e) {
      EXPECT_NE(std::string(e.what()).find(path), std::string::npos) << e.what();
    }
  }
  // A preset without the calibration block cannot be scored.
  const std::string no_block = dir.write("no_block.yaml", "needle: {cutting_force_N: 0.3}\n");
  try {
    cal::loadPreset(no_block);
    FAIL() << "a preset without calibration_block cannot be simulated";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("calibration_block.length_mm"), std::string::npos)
        << e.what();
  }
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
