// 3-D closed-loop steerable-needle trials against steering_planner_3d with a simulated noisy
// needle; writes the report and exits non-zero on a fault (see SteerableProcedure3dRos).
#include <ros/ros.h>

#include "needle_guidance/ros/steerable_procedure_3d_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "steerable_procedure_3d");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  ros::AsyncSpinner spinner(1);
  spinner.start();
  try {
    needle_guidance::SteerableProcedure3dRos procedure(nh, private_nh);
    const bool ok = procedure.run();
    return ok ? 0 : 1;
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("steerable_procedure_3d: " << e.what());
    return 1;
  }
}
