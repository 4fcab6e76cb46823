// Needle-tip tracker node: a thin wrapper around
// imaging::TipTracker. Frames from the imager, the imager's calibration, and the robot's
// proprioception (needle guide, inserted length, bevel) go in; the tip pose with its covariance,
// source and confidence goes out, with a debug image of the detection.
#pragma once

#include <ros/ros.h>
#include <sensor_msgs/Image.h>

#include <deque>
#include <memory>
#include <string>

#include "needle_guidance/ImageCalibration.h"
#include "needle_guidance/NeedleDrive.h"
#include "needle_guidance/imaging/needle_acquisition.h"
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/scene/scene.h"

namespace needle_guidance {

/// Reads its parameters once (throws std::runtime_error naming a bad one).
///
/// Subscribes `image` (sensor_msgs/Image mono8), `calibration` (ImageCalibration, latched) and
/// `drive` (NeedleDrive); publishes `~tip` (NeedleTip, one per usable or unusable frame once the
/// tracker has an entry pose) and `~debug_image` (bgr8, only while someone listens).
class TipTrackerRos {
public:
  TipTrackerRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);

private:
  void onCalibration(const ImageCalibrationConstPtr& msg);
  void onDrive(const NeedleDriveConstPtr& msg);
  void onImage(const sensor_msgs::ImageConstPtr& msg);
  /// Feeds the tracker the robot's drive messages stamped at or before `stamp`.
  void applyDrives(const ros::Time& stamp);
  /// ~motion_model axis: a recorded or freehand sequence, no robot. SequenceTracker (needle
  /// acquisition without a prior, motion along the needle's own axis, earned confidence).
  void onImageWithoutRobot(const sensor_msgs::ImageConstPtr& msg);

  scene::Scene scene_;
  imaging::TrackerConfig settings_;  ///< parameters that do not come from the calibration
  std::unique_ptr<imaging::TipTracker> tracker_;
  std::deque<NeedleDrive> drives_;
  std::uint32_t entry_id_ = 0;
  bool have_entry_ = false;
  NeedleDrive last_drive_;
  std::uint64_t frames_ = 0;
  void resetSequence();
  /// ~motion_model: auto (default) chooses per frame by whether the robot's drive is there.
  imaging::MotionModel motion_model_ = imaging::MotionModel::kAuto;
  imaging::AcquisitionOptions sequence_options_;  ///< axis model: ~entry
  double sequence_radius_m_ = 0.0;                ///< axis model: ~radius_m (0 = straight)
  std::unique_ptr<imaging::SequenceTracker> sequence_;
  imaging::ImageGeometry geometry_;  ///< calibration (axis model)
  ros::Subscriber image_sub_;
  ros::Subscriber calibration_sub_;
  ros::Subscriber drive_sub_;
  ros::Publisher tip_pub_;
  ros::Publisher debug_pub_;
};

}  // namespace needle_guidance
