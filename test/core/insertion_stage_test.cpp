// InsertionStage: limits from the URDF, constant-velocity motion, refusals, e-stop, journal.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <sstream>

#include "needle_guidance/robot/insertion_stage.h"

namespace needle_guidance::robot {
namespace {

constexpr double kPositionTol_m = 1e-12;
constexpr double kDt_s = 0.002;

std::string readFile(const std::string& path) {
  std::ifstream in(path);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

class InsertionStageTest : public ::testing::Test {
protected:
  InsertionStageTest()
      : limits_(
            parseStageLimits(readFile(std::string(NG_SOURCE_DIR) + "/urdf/insertion_stage.urdf"))),
        stage_(limits_, SceneLimits{0.005, 0.055, 0.055}, {0.03, -0.01, 0.0}) {}

  void run(double seconds) {
    for (int i = 0; i < static_cast<int>(std::lround(seconds / kDt_s)); ++i) {
      stage_.step(kDt_s);
    }
  }
  void expectState(const StageState& a, const StageState& b) {
    for (std::size_t j = 0; j < kStageJointCount; ++j) {
      EXPECT_NEAR(a.position[j], b.position[j], kPositionTol_m) << jointName(StageJoint(j));
    }
  }

  StageLimits limits_;
  InsertionStage stage_;
};

TEST_F(InsertionStageTest, LimitsComeFromTheUrdf) {
  EXPECT_DOUBLE_EQ(limits_[StageJoint::kHeight].lower, 0.0);
  EXPECT_DOUBLE_EQ(limits_[StageJoint::kHeight].upper, 0.12);
  EXPECT_DOUBLE_EQ(limits_[StageJoint::kDepth].lower, -0.03);
  EXPECT_DOUBLE_EQ(limits_[StageJoint::kDepth].upper, 0.15);
  EXPECT_DOUBLE_EQ(limits_[StageJoint::kDepth].max_velocity, 0.05);
  EXPECT_NEAR(limits_[StageJoint::kBevel].upper, M_PI, 1e-15);
  EXPECT_DOUBLE_EQ(limits_.needle_length_m, 0.20);
}

TEST_F(InsertionStageTest, BadUrdfIsRefusedNamingTheJoint) {
  std::string urdf = readFile(std::string(NG_SOURCE_DIR) + "/urdf/insertion_stage.urdf");
  EXPECT_THROW(parseStageLimits("<robot"), std::invalid_argument);
  const std::string no_velocity =
      std::string(urdf).replace(urdf.find("velocity=\"0.05\""), 15, "velocity=\"0\"");
  try {
    parseStageLimits(no_velocity);
    FAIL() << "a zero velocity limit was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("'insertion'"), std::string::npos) << e.what();
  }
}

TEST_F(InsertionStageTest, InsertMovesAtConstantVelocityAndStopsAtTarget) {
  ASSERT_TRUE(stage_.command(StageJoint::kDepth, 0.03, 0.01));
  run(1.0);  // 1 s at 10 mm/s from -10 mm
  EXPECT_NEAR(stage_.state().depth_m(), 0.0, 1e-9);
  EXPECT_NEAR(stage_.state().velocity[1], 0.01, 1e-12);
  EXPECT_TRUE(stage_.busy());
  run(3.5);
  EXPECT_NEAR(stage_.state().depth_m(), 0.03, kPositionTol_m);
  EXPECT_FALSE(stage_.busy());
  EXPECT_EQ(stage_.journal().back().event, "reached");
  EXPECT_EQ(stage_.tipPosition(), geometry::Point2(0.03, 0.03));
}

TEST_F(InsertionStageTest, RefusalsLeaveStateUnchangedAndAreJournalled) {
  const StageState before = stage_.state();
  EXPECT_FALSE(stage_.command(StageJoint::kDepth, 0.2, 0.01));        // joint limit
  EXPECT_FALSE(stage_.command(StageJoint::kDepth, 0.06, 0.01));       // scene max depth
  EXPECT_FALSE(stage_.command(StageJoint::kDepth, 0.02, 0.5));        // velocity limit
  EXPECT_FALSE(stage_.command(StageJoint::kDepth, 0.02, 0.0));        // zero velocity
  EXPECT_FALSE(stage_.command(StageJoint::kDepth, NAN, 0.01));        // NaN
  EXPECT_FALSE(stage_.command(StageJoint::kHeight, 0.03, INFINITY));  // inf
  const std::size_t refusals = stage_.journal().size();
  EXPECT_EQ(refusals, 6U);
  for (const JournalEntry& e : stage_.journal()) {
    EXPECT_FALSE(e.accepted);
  }
  run(0.5);
  expectState(before, stage_.state());
}

TEST_F(InsertionStageTest, HeightChangeInTissueIsRefused) {
  ASSERT_TRUE(stage_.command(StageJoint::kDepth, 0.01, 0.02));
  run(2.0);
  const StageState before = stage_.state();
  const CommandStatus status = stage_.command(StageJoint::kHeight, 0.04, 0.01);
  EXPECT_FALSE(status);
  EXPECT_NE(status.toString().find("in tissue"), std::string::npos) << status.toString();
  run(0.5);
  expectState(before, stage_.state());
}

TEST_F(InsertionStageTest, EntryOutsideTheSceneHeightsIsRefused) {
  ASSERT_TRUE(stage_.command(StageJoint::kHeight, 0.001, 0.02));
  run(2.0);
  EXPECT_FALSE(stage_.command(StageJoint::kDepth, 0.01, 0.01));
  EXPECT_TRUE(stage_.command(StageJoint::kDepth, -0.001, 0.01));  // moving outside tissue is fine
}

TEST_F(InsertionStageTest, BusyStageRefusesASecondMotion) {
  ASSERT_TRUE(stage_.command(StageJoint::kDepth, 0.02, 0.01));
  EXPECT_FALSE(stage_.command(StageJoint::kBevel, M_PI, 1.0));
  stage_.cancel();
  EXPECT_FALSE(stage_.busy());
  EXPECT_TRUE(stage_.flipBevel(2.0 * M_PI));
  run(1.0);
  EXPECT_NEAR(stage_.state().bevel_rad(), M_PI, kPositionTol_m);
}

TEST_F(InsertionStageTest, EstopStopsAtOnceAndRefusesUntilReset) {
  ASSERT_TRUE(stage_.command(StageJoint::kDepth, 0.03, 0.01));
  run(1.5);
  stage_.estop("test");
  const StageState stopped = stage_.state();
  EXPECT_EQ(stage_.operatingState(), OperatingState::kEstopped);
  EXPECT_FALSE(stage_.busy());
  EXPECT_FALSE(stage_.command(StageJoint::kDepth, 0.0, 0.01));
  EXPECT_FALSE(stage_.flipBevel(1.0));
  run(1.0);
  expectState(stopped, stage_.state());
  EXPECT_TRUE(stage_.resetEstop());
  EXPECT_FALSE(stage_.resetEstop());
  EXPECT_TRUE(stage_.command(StageJoint::kDepth, -0.005, 0.05));
}

TEST_F(InsertionStageTest, BadConstructionAndStepThrow) {
  EXPECT_THROW(InsertionStage(limits_, SceneLimits{0.0, 0.2, 0.05}, {0.03, -0.01, 0.0}),
               std::invalid_argument);  // scene heights beyond the stage
  EXPECT_THROW(InsertionStage(limits_, SceneLimits{0.0, 0.1, 0.5}, {0.03, -0.01, 0.0}),
               std::invalid_argument);  // scene depth beyond the stage
  EXPECT_THROW(InsertionStage(limits_, SceneLimits{0.0, 0.1, 0.05}, {0.03, NAN, 0.0}),
               std::invalid_argument);
  EXPECT_THROW(stage_.step(-1.0), std::invalid_argument);
  EXPECT_THROW(stage_.step(NAN), std::invalid_argument);
}

TEST_F(InsertionStageTest, JournalFileKeepsEveryEntry) {
  const std::string path = ::testing::TempDir() + "/insertion_stage_journal.csv";
  std::remove(path.c_str());
  {
    JournalFile file(path);
    stage_.setJournalSink([&file](const JournalEntry& e) { file.write(e); });
    EXPECT_FALSE(stage_.command(StageJoint::kDepth, 0.2, 0.01));
    EXPECT_TRUE(stage_.command(StageJoint::kDepth, 0.0, 0.05));
    run(1.0);
    stage_.setJournalSink(nullptr);
  }
  std::ifstream in(path);
  std::string line;
  std::vector<std::string> lines;
  while (std::getline(in, line)) {
    lines.push_back(line);
  }
  ASSERT_EQ(lines.size(), 4U);  // header, refused, accepted, reached
  EXPECT_EQ(lines[0], JournalFile::header());
  EXPECT_NE(lines[1].find(",command,insertion,"), std::string::npos);
  EXPECT_NE(lines[1].find("outside the joint limits"), std::string::npos);
  EXPECT_NE(lines[3].find(",reached,insertion,"), std::string::npos);
  EXPECT_THROW(JournalFile("/nonexistent_dir/x.csv"), std::runtime_error);
}

}  // namespace
}  // namespace needle_guidance::robot

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
