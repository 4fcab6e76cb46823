// Runs the HDR delivery procedure once (plan, deliver, evaluate, report) and exits (0 = success).
#include <ros/ros.h>

#include "needle_guidance/ros/hdr_procedure_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "hdr_procedure");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  ros::AsyncSpinner spinner(1);
  spinner.start();
  try {
    needle_guidance::HdrProcedureRos procedure(nh, private_nh);
    const bool ok = procedure.run();
    ros::shutdown();
    return ok ? 0 : 2;
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("hdr_procedure: " << e.what());
    ros::shutdown();
    return 1;
  }
}
