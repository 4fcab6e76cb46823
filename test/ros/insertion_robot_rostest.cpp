// rostest node for insertion_robot: motion accuracy and refusals, against the real node.
#include <actionlib/client/simple_action_client.h>
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <sensor_msgs/JointState.h>
#include <std_srvs/Trigger.h>

#include <mutex>
#include <vector>

#include "../ros_wait.h"
#include "needle_guidance/FlipBevelAction.h"
#include "needle_guidance/LinearMoveAction.h"
#include "needle_guidance/OperatingState.h"

namespace {

using LinearMoveClient = actionlib::SimpleActionClient<needle_guidance::LinearMoveAction>;
using FlipBevelClient = actionlib::SimpleActionClient<needle_guidance::FlipBevelAction>;
using State = actionlib::SimpleClientGoalState;

constexpr double kDepthTol_m = 1e-6;      // reached depth vs commanded
constexpr double kVelocityRelTol = 0.02;  // measured insertion speed vs commanded
constexpr double kUnchangedTol = 1e-12;   // a refused command moves nothing
const ros::Duration kTimeout(20.0);

struct Sample {
  double t_s;
  double height_m;
  double depth_m;
  double bevel_rad;
};

class InsertionRobotTest : public ::testing::Test {
protected:
  void SetUp() override {
    js_sub_ =
        nh_.subscribe("insertion_robot/measured_js", 1000, &InsertionRobotTest::onJointState, this);
    op_sub_ = nh_.subscribe("insertion_robot/operating_state", 10,
                            &InsertionRobotTest::onOperatingState, this);
    ASSERT_TRUE(height_.waitForServer(kTimeout));
    ASSERT_TRUE(insert_.waitForServer(kTimeout));
    ASSERT_TRUE(retract_.waitForServer(kTimeout));
    ASSERT_TRUE(flip_.waitForServer(kTimeout));
    ASSERT_TRUE(waitFor([this] { return latest().has_value(); }));
  }

  void onJointState(const sensor_msgs::JointStateConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex_);
    ASSERT_EQ(msg->name.size(), 4U);
    EXPECT_EQ(msg->name[0], "height");
    EXPECT_EQ(msg->name[1], "insertion");
    EXPECT_EQ(msg->name[2], "bevel");
    EXPECT_EQ(msg->name[3], "axial_rotation");  // the URDF's continuous joint, 0 in rigid mode
    EXPECT_EQ(msg->position[3], 0.0);
    samples_.push_back(
        {msg->header.stamp.toSec(), msg->position[0], msg->position[1], msg->position[2]});
  }
  void onOperatingState(const needle_guidance::OperatingStateConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex_);
    op_state_ = msg->state;
  }
  std::optional<Sample> latest() {
    std::lock_guard<std::mutex> lock(mutex_);
    if (samples_.empty()) {
      return std::nullopt;
    }
    return samples_.back();
  }
  std::string opState() {
    std::lock_guard<std::mutex> lock(mutex_);
    return op_state_;
  }
  /// The state after letting the node run a little (several publish periods).
  Sample settledState() {
    ros::WallDuration(0.3).sleep();
    return *latest();
  }
  State move(LinearMoveClient& client, double target_m, double velocity_m_s) {
    needle_guidance::LinearMoveGoal goal;
    goal.target_m = target_m;
    goal.velocity_m_s = velocity_m_s;
    return client.sendGoalAndWait(goal, kTimeout);
  }
  void expectUnchanged(const Sample& before, const Sample& after) {
    EXPECT_NEAR(after.height_m, before.height_m, kUnchangedTol);
    EXPECT_NEAR(after.depth_m, before.depth_m, kUnchangedTol);
    EXPECT_NEAR(after.bevel_rad, before.bevel_rad, kUnchangedTol);
  }

  ros::NodeHandle nh_;
  ros::Subscriber js_sub_;
  ros::Subscriber op_sub_;
  std::mutex mutex_;
  std::vector<Sample> samples_;
  std::string op_state_;
  LinearMoveClient height_{"insertion_robot/move_to_height", true};
  LinearMoveClient insert_{"insertion_robot/insert", true};
  LinearMoveClient retract_{"insertion_robot/retract", true};
  FlipBevelClient flip_{"insertion_robot/flip_bevel", true};
};

