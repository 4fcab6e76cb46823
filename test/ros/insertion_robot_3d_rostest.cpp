// rostest node for insertion_robot in 3-D steerable mode (insertion_robot_3d.test): unsafe
// steer goals are refused with nothing moved; an accepted goal ends on the core needle's exact
// path (noise off); the axial rotation joint is published; a straight push stops at the
// urethra, further goals are refused until a retraction brings the tip back to the entry; an
// entry off the disc is refused; the journal holds one "steer" line per goal.
#include <actionlib/client/simple_action_client.h>
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <sensor_msgs/JointState.h>

#include <cmath>
#include <fstream>
#include <string>

#include "../ros_wait.h"
#include "needle_guidance/LinearMoveAction.h"
#include "needle_guidance/SetEntryPose3.h"
#include "needle_guidance/Steer3Action.h"
#include "needle_guidance/math.h"
#include "needle_guidance/needle_model/scene_3d.h"
#include "needle_guidance/ros/conversions_3d.h"

namespace {

namespace ng = needle_guidance;
namespace sd = needle_guidance::needle_model;
using SteerClient = actionlib::SimpleActionClient<ng::Steer3Action>;
using LinearMoveClient = actionlib::SimpleActionClient<ng::LinearMoveAction>;
using State = actionlib::SimpleClientGoalState;

using needle_guidance::kPi;
constexpr double kPoseTol_m = 1e-9;       // the node's tip vs the core needle (noise 0, via a Pose)
constexpr double kSpinRate_rad_s = 10.0;  // below the 5 rev/s spin-rate limit
const ros::Duration kTimeout(30.0);

class InsertionRobot3dTest : public ::testing::Test {
protected:
  void SetUp() override {
    ros::NodeHandle pnh("~");
    ASSERT_TRUE(pnh.getParam("scene", scene_path_));
    ASSERT_TRUE(pnh.getParam("journal", journal_));
    scene_ = sd::loadScene3d(scene_path_);
    v_ = scene_.needle.insertion_speed_m_s;
    entry_ = nh_.serviceClient<ng::SetEntryPose3>("insertion_robot/set_entry_pose_3d");
    ASSERT_TRUE(entry_.waitForExistence(kTimeout));
    ASSERT_TRUE(steer_.waitForServer(kTimeout));
    ASSERT_TRUE(retract_.waitForServer(kTimeout));
  }

  ng::Steer3Result steer(double rotate, double rate, double kappa, double length, double v) {
    ng::Steer3Goal goal;
    goal.rotate_rad = rotate;
    goal.spin_rate_rad_s = rate;
    goal.curvature_per_m = kappa;
    goal.length_m = length;
    goal.velocity_m_s = v;
    steer_.sendGoal(goal);
    EXPECT_TRUE(steer_.waitForResult(kTimeout));
    ++goals_;
    return *steer_.getResult();
  }
  void retract() {
    ng::LinearMoveGoal goal;
    goal.velocity_m_s = 0.05;
    retract_.sendGoal(goal);
    ASSERT_TRUE(retract_.waitForResult(kTimeout));
    EXPECT_EQ(retract_.getState(), State::SUCCEEDED) << retract_.getState().getText();
  }
  bool setEntry(const sd::TipPose3& pose, std::string& message) {
    ng::SetEntryPose3 srv;
    srv.request.entry = ng::ros_conversions::toMessage(pose);
    EXPECT_TRUE(entry_.call(srv));
    message = srv.response.message;
    return srv.response.success;
  }
  static sd::TipPose3 fromPose(const geometry_msgs::Pose& pose) {
    geometry_msgs::PoseWithCovarianceStamped msg;
    msg.header.frame_id = "scene";
    msg.pose.pose = pose;
    sd::TipPose3 tip;
    EXPECT_EQ(ng::ros_conversions::fromMessage(msg, "scene", tip), "");
    return tip;
  }
  /// Journal lines of `event` (",event," in the CSV).
  int journalLines(const std::string& event) const {
    std::ifstream in(journal_);
    int n = 0;
    for (std::string line; std::getline(in, line);) {
      n += line.find("," + event + ",") != std::string::npos ? 1 : 0;
    }
    return n;
  }

