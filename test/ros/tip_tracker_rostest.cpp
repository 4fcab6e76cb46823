// rostest node for the image-guided chain (tip_tracker.test): robot -> imager -> tip_tracker.
#include <actionlib/client/simple_action_client.h>
#include <cv_bridge/cv_bridge.h>
#include <gtest/gtest.h>
#include <ros/ros.h>

#include <cmath>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "../ros_wait.h"
#include "needle_guidance/ImageCalibration.h"
#include "needle_guidance/LinearMoveAction.h"
#include "needle_guidance/NeedleTip.h"
#include "needle_guidance/SetEntryPose.h"
#include "needle_guidance/math.h"

namespace {

using LinearMoveClient = actionlib::SimpleActionClient<needle_guidance::LinearMoveAction>;
using needle_guidance::NeedleTip;

using needle_guidance::kPi;
constexpr double kStep_m = 2.0 * kPi * 0.05 / 40.0;  // delta of steering_workspace
constexpr double kEntryHeight_m = 0.05;
constexpr double kEntryTol_m = 0.2e-3;  // the guide pose is known: [m]
constexpr double kTipTol_m = 1.0e-3;    // tracked vs true tip after an insertion [m]
constexpr double kHeadingTol_rad = 5.0 * kPi / 180.0;
constexpr double kInsertVelocity_m_s = 0.05;
const ros::Duration kTimeout(20.0);

class TipTrackerChainTest : public ::testing::Test {
protected:
  void SetUp() override {
    tracked_sub_ = nh_.subscribe("tip_tracker/tip", 100, &TipTrackerChainTest::onTracked, this);
    truth_sub_ =
        nh_.subscribe("insertion_robot/measured_tip", 100, &TipTrackerChainTest::onTruth, this);
    calibration_sub_ =
        nh_.subscribe("imager/calibration", 1, &TipTrackerChainTest::onCalibration, this);
    image_pub_ = nh_.advertise<sensor_msgs::Image>("imager/image", 5);
    entry_ = nh_.serviceClient<needle_guidance::SetEntryPose>("insertion_robot/set_entry_pose");
    ASSERT_TRUE(entry_.waitForExistence(kTimeout));
    ASSERT_TRUE(insert_.waitForServer(kTimeout));
    ASSERT_TRUE(retract_.waitForServer(kTimeout));
    ASSERT_TRUE(waitFor(
        [this] {
          std::lock_guard<std::mutex> lock(mutex_);
          return truth_.has_value() && calibration_.has_value() && !tracked_.empty();
        },
        30.0))
        << "no tracked tip, true tip or calibration";
  }

  void onTracked(const needle_guidance::NeedleTipConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex_);
    tracked_.push_back(*msg);
  }
  void onTruth(const needle_guidance::NeedleTipConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex_);
    truth_ = *msg;
  }
  void onCalibration(const needle_guidance::ImageCalibrationConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex_);
    calibration_ = *msg;
  }
  /// The first tracked tip stamped at or after `since` for which `accept` holds.
  template <typename Accept>
  std::optional<NeedleTip> trackedAfter(const ros::Time& since, Accept accept,
                                        double timeout_s = 10.0) {
    std::optional<NeedleTip> found;
    waitFor(
        [&] {
          std::lock_guard<std::mutex> lock(mutex_);
          for (const NeedleTip& t : tracked_) {
            if (t.header.stamp >= since && accept(t)) {
              found = t;
              return true;
            }
          }
          return false;
        },
        timeout_s);
    return found;
  }
  NeedleTip truth() {
    std::lock_guard<std::mutex> lock(mutex_);
    return *truth_;
  }
  bool place(double height_m) {
    needle_guidance::SetEntryPose srv;
    srv.request.height_m = height_m;
    srv.request.angle_rad = 0.0;
    srv.request.bevel = "left";
    return entry_.call(srv) && srv.response.success;
  }
  bool insertTo(double length_m) {
    needle_guidance::LinearMoveGoal goal;
    goal.target_m = length_m;
    goal.velocity_m_s = kInsertVelocity_m_s;
    return insert_.sendGoalAndWait(goal, kTimeout) == actionlib::SimpleClientGoalState::SUCCEEDED;
  }
  void retract() {
    needle_guidance::LinearMoveGoal goal;
    goal.target_m = 0.0;
    goal.velocity_m_s = kInsertVelocity_m_s;
    retract_.sendGoalAndWait(goal, kTimeout);
  }
  /// Publishes a frame with a unique stamp and returns the tracker's answer to it.
  std::optional<NeedleTip> answerTo(const cv::Mat& image, const std::string& encoding,
                                    double stamp_s) {
    cv_bridge::CvImage frame;
    frame.header.stamp = ros::Time(stamp_s);
    frame.encoding = encoding;
    frame.image = image;
    const ros::Time stamp(stamp_s);
    // The imager streams frames into the same topic (queue of 5), so under load one publication
    // can be dropped before the tracker sees it: the frame is sent again, up to three times.
    for (int attempt = 0; attempt < 3; ++attempt) {
      image_pub_.publish(frame.toImageMsg());
      if (auto answer = trackedAfter(ros::Time(0),
                                     [&](const NeedleTip& t) { return t.header.stamp == stamp; })) {
        return answer;
      }
    }
    return std::nullopt;
  }

  ros::NodeHandle nh_;
  std::mutex mutex_;
  std::vector<NeedleTip> tracked_;
  std::optional<NeedleTip> truth_;
  std::optional<needle_guidance::ImageCalibration> calibration_;
  ros::Subscriber tracked_sub_, truth_sub_, calibration_sub_;
  ros::Publisher image_pub_;
  ros::ServiceClient entry_;
  LinearMoveClient insert_{"insertion_robot/insert", true};
  LinearMoveClient retract_{"insertion_robot/retract", true};
};