TEST_F(InsertionRobotTest, InsertReachesDepthAtCommandedVelocity) {
  constexpr double kTarget_m = 0.03;
  constexpr double kVelocity_m_s = 0.02;
  ASSERT_EQ(move(height_, 0.03, 0.01), State::SUCCEEDED);
  const double t0 = ros::Time::now().toSec();
  ASSERT_EQ(move(insert_, kTarget_m, kVelocity_m_s), State::SUCCEEDED);
  const auto result = insert_.getResult();
  EXPECT_TRUE(result->success);
  EXPECT_NEAR(result->reached_m, kTarget_m, kDepthTol_m);
  EXPECT_NEAR(result->mean_velocity_m_s, kVelocity_m_s, kVelocityRelTol * kVelocity_m_s);
  EXPECT_NEAR(settledState().depth_m, kTarget_m, kDepthTol_m);

  // Least-squares slope of depth over time while moving, from measured_js.
  std::vector<Sample> moving;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const Sample& s : samples_) {
      if (s.t_s > t0 && s.depth_m > 0.002 && s.depth_m < kTarget_m - 0.002) {
        moving.push_back(s);
      }
    }
  }
  ASSERT_GE(moving.size(), 50U) << "too few measured_js samples while inserting";
  double mt = 0.0, md = 0.0;
  for (const Sample& s : moving) {
    mt += s.t_s;
    md += s.depth_m;
  }
  mt /= moving.size();
  md /= moving.size();
  double stt = 0.0, std_ = 0.0;
  for (const Sample& s : moving) {
    stt += (s.t_s - mt) * (s.t_s - mt);
    std_ += (s.t_s - mt) * (s.depth_m - md);
  }
  EXPECT_NEAR(std_ / stt, kVelocity_m_s, kVelocityRelTol * kVelocity_m_s);

  ASSERT_EQ(move(retract_, -0.005, 0.05), State::SUCCEEDED);
  EXPECT_NEAR(retract_.getResult()->reached_m, -0.005, kDepthTol_m);
}

TEST_F(InsertionRobotTest, FlipBevelTurnsHalfAround) {
  const Sample before = settledState();
  needle_guidance::FlipBevelGoal goal;
  goal.velocity_rad_s = 6.0;
  ASSERT_EQ(flip_.sendGoalAndWait(goal, kTimeout), State::SUCCEEDED);
  EXPECT_NEAR(std::abs(flip_.getResult()->bevel_rad - before.bevel_rad), M_PI, 1e-9);
  ASSERT_EQ(flip_.sendGoalAndWait(goal, kTimeout), State::SUCCEEDED);
  EXPECT_NEAR(flip_.getResult()->bevel_rad, before.bevel_rad, 1e-9);
}

TEST_F(InsertionRobotTest, OutOfLimitsCommandsAreRefusedAndNothingMoves) {
  const Sample before = settledState();
  EXPECT_EQ(move(insert_, 0.5, 0.01), State::ABORTED);  // beyond the joint limit
  EXPECT_NE(insert_.getResult()->message.find("outside the joint limits"), std::string::npos)
      << insert_.getResult()->message;
  EXPECT_EQ(move(insert_, 0.058, 0.01), State::ABORTED);  // beyond the scene's max depth
  EXPECT_NE(insert_.getResult()->message.find("max depth"), std::string::npos);
  EXPECT_EQ(move(insert_, 0.02, 1.0), State::ABORTED);  // faster than the velocity limit
  EXPECT_NE(insert_.getResult()->message.find("velocity"), std::string::npos);
  EXPECT_EQ(move(insert_, 0.02, -0.01), State::ABORTED);    // negative velocity
  EXPECT_EQ(move(height_, -0.01, 0.01), State::ABORTED);    // below the height limit
  EXPECT_EQ(move(height_, 0.002, 0.01), State::SUCCEEDED);  // allowed outside tissue...
  EXPECT_EQ(move(insert_, 0.01, 0.01), State::ABORTED);     // ...but not an entry height
  EXPECT_NE(insert_.getResult()->message.find("entry range"), std::string::npos);
  EXPECT_EQ(move(height_, before.height_m, 0.01), State::SUCCEEDED);
  expectUnchanged(before, settledState());
}

TEST_F(InsertionRobotTest, HeightChangeInTissueIsRefused) {
  ASSERT_EQ(move(insert_, 0.01, 0.02), State::SUCCEEDED);
  const Sample before = settledState();
  EXPECT_EQ(move(height_, before.height_m + 0.005, 0.01), State::ABORTED);
  EXPECT_NE(height_.getResult()->message.find("in tissue"), std::string::npos);
  EXPECT_EQ(move(insert_, 0.005, 0.02), State::ABORTED);  // insert may not go backwards
  expectUnchanged(before, settledState());
  ASSERT_EQ(move(retract_, -0.005, 0.05), State::SUCCEEDED);
}

