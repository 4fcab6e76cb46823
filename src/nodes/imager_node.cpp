// Simulated imaging device: fluoroscopy- or ultrasound-like frames of the scene plane rendered
// from the robot's true needle shape, with the pixel <-> scene calibration (see ImagerRos).
#include <ros/ros.h>

#include "needle_guidance/ros/imager_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "imager");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    needle_guidance::ImagerRos imager(nh, private_nh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("imager: " << e.what());
    return 1;
  }
  return 0;
}
