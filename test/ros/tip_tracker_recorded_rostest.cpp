// rostest node for tip_tracker without a robot (tip_tracker_recorded.test): frames of
// a recorded-like B-mode sequence (synthetic: speckle, a brighter specular interface, a needle
// with shadow and reverberations advancing along its axis) arrive on a sensor_msgs/Image topic
// as from `rosbag play`, with no NeedleDrive and the calibration as parameters. The node must
// acquire the needle without a prior, follow it, and earn confidence; a frame without a needle
// is never answered with a confident tip.
#include <cv_bridge/cv_bridge.h>
#include <gtest/gtest.h>
#include <ros/ros.h>

#include <cmath>
#include <mutex>
#include <optional>
#include <vector>

#include "needle_guidance/NeedleTip.h"
#include "needle_guidance/imaging/synthetic_bmode.h"
#include "stamped_answer.h"

namespace {

using needle_guidance::NeedleTip;
namespace im = needle_guidance::imaging;

constexpr double kPixel_m = 1e-4;     // ~pixel_size_m in the .test file
constexpr double kTipTol_px = 8.0;    // median tip error target on real frames [px]
constexpr double kAdvance_px = 10.0;  // tip motion per frame along the axis [px]
constexpr int kFrames = 14;
const cv::Size kSize(720, 440);

class RecordedSequence : public ::testing::Test {
protected:
  void SetUp() override {
    pub_ = nh_.advertise<sensor_msgs::Image>("frames", 10);
    sub_ = nh_.subscribe("tip_tracker/tip", 100, &RecordedSequence::onTip, this);
    const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(20.0);
    while (ros::WallTime::now() < end &&
           (pub_.getNumSubscribers() == 0 || sub_.getNumPublishers() == 0)) {
      ros::WallDuration(0.05).sleep();
    }
    ASSERT_GT(pub_.getNumSubscribers(), 0U);
  }
  void onTip(const needle_guidance::NeedleTipConstPtr& m) {
    std::lock_guard<std::mutex> lock(mutex_);
    tips_.push_back(*m);
  }
  std::optional<NeedleTip> answerTo(const ros::Time& stamp) {
    return needle_guidance::rostest_support::waitForStamp(mutex_, tips_, stamp, 5.0);
  }
  ros::Time send(const cv::Mat& frame, int k) {
    std_msgs::Header h;
    h.stamp = ros::Time(100 + k, 0);
    pub_.publish(cv_bridge::CvImage(h, "mono8", frame).toImageMsg());
    return h.stamp;
  }

  ros::NodeHandle nh_;
  ros::Publisher pub_;
  ros::Subscriber sub_;
  std::mutex mutex_;
  std::vector<NeedleTip> tips_;
};

TEST_F(RecordedSequence, AcquiresFollowsAndEarnsConfidenceWithoutARobot) {
  const im::BModeInterface iface{300.0, 280.0, 230.0, 0.4};
  const cv::Point2d tail(60.0, 200.0), dir(std::cos(0.12), std::sin(0.12));
  int confident = 0;
  for (int k = 0; k < kFrames; ++k) {
    const double length = 200.0 + kAdvance_px * k;
    const im::BModeNeedle needle{tail, tail + length * dir, 170.0, 0.0};
    const ros::Time stamp = send(im::syntheticBMode(kSize, 7, iface, needle), k);
    const auto tip = answerTo(stamp);
    ASSERT_TRUE(tip) << "no answer to frame " << k;
    if (!tip->confident)
      continue;
    ++confident;
    // Pixel (col, row) -> scene with origin (0, 0) at the top-left corner, y up.
    const double col = tip->pose.x / kPixel_m - 0.5, row = -tip->pose.y / kPixel_m - 0.5;
    EXPECT_LT(std::hypot(col - needle.tip.x, row - needle.tip.y), kTipTol_px)
        << "frame " << k << " confident tip off [px]";
    EXPECT_LT(std::abs(tip->pose.theta + 0.12), 3.0 * M_PI / 180.0) << "heading, y up [rad]";
  }
  EXPECT_GE(confident, kFrames / 2) << "confidence is earned after a few agreeing frames";

  // A frame with the interface and no needle: never a confident tip.
  const ros::Time empty = send(im::syntheticBMode(kSize, 8, iface, std::nullopt), kFrames);
  const auto none = answerTo(empty);
  ASSERT_TRUE(none);
  EXPECT_FALSE(none->confident) << "source " << none->source;
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "tip_tracker_recorded_rostest");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  const int result = RUN_ALL_TESTS();
  ros::shutdown();
  return result;
}