  ros::NodeHandle nh_;
  std::string scene_path_, journal_;
  sd::Scene3d scene_;
  double v_ = 0.0;
  int goals_ = 0;
  ros::ServiceClient entry_;
  SteerClient steer_{"insertion_robot/steer", true};
  LinearMoveClient retract_{"insertion_robot/retract", true};
};

TEST_F(InsertionRobot3dTest, UnsafeGoalsAreRefusedAndEveryGoalIsJournalled) {
  const sd::TipPose3 entry =
      sd::makeTipPose(sd::Vector3(0, 0.003, 0.002), sd::Vector3(1, 0, 0.05), sd::Vector3::UnitY());
  std::string message;
  ASSERT_TRUE(setEntry(entry, message)) << message;
  // A rotation faster than the spin-rate limit, and one too fast for the duty cycle at 50 mm/s.
  ng::Steer3Result r = steer(kPi, 4.0 * kPi * 5.0, 0.0, 0.005, v_);
  EXPECT_EQ(steer_.getState(), State::ABORTED);
  EXPECT_NE(r.message.find("spin-rate limit"), std::string::npos) << r.message;
  EXPECT_EQ(r.inserted_length_m, 0.0);
  r = steer(0.0, kSpinRate_rad_s, 10.0, 0.005, 0.05);
  EXPECT_EQ(steer_.getState(), State::ABORTED);
  EXPECT_NE(r.message.find("insert slower"), std::string::npos) << r.message;
  // An insertion beyond the joint's travel.
  r = steer(0.0, kSpinRate_rad_s, 0.0, 0.3, v_);
  EXPECT_EQ(steer_.getState(), State::ABORTED);
  EXPECT_NE(r.message.find("travel"), std::string::npos) << r.message;
  EXPECT_EQ(r.inserted_length_m, 0.0);
  // Accepted: the tip ends where the noiseless core needle ends.
  sd::NoisyNeedle3 core(scene_.needle, sd::NoiseParams3{}, 1);
  const sd::TipPose3 expected = core.step(entry, {kPi / 2, 10.0, 0.005}).pose;
  r = steer(kPi / 2, kSpinRate_rad_s, 10.0, 0.005, v_);
  EXPECT_EQ(steer_.getState(), State::SUCCEEDED) << r.message;
  EXPECT_LT((fromPose(r.tip).p_SceneTip - expected.p_SceneTip).norm(), kPoseTol_m);
  EXPECT_LT((fromPose(r.tip).R_SceneTip - expected.R_SceneTip).norm(), 1e-6);
  EXPECT_NEAR(r.inserted_length_m, 0.005, 1e-9);
  EXPECT_FALSE(r.saturated);
  EXPECT_GT(r.path.size(), 2U);
  // The axial rotation joint shows the rotation (whole duty-cycle turns leave it at pi / 2).
  const auto js = firstMessage<sensor_msgs::JointState>("insertion_robot/measured_js", 5.0);
  ASSERT_TRUE(js);
  ASSERT_EQ(js->name.size(), 4U);
  EXPECT_EQ(js->name[3], "axial_rotation");
  EXPECT_NEAR(js->position[3], kPi / 2, 1e-6);
  retract();
  // One "steer" line per goal, accepted or not (flushed per line).
  EXPECT_TRUE(waitFor([&] { return journalLines("steer") == goals_; }, 5.0))
      << journalLines("steer") << " steer lines for " << goals_ << " goals";
}

TEST_F(InsertionRobot3dTest, ContactStopsTheInsertionUntilRetracted) {
  std::string message;
  const sd::TipPose3 centre =
      sd::makeTipPose(scene_.entry.center_m, scene_.entry.direction, sd::Vector3::UnitY());
  ASSERT_TRUE(setEntry(centre, message)) << message;
  ng::Steer3Result r = steer(0.0, kSpinRate_rad_s, 0.0, 0.08, v_);
  EXPECT_EQ(steer_.getState(), State::ABORTED);
  EXPECT_EQ(r.contact, "obstacle");
  EXPECT_EQ(r.obstacle, "urethra");
  EXPECT_GT(r.inserted_length_m, 0.0);
  EXPECT_LT(r.inserted_length_m, 0.08);
  const double stopped = r.inserted_length_m;
  r = steer(kPi, kSpinRate_rad_s, 20.0, 0.005, v_);
  EXPECT_EQ(steer_.getState(), State::ABORTED);
  EXPECT_NE(r.message.find("contact"), std::string::npos) << r.message;
  EXPECT_EQ(r.inserted_length_m, stopped);
  // In tissue the guide cannot move.
  EXPECT_FALSE(setEntry(centre, message));
  EXPECT_NE(message.find("in tissue"), std::string::npos) << message;
  retract();
  r = steer(0.0, kSpinRate_rad_s, 20.0, 0.005, v_);
  EXPECT_EQ(steer_.getState(), State::SUCCEEDED) << r.message;
  retract();
  // Off the entry disc: refused.
  EXPECT_FALSE(
      setEntry(sd::makeTipPose(sd::Vector3(0, 0.05, 0), sd::Vector3::UnitX(), sd::Vector3::UnitY()),
               message));
  EXPECT_NE(message.find("entry disc"), std::string::npos) << message;
  EXPECT_EQ(journalLines("contact"), 1);
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "insertion_robot_3d_rostest");
  ros::AsyncSpinner spinner(1);
  spinner.start();
  return RUN_ALL_TESTS();
}