TEST_F(InsertionRobotTest, EstopStopsMotionAndRefusesCommandsUntilReset) {
  ros::ServiceClient estop = nh_.serviceClient<std_srvs::Trigger>("insertion_robot/estop");
  ros::ServiceClient reset = nh_.serviceClient<std_srvs::Trigger>("insertion_robot/reset_estop");
  ASSERT_TRUE(estop.waitForExistence(kTimeout));

  // E-stop during an insertion: the goal aborts and the needle stops short of the target.
  needle_guidance::LinearMoveGoal goal;
  goal.target_m = 0.04;
  goal.velocity_m_s = 0.01;
  insert_.sendGoal(goal);
  ASSERT_TRUE(waitFor([this] { return latest()->depth_m > 0.005; }));
  std_srvs::Trigger trigger;
  ASSERT_TRUE(estop.call(trigger));
  EXPECT_TRUE(trigger.response.success);
  ASSERT_TRUE(insert_.waitForResult(kTimeout));
  EXPECT_EQ(insert_.getState(), State::ABORTED);
  EXPECT_TRUE(waitFor([this] { return opState() == "ESTOP"; }));
  const Sample stopped = settledState();
  EXPECT_LT(stopped.depth_m, 0.04 - 0.01);

  // Every command is refused while stopped, and nothing moves.
  EXPECT_EQ(move(retract_, -0.005, 0.01), State::ABORTED);
  EXPECT_NE(retract_.getResult()->message.find("emergency stop"), std::string::npos);
  EXPECT_EQ(move(insert_, 0.03, 0.01), State::ABORTED);
  needle_guidance::FlipBevelGoal flip_goal;
  flip_goal.velocity_rad_s = 3.0;
  EXPECT_EQ(flip_.sendGoalAndWait(flip_goal, kTimeout), State::ABORTED);
  expectUnchanged(stopped, settledState());

  ASSERT_TRUE(reset.call(trigger));
  EXPECT_TRUE(trigger.response.success);
  EXPECT_TRUE(waitFor([this] { return opState() == "ENABLED"; }));
  EXPECT_EQ(move(retract_, -0.005, 0.05), State::SUCCEEDED);
}

TEST_F(InsertionRobotTest, SecondGoalWhileMovingIsRefusedAndCancelStops) {
  // Another client's goal while an insertion runs is rejected; the running one goes on to its
  // target. Only an explicit cancel of the running goal stops it.
  LinearMoveClient intruder("insertion_robot/insert", true);
  LinearMoveClient intruder_height("insertion_robot/move_to_height", true);
  ASSERT_TRUE(intruder.waitForServer(kTimeout));
  ASSERT_TRUE(intruder_height.waitForServer(kTimeout));
  needle_guidance::LinearMoveGoal goal;
  goal.target_m = 0.03;
  goal.velocity_m_s = 0.01;
  insert_.sendGoal(goal);
  ASSERT_TRUE(waitFor([this] { return latest()->depth_m > 0.003; }));
  needle_guidance::LinearMoveGoal stray;
  stray.target_m = 0.06;
  stray.velocity_m_s = 0.02;
  EXPECT_EQ(intruder.sendGoalAndWait(stray, kTimeout), State::REJECTED);
  ASSERT_TRUE(intruder.getResult());
  EXPECT_NE(intruder.getResult()->message.find("an insert motion is running"), std::string::npos)
      << intruder.getResult()->message;
  stray.target_m = 0.01;
  EXPECT_EQ(intruder_height.sendGoalAndWait(stray, kTimeout), State::REJECTED);
  ASSERT_TRUE(insert_.waitForResult(kTimeout));
  EXPECT_EQ(insert_.getState(), State::SUCCEEDED);
  EXPECT_NEAR(settledState().depth_m, 0.03, 1e-4) << "the running goal reached its own target [m]";

  // An explicit cancel stops the motion short of its target.
  goal.target_m = 0.05;
  insert_.sendGoal(goal);
  ASSERT_TRUE(waitFor([this] { return latest()->depth_m > 0.033; }));
  insert_.cancelGoal();
  ASSERT_TRUE(insert_.waitForResult(kTimeout));
  EXPECT_EQ(insert_.getState(), State::PREEMPTED);
  EXPECT_LT(settledState().depth_m, 0.05 - 0.005);
  EXPECT_EQ(move(retract_, -0.005, 0.05), State::SUCCEEDED);
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "insertion_robot_rostest");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  const int result = RUN_ALL_TESTS();
  ros::shutdown();
  return result;
}
