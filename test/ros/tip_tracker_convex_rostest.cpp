// rostest node for the imager's convex probe and tip_tracker (tip_tracker_convex.test): the test
// publishes the needle's shape (a straight needle entering at the probe face's left end, 40
// degrees below the rows, advancing kAdvance_px a frame), the imager renders convex frames of
// it, and tip_tracker (no robot: the axis model) must follow the tip; frames without a needle
// are never answered with a confident tip.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include <cmath>
#include <iostream>
#include <mutex>
#include <optional>
#include <vector>

#include "needle_guidance/ImageCalibration.h"
#include "needle_guidance/NeedleShape.h"
#include "needle_guidance/NeedleTip.h"
#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/tissue/image_warp.h"
#include "stamped_answer.h"

namespace {

namespace ng = needle_guidance;
namespace im = ng::imaging;

constexpr double kRadius_m = 0.05;       // the imager's default convex_radius_m
constexpr double kHalfAngle_rad = 0.55;  // the imager's default convex_half_angle_deg
constexpr double kEntry = -0.8;          // where on the face: -1 its left end, +1 its right end
constexpr double kAngle_rad = 40.0 * M_PI / 180.0;  // below the rows, towards the fan's middle
constexpr double kStart_px = 60.0;                  // inserted length in the first frame
constexpr double kAdvance_px = 8.0;                 // per frame
constexpr int kEmptyFrames = 4, kFrames = 14;
constexpr double kTipTol_px = 15.0;  // the p90 tip error target of the tracking benchmark

class ConvexChain : public ::testing::Test {
protected:
  void SetUp() override {
    shape_pub_ = nh_.advertise<ng::NeedleShape>("needle_shape", 10);
    tip_sub_ = nh_.subscribe("tip_tracker/tip", 100, &ConvexChain::onTip, this);
    calibration_sub_ = nh_.subscribe("imager/calibration", 1, &ConvexChain::onCalibration, this);
    const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(30.0);
    while (ros::WallTime::now() < end && (shape_pub_.getNumSubscribers() == 0 ||
                                          tip_sub_.getNumPublishers() == 0 || !calibration())) {
      ros::WallDuration(0.05).sleep();
    }
    ASSERT_GT(shape_pub_.getNumSubscribers(), 0U);
    ASSERT_TRUE(calibration()) << "no calibration from the imager";
  }
  void onTip(const ng::NeedleTipConstPtr& m) {
    std::lock_guard<std::mutex> lock(mutex_);
    tips_.push_back(*m);
  }
  void onCalibration(const ng::ImageCalibrationConstPtr& m) {
    std::lock_guard<std::mutex> lock(mutex_);
    ng::tissue::ImageGeometry g;
    g.pixel_size_m = m->pixel_size_m;
    g.cols = static_cast<int>(m->width);
    g.rows = static_cast<int>(m->height);
    g.origin_m = ng::geometry::Point2(m->origin_x_m, m->origin_y_m);
    geometry_ = g;
  }
  std::optional<ng::tissue::ImageGeometry> calibration() {
    std::lock_guard<std::mutex> lock(mutex_);
    return geometry_;
  }
  /// The first tip answering a frame of the shape stamped `stamp`.
  std::optional<ng::NeedleTip> answerTo(const ros::Time& stamp) {
    return needle_guidance::rostest_support::waitForStamp(mutex_, tips_, stamp, 10.0);
  }
  /// Publishes the needle (pixels, entry -> tip; empty: none) in scene coordinates.
  ros::Time send(const std::vector<cv::Point2d>& needle_px, int k) {
    const ng::tissue::ImageGeometry g = *calibration();
    ng::NeedleShape msg;
    msg.header.stamp = ros::Time(100 + k, 0);
    msg.header.frame_id = "scene";
    for (const cv::Point2d& p : needle_px) {
      const ng::geometry::Point2 s = g.toScene(p);
      geometry_msgs::Point q;
      q.x = s.x();
      q.y = s.y();
      msg.points.push_back(q);
    }
    shape_pub_.publish(msg);
    return msg.header.stamp;
  }

  ros::NodeHandle nh_;
  ros::Publisher shape_pub_;
  ros::Subscriber tip_sub_, calibration_sub_;
  std::mutex mutex_;
  std::vector<ng::NeedleTip> tips_;
  std::optional<ng::tissue::ImageGeometry> geometry_;
};

TEST_F(ConvexChain, FollowsASteepNeedleFromTheProbeEndAndIsNeverConfidentWithoutOne) {
  const ng::tissue::ImageGeometry g = *calibration();
  ASSERT_EQ(g.cols, 720);
  const double radius_px = kRadius_m / g.pixel_size_m;
  const cv::Point2d apex(0.5 * (g.cols - 1), im::FrameRenderer::kConvexFaceTop_px -
                                                 radius_px * std::cos(kHalfAngle_rad));
  const double th = kEntry * kHalfAngle_rad;
  const cv::Point2d entry = apex + radius_px * cv::Point2d(std::sin(th), std::cos(th));
  const cv::Point2d u(std::cos(kAngle_rad), std::sin(kAngle_rad));
  for (int k = 0; k < kEmptyFrames; ++k) {  // the fan without a needle
    const auto tip = answerTo(send({}, k));
    ASSERT_TRUE(tip) << "no answer to empty frame " << k;
    EXPECT_FALSE(tip->confident) << "empty frame " << k << ": source " << tip->source;
  }
  int found = 0, close = 0, confident = 0;
  for (int k = 0; k < kFrames; ++k) {
    const double length = kStart_px + kAdvance_px * k;
    std::vector<cv::Point2d> needle;
    for (double t = -60.0; t <= length; t += 2.0)
      needle.push_back(entry + t * u);
    const auto tip = answerTo(send(needle, kEmptyFrames + k));
    ASSERT_TRUE(tip) << "no answer to frame " << k;
    if (tip->source == "not_found")
      continue;
    ++found;
    const cv::Point2d est = g.toPixel(ng::geometry::Point2(tip->pose.x, tip->pose.y));
    const double error_px = cv::norm(est - (entry + length * u));
    close += error_px < kTipTol_px ? 1 : 0;
    if (tip->confident) {
      ++confident;
      EXPECT_LT(error_px, kTipTol_px) << "frame " << k << ": a confident tip off [px]";
    }
  }
  std::cout << "[tip_tracker_convex] " << found << " of " << kFrames << " frames with a tip, "
            << close << " within " << kTipTol_px << " px, " << confident << " confident\n";
  // The tracker's first frames may miss the short needle under the probe face (its ring-down);
  // from then on it follows the tip.
  EXPECT_GE(found, kFrames - 4) << "frames with a tip";
  EXPECT_GE(close, kFrames - 4) << "tips within " << kTipTol_px << " px";
  EXPECT_GE(confident, 1) << "confidence is earned by a needle moving along its axis";
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "tip_tracker_convex_rostest");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  const int result = RUN_ALL_TESTS();
  ros::shutdown();
  return result;
}
