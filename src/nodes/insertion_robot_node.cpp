// Simulated needle insertion stage (see InsertionRobotRos).
#include <ros/ros.h>

#include "needle_guidance/ros/insertion_robot_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "insertion_robot");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    needle_guidance::InsertionRobotRos robot(nh, private_nh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("insertion_robot: " << e.what());
    return 1;
  }
  return 0;
}
