// Procedure runner for deformable registration (see RegistrationProcedureRos).
#include <ros/ros.h>

#include "needle_guidance/ros/registration_procedure_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "registration_procedure");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    needle_guidance::RegistrationProcedureRos procedure(nh, private_nh);
    return procedure.run() ? 0 : 1;
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("registration_procedure: " << e.what());
    return 1;
  }
}
