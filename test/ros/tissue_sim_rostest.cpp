// rostest for tissue_sim following the real insertion_robot: seeds, status, reset.
#include <actionlib/client/simple_action_client.h>
#include <geometry_msgs/PoseArray.h>
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <std_srvs/Trigger.h>

#include <cmath>
#include <mutex>

#include "../ros_wait.h"
#include "needle_guidance/ImplantSeed.h"
#include "needle_guidance/LinearMoveAction.h"
#include "needle_guidance/TissueStatus.h"

namespace {

using LinearMoveClient = actionlib::SimpleActionClient<needle_guidance::LinearMoveAction>;
using State = actionlib::SimpleClientGoalState;

constexpr double kTarget_m = 0.03;        // depth and height of the insertion
constexpr double kSeedAtTipTol_m = 1e-6;  // a seed is implanted exactly at the tissue's tip node
const ros::Duration kTimeout(30.0);

class TissueSimTest : public ::testing::Test {
protected:
  void SetUp() override {
    status_sub_ = nh_.subscribe("tissue_sim/status", 10, &TissueSimTest::onStatus, this);
    seeds_sub_ = nh_.subscribe("tissue_sim/seeds", 10, &TissueSimTest::onSeeds, this);
    implant_ = nh_.serviceClient<needle_guidance::ImplantSeed>("tissue_sim/implant_seed");
    reset_ = nh_.serviceClient<std_srvs::Trigger>("tissue_sim/reset");
    ASSERT_TRUE(implant_.waitForExistence(kTimeout));
    ASSERT_TRUE(reset_.waitForExistence(kTimeout));
    ASSERT_TRUE(insert_.waitForServer(kTimeout));
    ASSERT_TRUE(retract_.waitForServer(kTimeout));
  }
  void onStatus(const needle_guidance::TissueStatusConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex_);
    status_ = *msg;
    have_status_ = true;
  }
  void onSeeds(const geometry_msgs::PoseArrayConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex_);
    seeds_ = *msg;
  }
  /// waitFor (ros_wait.h) with pred() evaluated under the fixture's lock.
  template <typename Pred>
  bool waitLocked(Pred pred, double timeout_s = 10.0) {
    return waitFor(
        [&] {
          std::lock_guard<std::mutex> lock(mutex_);
          return pred();
        },
        timeout_s, 0.02);
  }
  State move(LinearMoveClient& client, double target_m, double velocity_m_s) {
    needle_guidance::LinearMoveGoal goal;
    goal.target_m = target_m;
    goal.velocity_m_s = velocity_m_s;
    return client.sendGoalAndWait(goal, kTimeout);
  }

  ros::NodeHandle nh_;
  ros::Subscriber status_sub_, seeds_sub_;
  ros::ServiceClient implant_, reset_;
  std::mutex mutex_;
  needle_guidance::TissueStatus status_;
  bool have_status_ = false;
  geometry_msgs::PoseArray seeds_;
  LinearMoveClient insert_{"insertion_robot/insert", true};
  LinearMoveClient retract_{"insertion_robot/retract", true};
};

TEST_F(TissueSimTest, SeedImplantedAtTheTipMovesWithTheTissueAndResetClearsIt) {
  ASSERT_TRUE(waitLocked([this] { return have_status_; }));
  needle_guidance::ImplantSeed srv;
  ASSERT_TRUE(implant_.call(srv));
  EXPECT_FALSE(srv.response.success) << "a seed outside tissue must be refused";
  EXPECT_NE(srv.response.message.find("not in tissue"), std::string::npos) << srv.response.message;

  ASSERT_EQ(move(insert_, kTarget_m, 0.02), State::SUCCEEDED);
  ASSERT_TRUE(waitLocked([this] {
    return status_.needle_in_tissue && status_.shaft_nodes > 0 &&
           std::isfinite(status_.tip_force_N);
  }));
  ros::WallDuration(0.3).sleep();  // the simulation catches up with the stopped robot
  ASSERT_TRUE(implant_.call(srv));
  ASSERT_TRUE(srv.response.success) << srv.response.message;
  EXPECT_NEAR(srv.response.position.x, kTarget_m, kSeedAtTipTol_m);
  EXPECT_NEAR(srv.response.position.y, kTarget_m, kSeedAtTipTol_m);

  ASSERT_EQ(move(retract_, -0.005, 0.05), State::SUCCEEDED);
  ASSERT_TRUE(waitLocked([this] { return !status_.needle_in_tissue; }));
  ros::WallDuration(0.3).sleep();
  ASSERT_TRUE(waitLocked([this] { return seeds_.poses.size() == 1U; }));
  {
    std::lock_guard<std::mutex> lock(mutex_);
    const auto& p = seeds_.poses.front().position;
    EXPECT_TRUE(std::isfinite(p.x) && std::isfinite(p.y));
    // The tissue was pushed ahead of the needle: once released, the seed lies short of the tip
    // position where it was implanted, by less than the insertion depth [m].
    EXPECT_LT(p.x, kTarget_m - 1e-4);
    EXPECT_GT(p.x, 0.0);
    EXPECT_NEAR(p.y, kTarget_m, 2e-3);
  }

  std_srvs::Trigger trigger;
  ASSERT_TRUE(reset_.call(trigger));
  EXPECT_TRUE(trigger.response.success);
  EXPECT_TRUE(waitLocked([this] { return seeds_.poses.empty(); }));
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "tissue_sim_rostest");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  const int result = RUN_ALL_TESTS();
  ros::shutdown();
  return result;
}
