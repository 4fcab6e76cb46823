// Publishes a scene's regions, obstacles, targets and boundary conditions as latched rviz
// markers on `scene_markers` (frame scene).
#include <ros/ros.h>
#include <visualization_msgs/MarkerArray.h>

#include "needle_guidance/ros/conversions.h"
#include "needle_guidance/ros/params.h"
#include "needle_guidance/scene/scene.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "scene_publisher");
  ros::NodeHandle nh;
  ros::NodeHandle private_nh("~");
  try {
    ROS_INFO("scene_publisher parameters:");
    const std::string spec =
        needle_guidance::ros_params::text(private_nh, "scene", "prostate_sagittal");
    const needle_guidance::scene::Scene scene = needle_guidance::scene::loadSceneSpec(spec);
    ros::Publisher pub = nh.advertise<visualization_msgs::MarkerArray>("scene_markers", 1, true);
    pub.publish(needle_guidance::ros_conversions::sceneToMarkers(scene, "scene"));
    ROS_INFO_STREAM("scene_publisher: published scene '" << scene.name << "' ("
                                                         << scene.regions.size() << " regions, "
                                                         << scene.targets.size() << " targets)");
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("scene_publisher: " << e.what());
    return 1;
  }
  return 0;
}
