// 3-D steerable-needle planner: replans from every tip pose, publishes the control and the plan,
// serves ~plan from the entry (see SteeringPlanner3dRos).
#include <ros/ros.h>

#include "needle_guidance/ros/steering_planner_3d_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "steering_planner_3d");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    needle_guidance::SteeringPlanner3dRos planner(nh, private_nh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("steering_planner_3d: " << e.what());
    return 1;
  }
  return 0;
}
