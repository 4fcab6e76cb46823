// HDR dwell-time planning and delivery schedules (see DwellSchedulerRos).
#include <ros/ros.h>

#include "needle_guidance/ros/dwell_scheduler_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "dwell_scheduler");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    needle_guidance::DwellSchedulerRos scheduler(nh, private_nh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("dwell_scheduler: " << e.what());
    return 1;
  }
  return 0;
}
