// Simulated imaging device node: renders frames of the scene plane from
// the robot's true needle shape (imaging::FrameRenderer) at the device's frame rate, drops the
// frames the device loses, and publishes the images with their pixel <-> scene calibration.
// ~view along_z / along_y: one of the two orthogonal fluoroscopy views of the 3-D
// scene ~scene_3d (imaging::biplaneViewSetup: the tissue's projected bounds plus a margin); the
// robot's 3-D shape is projected on the view's plane (view along z sees x, y; along y, x, z).
#pragma once

#include <ros/ros.h>

#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>

#include <Eigen/Core>
#include <vector>

#include "needle_guidance/NeedleShape.h"
#include "needle_guidance/imaging/frame_renderer.h"

namespace needle_guidance {

/// Reads its parameters once (throws std::runtime_error naming a bad one).
///
/// Subscribes `needle_shape` (NeedleShape, remap to the robot's ~needle_shape); publishes
/// `~image` (sensor_msgs/Image mono8, stamped with the time of the shape it shows) and latched
/// `~calibration` (ImageCalibration).
class ImagerRos {
public:
  ImagerRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);
  ~ImagerRos();

private:
  void onShape(const NeedleShapeConstPtr& msg);
  void onFrameTimer(const ros::TimerEvent& event);

  std::unique_ptr<imaging::FrameRenderer> renderer_;
  /// ~view along_z / along_y: the view's rows projecting the 3-D shape on its plane; none for
  /// plane (the shape's x, y).
  std::optional<Eigen::Matrix<double, 2, 3>> rows_;
  double frame_rate_hz_ = 0.0;
  std::mutex mutex_;
  std::vector<imaging::Point2> needle_points_;
  ros::Time shape_stamp_;
  bool have_shape_ = false;
  std::uint64_t next_index_ = 0;
  std::uint64_t published_ = 0;
  std::uint64_t dropped_ = 0;
  ros::Subscriber shape_sub_;
  ros::Publisher image_pub_;
  ros::Publisher calibration_pub_;
  ros::Timer frame_timer_;
};

}  // namespace needle_guidance
