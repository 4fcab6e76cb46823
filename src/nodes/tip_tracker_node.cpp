// Needle-tip tracker: tip position and heading with covariance from each imager frame, filtered
// with the robot's own motion (see TipTrackerRos and imaging::TipTracker).
#include <ros/ros.h>

#include "needle_guidance/ros/tip_tracker_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "tip_tracker");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    needle_guidance::TipTrackerRos tracker(nh, private_nh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("tip_tracker: " << e.what());
    return 1;
  }
  return 0;
}