TEST_F(TipTrackerChainTest, CalibrationDescribesTheWorkspaceFrames) {
  std::lock_guard<std::mutex> lock(mutex_);
  EXPECT_EQ(calibration_->modality, "ultrasound");
  EXPECT_EQ(calibration_->width, 500U);  // 10 cm / 0.2 mm
  EXPECT_EQ(calibration_->height, 500U);
  EXPECT_NEAR(calibration_->pixel_size_m, 0.2e-3, 1e-12);
  EXPECT_NEAR(calibration_->origin_y_m, 0.1, 1e-12);
}

TEST_F(TipTrackerChainTest, TracksTheTipThroughInsertions) {
  retract();
  ASSERT_TRUE(place(kEntryHeight_m));
  const ros::Time placed = ros::Time::now();
  const auto at_entry = trackedAfter(placed, [](const NeedleTip&) { return true; });
  ASSERT_TRUE(at_entry);
  EXPECT_EQ(at_entry->source, "entry");
  EXPECT_TRUE(at_entry->confident);
  EXPECT_NEAR(at_entry->pose.y, kEntryHeight_m, kEntryTol_m);
  for (int step = 1; step <= 3; ++step) {
    ASSERT_TRUE(insertTo(step * kStep_m)) << "step " << step;
    const ros::Time stopped = ros::Time::now();
    const auto tracked = trackedAfter(stopped, [](const NeedleTip& t) { return t.confident; });
    ASSERT_TRUE(tracked) << "no confident tracked tip after step " << step;
    const NeedleTip true_tip = truth();
    EXPECT_EQ(tracked->source, "tracked");
    EXPECT_NEAR(tracked->pose.x, true_tip.pose.x, kTipTol_m) << "step " << step;
    EXPECT_NEAR(tracked->pose.y, true_tip.pose.y, kTipTol_m) << "step " << step;
    EXPECT_NEAR(std::remainder(tracked->pose.theta - true_tip.pose.theta, 2.0 * kPi), 0.0,
                kHeadingTol_rad);
    EXPECT_EQ(tracked->bevel, true_tip.bevel);
    for (double c : tracked->covariance) {
      EXPECT_TRUE(std::isfinite(c));
    }
    EXPECT_GT(tracked->covariance[0], 0.0);  // a tracked tip is not exact
  }
}

TEST_F(TipTrackerChainTest, BadFramesAreReportedAndTrackingGoesOn) {
  retract();
  ASSERT_TRUE(place(kEntryHeight_m));
  ASSERT_TRUE(insertTo(2.0 * kStep_m));
  std::uint32_t w = 0, h = 0;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    w = calibration_->width;
    h = calibration_->height;
  }
  const int cols = static_cast<int>(w), rows = static_cast<int>(h);
  struct Bad {
    std::string what;
    cv::Mat image;
    std::string encoding;
  };
  const std::vector<Bad> bad = {
      {"colour frame", cv::Mat(rows, cols, CV_8UC3, cv::Scalar(90, 90, 90)), "bgr8"},
      {"wrong size", cv::Mat(rows / 2, cols, CV_8UC1, cv::Scalar(90)), "mono8"},
      {"all zeros", cv::Mat(rows, cols, CV_8UC1, cv::Scalar(0)), "mono8"},
      {"16-bit frame", cv::Mat(rows, cols, CV_16UC1, cv::Scalar(900)), "mono16"},
  };
  double stamp_s = 1000.0;
  for (const Bad& b : bad) {
    stamp_s += 1.0;
    const auto answer = answerTo(b.image, b.encoding, stamp_s);
    ASSERT_TRUE(answer) << b.what << ": no answer from the tracker";
    EXPECT_EQ(answer->source, "bad_frame") << b.what;
    EXPECT_FALSE(answer->confident) << b.what;
    EXPECT_TRUE(std::isfinite(answer->pose.x) && std::isfinite(answer->pose.y)) << b.what;
  }
  // The imager's next frames are still tracked.
  const ros::Time after = ros::Time::now();
  const auto tracked = trackedAfter(after, [](const NeedleTip& t) { return t.confident; });
  ASSERT_TRUE(tracked) << "tracking did not resume after the bad frames";
  const NeedleTip true_tip = truth();
  EXPECT_NEAR(tracked->pose.x, true_tip.pose.x, kTipTol_m);
  EXPECT_NEAR(tracked->pose.y, true_tip.pose.y, kTipTol_m);
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "tip_tracker_rostest");
  ros::AsyncSpinner spinner(1);
  spinner.start();
  return RUN_ALL_TESTS();
}
