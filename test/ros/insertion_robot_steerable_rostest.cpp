// rostest node for insertion_robot in steerable mode (insertion_robot_steerable.test): with the
// deflections off, the true tip the node publishes must follow the exact arcs of advanceTip;
// entry changes in tissue are refused; an insertion into an obstacle stops at the contact the
// continuous workspace predicts; retraction returns to the entry.
#include <actionlib/client/simple_action_client.h>
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <sensor_msgs/JointState.h>
#include <visualization_msgs/Marker.h>

#include <cmath>
#include <limits>
#include <mutex>
#include <optional>
#include <string>

#include "../ros_wait.h"
#include "needle_guidance/FlipBevelAction.h"
#include "needle_guidance/LinearMoveAction.h"
#include "needle_guidance/NeedleTip.h"
#include "needle_guidance/SetEntryPose.h"
#include "needle_guidance/math.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/continuous_workspace.h"
#include "needle_guidance/steering/steering_model.h"

namespace {

namespace st = needle_guidance::steering;
using LinearMoveClient = actionlib::SimpleActionClient<needle_guidance::LinearMoveAction>;
using FlipBevelClient = actionlib::SimpleActionClient<needle_guidance::FlipBevelAction>;
using State = actionlib::SimpleClientGoalState;

using needle_guidance::kPi;
constexpr double kPoseTol_m = 1e-6;  // published tip vs advanceTip (sigmas are 0)
constexpr double kAngleTol_rad = 1e-6;
// The node checks contact step by step, the test in one trace; the two chord polylines may
// meet the obstacle edge a little apart.
constexpr double kContactTol_m = 1e-4;
constexpr double kInsertVelocity_m_s = 0.05;  // the URDF's limit, in simulated time
constexpr double kFlipVelocity_rad_s = 6.0;
const ros::Duration kTimeout(20.0);

class InsertionRobotSteerableTest : public ::testing::Test {
protected:
  void SetUp() override {
    const needle_guidance::scene::Scene scene =
        needle_guidance::scene::loadSceneSpec("steering_workspace");
    problem_ = st::problemFromScene(scene);
    start_x_m_ = scene.steering->start_x_m;
    tip_sub_ = nh_.subscribe("insertion_robot/measured_tip", 100,
                             &InsertionRobotSteerableTest::onTip, this);
    js_sub_ = nh_.subscribe("insertion_robot/measured_js", 100,
                            &InsertionRobotSteerableTest::onJointState, this);
    path_sub_ = nh_.subscribe("insertion_robot/needle_path", 10,
                              &InsertionRobotSteerableTest::onPath, this);
    entry_ = nh_.serviceClient<needle_guidance::SetEntryPose>("insertion_robot/set_entry_pose");
    ASSERT_TRUE(entry_.waitForExistence(kTimeout));
    ASSERT_TRUE(insert_.waitForServer(kTimeout));
    ASSERT_TRUE(retract_.waitForServer(kTimeout));
    ASSERT_TRUE(flip_.waitForServer(kTimeout));
    ASSERT_TRUE(waitFor([this] { return tip().has_value() && joints().has_value(); }));
  }

