// SteerableStage3d (the insertion robot's 3-D steerable mode): a command ends where the
// core's noisy needle puts it with the same seed; unsafe rotations and insertions are refused
// with nothing changed and journalled; an insertion stops exactly at a contact and is refused
// until a retraction, which brings the tip back to the entry; the axial joint turns with the
// rotation and the duty cycle; entries off the disc are refused; the e-stop ends a command.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <sstream>
#include <string>

#include "needle_guidance/robot/steerable_stage_3d.h"

namespace needle_guidance::robot {
namespace {

namespace sd = needle_model;

constexpr double kDt_s = 0.002;
constexpr double kPoseTol_m = 1e-12;   // the stage replays the same arithmetic
constexpr double kStopTol_m = 1e-9;    // the stage stops at the contact it was commanded to
constexpr double kSpinTol_rad = 1e-9;  // joint angle after a whole command

std::string readFile(const std::string& path) {
  std::ifstream in(path);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

class SteerableStage3dTest : public ::testing::Test {
protected:
  SteerableStage3dTest()
      : scene_(sd::loadScene3d(std::string(NG_SOURCE_DIR) +
                               "/config/scenes/steering_3d/prostate_3d.yaml")),
        limits_(
            parseStageLimits(readFile(std::string(NG_SOURCE_DIR) + "/urdf/insertion_stage.urdf"))),
        stage_(limits_, SceneLimits{0.0, 0.12, limits_[StageJoint::kDepth].upper, 0.0},
               {0.06, 0.0, 0.0}),
        steer_(stage_, scene_, scene_.noise, limits_.spin_rate_max_rad_s, 3) {}

  /// Steps until the running command ends (at most `seconds`).
  SteerableStage3d::StepResult run(double seconds = 100.0) {
    for (int i = 0; i < static_cast<int>(seconds / kDt_s); ++i) {
      const SteerableStage3d::StepResult r = steer_.step(kDt_s);
      if (r.ended || !steer_.busy()) {
        return r;
      }
    }
    return {};
  }
  Steer3Command command(double rotate, double kappa, double length) const {
    return {{rotate, kappa, length}, 10.0, scene_.needle.insertion_speed_m_s};
  }

  sd::Scene3d scene_;
  StageLimits limits_;
  InsertionStage stage_;
  SteerableStage3d steer_;
};

TEST_F(SteerableStage3dTest, SpinRateLimitIsTheSmallerOfTheUrdfAndTheScene) {
  EXPECT_NEAR(limits_.spin_rate_max_rad_s, 2.0 * M_PI * 10.0, 1e-9);  // URDF: 10 rev/s
  EXPECT_NEAR(steer_.spinRateLimit_rad_s(), 2.0 * M_PI * 5.0, 1e-9);  // scene: 5 rev/s
}

TEST_F(SteerableStage3dTest, CommandsEndWhereTheCoreNeedleWithTheSameSeedEnds) {
  const sd::TipPose3 entry =
      sd::makeTipPose(sd::Vector3(0, 0.002, -0.001), sd::Vector3(1, 0.05, 0), sd::Vector3::UnitY());
  ASSERT_TRUE(steer_.setEntry(entry, 42));
  sd::NoisyNeedle3 reference(scene_.needle, scene_.noise, 42);
  sd::TipPose3 expected = steer_.entry();
  for (const sd::Control3& c : {sd::Control3{M_PI / 2, 10.0, 0.005}, sd::Control3{0.0, 4.0, 0.005},
                                sd::Control3{-1.0, 20.0, 0.003}}) {
    expected = reference.step(expected, c).pose;
    ASSERT_TRUE(steer_.steer(command(c.rotate_rad, c.curvature_per_m, c.length_m)));
    const SteerableStage3d::StepResult r = run();
    ASSERT_TRUE(r.ended && r.success) << r.message;
    EXPECT_LT((steer_.tip().p_SceneTip - expected.p_SceneTip).norm(), kPoseTol_m);
    EXPECT_LT((steer_.tip().R_SceneTip - expected.R_SceneTip).norm(), kPoseTol_m);
  }
  EXPECT_NEAR(steer_.insertedLength_m(), 0.013, kStopTol_m);
  // Whole duty cycles leave the joint at the commanded rotations: pi/2 - 1 rad.
  EXPECT_NEAR(steer_.spin_rad(), M_PI / 2 - 1.0, kSpinTol_rad);
  EXPECT_EQ(steer_.path().front(), entry.p_SceneTip);
  EXPECT_LT((steer_.path().back() - expected.p_SceneTip).norm(), kPoseTol_m);
}

TEST_F(SteerableStage3dTest, UnsafeCommandsAreRefusedWithNothingChangedAndJournalled) {
  const double limit = steer_.spinRateLimit_rad_s();
  const double v = scene_.needle.insertion_speed_m_s;
  struct Case {
    Steer3Command command;
    std::string says;
  };
  const std::vector<Case> cases = {
      {{{M_PI, 0.0, 0.005}, 2.0 * limit, v}, "spin-rate limit"},
      {{{M_PI, 0.0, 0.005}, 0.0, v}, "spin-rate limit"},
      {{{7.0, 0.0, 0.005}, 1.0, v}, "more than one turn"},
      {{{0.0, 25.0, 0.005}, 1.0, v}, "curvature"},
      {{{0.0, 0.0, 0.2}, 1.0, v}, "travel"},
      {{{0.0, 0.0, -0.005}, 1.0, v}, "not positive"},
      {{{0.0, 0.0, 0.005}, 1.0, 0.1}, "velocity"},
      // alpha = 0.5 over 2 mm cycles at 50 mm/s needs 314 rad/s
      {{{0.0, 10.0, 0.005}, 1.0, 0.05}, "insert slower"},
      {{{0.0, std::nan(""), 0.005}, 1.0, v}, "finite"},
  };
  const sd::TipPose3 before = steer_.tip();
  for (const Case& c : cases) {
    const std::size_t journalled = steer_.journal().size();
    const CommandStatus status = steer_.steer(c.command);
    EXPECT_FALSE(status) << c.says;
    EXPECT_NE(status.toString().find(c.says), std::string::npos) << status.toString();
    EXPECT_FALSE(steer_.busy());
    ASSERT_EQ(steer_.journal().size(), journalled + 1);
    EXPECT_EQ(steer_.journal().back().event, "steer");
    EXPECT_FALSE(steer_.journal().back().accepted);
  }
  EXPECT_EQ(steer_.tip().p_SceneTip, before.p_SceneTip);
  EXPECT_EQ(steer_.insertedLength_m(), 0.0);
  EXPECT_EQ(steer_.spin_rad(), 0.0);
  // The last refusal left the noise stream where it was: the next command matches a fresh one.
  sd::NoisyNeedle3 reference(scene_.needle, scene_.noise, 3);
  const sd::TipPose3 expected = reference.step(before, {0.0, 5.0, 0.005}).pose;
  ASSERT_TRUE(steer_.steer(command(0.0, 5.0, 0.005)));
  EXPECT_TRUE(run().success);
  EXPECT_LT((steer_.tip().p_SceneTip - expected.p_SceneTip).norm(), kPoseTol_m);
}

TEST_F(SteerableStage3dTest, InsertionStopsAtAContactUntilRetracted) {
  // Straight along the entry axis the urethra is in the way (steering_3d_trials_test).
  ASSERT_TRUE(steer_.steer(command(0.0, 0.0, 0.08)));
  const SteerableStage3d::StepResult r = run();
  EXPECT_TRUE(r.ended);
  EXPECT_FALSE(r.success);
  EXPECT_NE(r.message.find("urethra"), std::string::npos) << r.message;
  EXPECT_EQ(steer_.contact(), sd::Contact3::kObstacle);
  EXPECT_EQ(steer_.contactObstacle(), "urethra");
  const double stopped = steer_.insertedLength_m();
  EXPECT_GT(stopped, 0.0);
  EXPECT_LT(stopped, 0.08);
  EXPECT_EQ(steer_.journal().back().event, "contact");
  EXPECT_LT((steer_.tip().p_SceneTip - steer_.path().back()).norm(), kStopTol_m);
  // From the contact: refused, whatever the command.
  const CommandStatus again = steer_.steer(command(M_PI, 20.0, 0.005));
  EXPECT_FALSE(again);
  EXPECT_NE(again.toString().find("contact"), std::string::npos) << again.toString();
  EXPECT_EQ(steer_.insertedLength_m(), stopped);
  // Retracting halfway clears the contact; all the way brings the tip back to the entry.
  EXPECT_EQ(steer_.linearRefusal(LinearCommand::kRetract, 0.5 * stopped), "");
  ASSERT_TRUE(stage_.command(StageJoint::kDepth, 0.5 * stopped, 0.01));
  run();
  EXPECT_EQ(steer_.contact(), sd::Contact3::kFree);
  EXPECT_NEAR(steer_.tip().p_SceneTip.x(), 0.5 * stopped, 1e-4);  // nearly straight along +x
  ASSERT_TRUE(stage_.command(StageJoint::kDepth, 0.0, 0.01));
  run();
  EXPECT_EQ(steer_.tip().p_SceneTip, steer_.entry().p_SceneTip);
  EXPECT_EQ(steer_.path().size(), 1U);
  EXPECT_TRUE(steer_.steer(command(0.0, 20.0, 0.005)));
}

TEST_F(SteerableStage3dTest, TheAxialJointTurnsWithTheDutyCycle) {
  // kappa_max / 2: alpha = 0.5, a 5 mm step cut into two 2.5 mm cycles: two turns.
  ASSERT_TRUE(steer_.steer(command(0.0, 10.0, 0.005)));
  double max_turn = 0.0;
  for (int i = 0; i < 20000 && steer_.busy(); ++i) {
    steer_.step(kDt_s);
    max_turn = std::max(max_turn, std::abs(steer_.spin_rad()));
  }
  EXPECT_FALSE(steer_.busy());
  EXPECT_GT(max_turn, 3.0 * M_PI);  // more than one and a half turns on the way
  EXPECT_NEAR(std::remainder(steer_.spin_rad(), 2.0 * M_PI), 0.0, kSpinTol_rad);
  EXPECT_NEAR(steer_.lastCycle().spin_fraction, 0.5, 1e-12);
}

TEST_F(SteerableStage3dTest, EntriesOffTheDiscOrConeOrInTissueAreRefused) {
  const sd::Vector3 x = sd::Vector3::UnitX();
  const CommandStatus off_disc =
      steer_.setEntry(sd::makeTipPose(sd::Vector3(0, 0.05, 0), x, sd::Vector3::UnitY()), 1);
  EXPECT_FALSE(off_disc);
  EXPECT_NE(off_disc.toString().find("entry disc"), std::string::npos) << off_disc.toString();
  EXPECT_FALSE(steer_.setEntry(
      sd::makeTipPose(sd::Vector3::Zero(), sd::Vector3(1, 1, 0), sd::Vector3::UnitZ()), 1));
  EXPECT_FALSE(steer_.journal().back().accepted);
  ASSERT_TRUE(steer_.steer(command(0.0, 20.0, 0.005)));
  run();
  const CommandStatus in_tissue =
      steer_.setEntry(sd::makeTipPose(sd::Vector3::Zero(), x, sd::Vector3::UnitY()), 1);
  EXPECT_FALSE(in_tissue);
  EXPECT_NE(in_tissue.toString().find("in tissue"), std::string::npos) << in_tissue.toString();
}

TEST_F(SteerableStage3dTest, EmergencyStopEndsACommandWhereItIs) {
  ASSERT_TRUE(steer_.steer(command(M_PI, 0.0, 0.01)));
  for (int i = 0; i < 500; ++i) {
    steer_.step(kDt_s);
  }
  stage_.estop("test");
  const SteerableStage3d::StepResult r = steer_.step(kDt_s);
  EXPECT_TRUE(r.ended);
  EXPECT_FALSE(r.success);
  EXPECT_FALSE(steer_.busy());
  EXPECT_LT(steer_.insertedLength_m(), 0.01);
  EXPECT_EQ(steer_.journal().back().event, "stopped");
  EXPECT_FALSE(steer_.steer(command(0.0, 0.0, 0.005)));
}

}  // namespace
}  // namespace needle_guidance::robot

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
