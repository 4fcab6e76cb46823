// Runs N closed-loop steerable-needle trials and exits (0 = success).
#include <ros/ros.h>

#include "needle_guidance/ros/steerable_procedure_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "steerable_procedure");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  try {
    needle_guidance::SteerableProcedureRos procedure(nh, private_nh);
    const bool ok = procedure.run();
    ros::shutdown();
    return ok ? 0 : 2;
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("steerable_procedure: " << e.what());
    ros::shutdown();
    return 1;
  }
}
