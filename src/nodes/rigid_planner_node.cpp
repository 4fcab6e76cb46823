// Rigid-needle offset planner service (see RigidPlannerRos).
#include <ros/ros.h>

#include "needle_guidance/ros/rigid_planner_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "rigid_planner");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    needle_guidance::RigidPlannerRos planner(nh, private_nh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("rigid_planner: " << e.what());
    return 1;
  }
  return 0;
}
