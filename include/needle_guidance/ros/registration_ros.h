// Deformable registration node (dissertation ch. 3): a thin
// wrapper of registration::registerSlices with a `~register` service and rviz markers of the
// probe-in prostate, the deformed probe-out prostate and the warped MRSI grid.
#pragma once

#include <ros/ros.h>

#include "needle_guidance/Register.h"
#include "needle_guidance/registration/deformable_registration.h"

namespace needle_guidance {

/// Reads its parameters once (throws std::runtime_error naming a bad one). Serves `~register`
/// (needle_guidance/Register); publishes latched `~markers` (visualization_msgs/MarkerArray,
/// frame scene) after every successful registration.
class RegistrationRos {
public:
  RegistrationRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);

private:
  bool onRegister(Register::Request& req, Register::Response& res);

  registration::RegistrationOptions defaults_;
  ros::ServiceServer register_srv_;
  ros::Publisher markers_pub_;
};

}  // namespace needle_guidance
