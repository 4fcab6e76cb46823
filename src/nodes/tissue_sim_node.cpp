// FEM tissue simulation following the insertion robot (see TissueSimRos).
#include <ros/ros.h>

#include "needle_guidance/ros/tissue_sim_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "tissue_sim");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    needle_guidance::TissueSimRos sim(nh, private_nh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("tissue_sim: " << e.what());
    return 1;
  }
  return 0;
}