  void onTip(const needle_guidance::NeedleTipConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex_);
    tip_ = *msg;
  }
  void onJointState(const sensor_msgs::JointStateConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex_);
    joints_ = *msg;
  }
  void onPath(const visualization_msgs::MarkerConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex_);
    path_ = *msg;
  }
  std::optional<needle_guidance::NeedleTip> tip() {
    std::lock_guard<std::mutex> lock(mutex_);
    return tip_;
  }
  std::optional<sensor_msgs::JointState> joints() {
    std::lock_guard<std::mutex> lock(mutex_);
    return joints_;
  }
  std::optional<visualization_msgs::Marker> path() {
    std::lock_guard<std::mutex> lock(mutex_);
    return path_;
  }
  /// The tip after letting the node publish a few more times.
  needle_guidance::NeedleTip settledTip() {
    ros::WallDuration(0.3).sleep();
    return *tip();
  }
  State move(LinearMoveClient& client, double target_m) {
    needle_guidance::LinearMoveGoal goal;
    goal.target_m = target_m;
    goal.velocity_m_s = kInsertVelocity_m_s;
    return client.sendGoalAndWait(goal, kTimeout);
  }
  State flip() {
    needle_guidance::FlipBevelGoal goal;
    goal.velocity_rad_s = kFlipVelocity_rad_s;
    return flip_.sendGoalAndWait(goal, kTimeout);
  }
  needle_guidance::SetEntryPose::Response setEntry(double height_m, double angle_rad,
                                                   const std::string& bevel) {
    needle_guidance::SetEntryPose srv;
    srv.request.height_m = height_m;
    srv.request.angle_rad = angle_rad;
    srv.request.bevel = bevel;
    EXPECT_TRUE(entry_.call(srv));
    return srv.response;
  }
  st::TipPose entryPose(double height_m, double angle_rad, st::Bevel bevel) const {
    st::TipPose pose;
    pose.p_SceneTip = {start_x_m_, height_m};
    pose.theta_rad = angle_rad;
    pose.bevel = bevel;
    return pose;
  }
  static st::TipPose fromMessage(const needle_guidance::NeedleTip& msg) {
    st::TipPose pose;
    pose.p_SceneTip = {msg.pose.x, msg.pose.y};
    pose.theta_rad = msg.pose.theta;
    pose.bevel = msg.bevel == "right" ? st::Bevel::kRight : st::Bevel::kLeft;
    return pose;
  }
  static void expectTip(const needle_guidance::NeedleTip& actual, const st::TipPose& expected,
                        double length_m, double tol_m) {
    EXPECT_EQ(actual.header.frame_id, "scene");
    EXPECT_NEAR(actual.pose.x, expected.p_SceneTip.x(), tol_m);
    EXPECT_NEAR(actual.pose.y, expected.p_SceneTip.y(), tol_m);
    EXPECT_NEAR(actual.pose.theta, expected.theta_rad, kAngleTol_rad);
    EXPECT_EQ(actual.bevel, st::toString(expected.bevel));
    EXPECT_NEAR(actual.inserted_length_m, length_m, tol_m);
  }
  double radius_m() const { return problem_.params.radius_m; }
  double delta_m() const { return 2.0 * kPi * radius_m() / problem_.params.orientations; }

  ros::NodeHandle nh_;
  st::SteeringProblem problem_;
  double start_x_m_ = 0.0;
  ros::Subscriber tip_sub_;
  ros::Subscriber js_sub_;
  ros::Subscriber path_sub_;
  ros::ServiceClient entry_;
  std::mutex mutex_;
  std::optional<needle_guidance::NeedleTip> tip_;
  std::optional<sensor_msgs::JointState> joints_;
  std::optional<visualization_msgs::Marker> path_;
  LinearMoveClient insert_{"insertion_robot/insert", true};
  LinearMoveClient retract_{"insertion_robot/retract", true};
  FlipBevelClient flip_{"insertion_robot/flip_bevel", true};
};

TEST_F(InsertionRobotSteerableTest, InsertFlipContactAndRetractFollowTheExactArcs) {
  ASSERT_NEAR(radius_m(), 0.05, 1e-12);  // the scene the numbers below assume
  // Entry.
  const auto placed = setEntry(0.02, 0.0, "left");
  ASSERT_TRUE(placed.success) << placed.message;
  const st::TipPose w0 = entryPose(0.02, 0.0, st::Bevel::kLeft);
  expectTip(settledTip(), w0, 0.0, kPoseTol_m);

  // Insert delta = 2 pi r / N_c with the bevel left.
  ASSERT_EQ(move(insert_, delta_m()), State::SUCCEEDED) << insert_.getResult()->message;
  EXPECT_TRUE(insert_.getResult()->success);
  EXPECT_NEAR(insert_.getResult()->reached_m, delta_m(), kPoseTol_m);
  const st::TipPose w1 = st::advanceTip(w0, st::Control::kInsert, 0.0, delta_m(), radius_m());
  expectTip(settledTip(), w1, delta_m(), kPoseTol_m);

  // Flip, then insert delta: the control u = 1 of 5.3.
  ASSERT_EQ(flip(), State::SUCCEEDED) << flip_.getResult()->message;
  EXPECT_NEAR(flip_.getResult()->bevel_rad, kPi, 1e-9);
  EXPECT_EQ(settledTip().bevel, "right");
  ASSERT_EQ(move(insert_, 2.0 * delta_m()), State::SUCCEEDED) << insert_.getResult()->message;
  const st::TipPose w2 = st::advanceTip(w1, st::Control::kFlip, 0.0, delta_m(), radius_m());
  expectTip(settledTip(), w2, 2.0 * delta_m(), kPoseTol_m);
  ASSERT_TRUE(waitFor([this] { return path() && path()->points.size() >= 2; }));
  EXPECT_EQ(path()->header.frame_id, "scene");
  EXPECT_NEAR(path()->points.back().x, w2.p_SceneTip.x(), kPoseTol_m);
  EXPECT_NEAR(path()->points.back().y, w2.p_SceneTip.y(), kPoseTol_m);

  // No new entry while the needle is in tissue; nothing moves.
  const auto in_tissue = setEntry(0.03, 0.0, "left");
  EXPECT_FALSE(in_tissue.success);
  EXPECT_NE(in_tissue.message.find("in tissue"), std::string::npos) << in_tissue.message;
  expectTip(settledTip(), w2, 2.0 * delta_m(), kPoseTol_m);

  // Towards an obstacle: of the two controls from w2, take one whose arc the continuous
  // workspace says ends on an obstacle, and insert far beyond it.
  const st::ContinuousWorkspace world(problem_);
  constexpr double kLong_m = 0.1;
  st::Control control = st::Control::kInsert;
  st::ArcTrace trace = world.traceArc(w2, control, 0.0, kLong_m);
  if (trace.outcome != st::ArcOutcome::kObstacle) {
    control = st::Control::kFlip;
    trace = world.traceArc(w2, control, 0.0, kLong_m);
  }
  ASSERT_EQ(trace.outcome, st::ArcOutcome::kObstacle)
      << "neither arc from the test's pose meets an obstacle in this scene";
  if (control == st::Control::kFlip) {
    ASSERT_EQ(flip(), State::SUCCEEDED);
  }
  const double target_m = 2.0 * delta_m() + kLong_m;
  EXPECT_EQ(move(insert_, target_m), State::ABORTED);
  const auto stopped = insert_.getResult();
  EXPECT_FALSE(stopped->success);
  EXPECT_NE(stopped->message.find("'" + trace.obstacle + "'"), std::string::npos)
      << "expected obstacle " << trace.obstacle << ": " << stopped->message;
  EXPECT_NEAR(stopped->reached_m, 2.0 * delta_m() + trace.free_length_m, kContactTol_m);
  const needle_guidance::NeedleTip at_contact = settledTip();
  EXPECT_NEAR(at_contact.pose.x, trace.end.p_SceneTip.x(), kContactTol_m);
  EXPECT_NEAR(at_contact.pose.y, trace.end.p_SceneTip.y(), kContactTol_m);
  EXPECT_LT(at_contact.inserted_length_m, target_m);
  // Stuck: another insertion is refused and moves nothing.
  EXPECT_EQ(move(insert_, target_m), State::ABORTED);
  EXPECT_NE(insert_.getResult()->message.find("contact"), std::string::npos)
      << insert_.getResult()->message;
  const needle_guidance::NeedleTip still = settledTip();
  EXPECT_EQ(still.pose.x, at_contact.pose.x);
  EXPECT_EQ(still.pose.y, at_contact.pose.y);

  // Retract to 0: back at the entry (the bevel stays where the last flip turned it).
  ASSERT_EQ(move(retract_, 0.0), State::SUCCEEDED) << retract_.getResult()->message;
  st::TipPose back = w0;
  back.bevel = fromMessage(still).bevel;
  expectTip(settledTip(), back, 0.0, kPoseTol_m);
  EXPECT_TRUE(
      waitFor([this] { return path() && path()->action == visualization_msgs::Marker::DELETE; }));
}

