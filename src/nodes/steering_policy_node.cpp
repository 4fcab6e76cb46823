// Steerable-needle policy: solves or loads the MDP table, answers tip poses with the control and
// P_s, serves the best start state (see SteeringPolicyRos).
#include <ros/ros.h>

#include "needle_guidance/ros/steering_policy_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "steering_policy");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    needle_guidance::SteeringPolicyRos policy(nh, private_nh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("steering_policy: " << e.what());
    return 1;
  }
  return 0;
}
