// Deformable registration of probe-out / probe-in slices (dissertation ch. 3): `~register`
// service and rviz markers of the warped MRSI grid (see RegistrationRos).
#include <ros/ros.h>

#include "needle_guidance/ros/registration_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "registration");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    needle_guidance::RegistrationRos node(nh, private_nh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("registration: " << e.what());
    return 1;
  }
  return 0;
}
