// Runs the robot insertion procedure once over all targets of a scene and exits (0 = success).
#include <ros/ros.h>

#include "needle_guidance/ros/insertion_procedure_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "insertion_procedure");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  ros::AsyncSpinner spinner(1);
  spinner.start();
  try {
    needle_guidance::InsertionProcedureRos procedure(nh, private_nh);
    const bool ok = procedure.run();
    ros::shutdown();
    return ok ? 0 : 2;
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("insertion_procedure: " << e.what());
    ros::shutdown();
    return 1;
  }
}
