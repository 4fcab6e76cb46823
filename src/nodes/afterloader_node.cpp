// Simulated HDR remote afterloader (see AfterloaderRos).
#include <ros/ros.h>

#include "needle_guidance/ros/afterloader_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "afterloader");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    needle_guidance::AfterloaderRos afterloader(nh, private_nh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("afterloader: " << e.what());
    return 1;
  }
  return 0;
}