TEST_F(InsertionRobotSteerableTest, EntryPoseIsCheckedAndPlacesTheGuide) {
  // Starts out of tissue (the previous test retracts to 0).
  ASSERT_NEAR(settledTip().inserted_length_m, 0.0, 1e-12);
  const auto bad_angle = setEntry(0.05, 2.0, "left");
  EXPECT_FALSE(bad_angle.success);
  EXPECT_NE(bad_angle.message.find("angle"), std::string::npos) << bad_angle.message;
  const auto bad_bevel = setEntry(0.05, 0.0, "up");
  EXPECT_FALSE(bad_bevel.success);
  EXPECT_NE(bad_bevel.message.find("bevel"), std::string::npos) << bad_bevel.message;
  EXPECT_FALSE(setEntry(std::numeric_limits<double>::quiet_NaN(), 0.0, "left").success);
  EXPECT_FALSE(setEntry(0.2, 0.0, "left").success);  // above the scene's needle heights
  EXPECT_FALSE(retract_.sendGoalAndWait(needle_guidance::LinearMoveGoal(), kTimeout) ==
               State::SUCCEEDED);  // velocity 0

  const auto ok = setEntry(0.05, 0.1, "right");
  ASSERT_TRUE(ok.success) << ok.message;
  expectTip(settledTip(), entryPose(0.05, 0.1, st::Bevel::kRight), 0.0, kPoseTol_m);
  // The stage's height and bevel joints follow the guide.
  const sensor_msgs::JointState js = *joints();
  ASSERT_EQ(js.position.size(), 4u);  // height, insertion, bevel, axial_rotation (0 here)
  EXPECT_EQ(js.position[3], 0.0);
  EXPECT_NEAR(js.position[0], 0.05, 1e-12);
  EXPECT_NEAR(js.position[1], 0.0, 1e-12);
  EXPECT_NEAR(js.position[2], kPi, 1e-9);

  // Insert at the angle with the bevel right: the arc of advanceTip, and back.
  ASSERT_EQ(move(insert_, delta_m()), State::SUCCEEDED) << insert_.getResult()->message;
  expectTip(settledTip(),
            st::advanceTip(entryPose(0.05, 0.1, st::Bevel::kRight), st::Control::kInsert, 0.0,
                           delta_m(), radius_m()),
            delta_m(), kPoseTol_m);
  ASSERT_EQ(move(retract_, 0.0), State::SUCCEEDED);
  expectTip(settledTip(), entryPose(0.05, 0.1, st::Bevel::kRight), 0.0, kPoseTol_m);
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "insertion_robot_steerable_rostest");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  const int result = RUN_ALL_TESTS();
  ros::shutdown();
  return result;
}
