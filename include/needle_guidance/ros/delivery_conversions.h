// Conversions between the HDR delivery core types and ROS messages.
#pragma once

#include <geometry_msgs/Point.h>

#include "needle_guidance/DwellSchedule.h"
#include "needle_guidance/delivery/schedule.h"

namespace needle_guidance::ros_conversions {

geometry_msgs::Point toPointMessage(const delivery::Point3& p);
delivery::Point3 fromPointMessage(const geometry_msgs::Point& p);

/// A schedule as a message; `frame_id` names the patient frame of positions and paths.
DwellSchedule toMessage(const delivery::Schedule& s, const std::string& frame_id);
/// The schedule of a message. Array-length mismatches are not fixed here: validateSchedule()
/// reports them (the lengths are copied as they are).
delivery::Schedule fromMessage(const DwellSchedule& msg);

}  // namespace needle_guidance::ros_conversions
