#include "needle_guidance/ros/delivery_conversions.h"

namespace needle_guidance::ros_conversions {

geometry_msgs::Point toPointMessage(const delivery::Point3& p) {
  geometry_msgs::Point m;
  m.x = p.x();
  m.y = p.y();
  m.z = p.z();
  return m;
}

delivery::Point3 fromPointMessage(const geometry_msgs::Point& p) {
  return delivery::Point3(p.x, p.y, p.z);
}

DwellSchedule toMessage(const delivery::Schedule& s, const std::string& frame_id) {
  DwellSchedule m;
  m.plan_id = s.plan_id;
  m.frame_id = frame_id;
  m.source = s.source;
  m.plan_air_kerma_strength_U = s.plan_air_kerma_strength_U;
  m.current_air_kerma_strength_U = s.current_air_kerma_strength_U;
  m.decay_days = s.decay_days;
  for (const auto& c : s.channels) {
    DwellChannel ch;
    ch.channel = c.channel;
    ch.catheter = c.catheter;
    ch.length_m = c.length_m;
    ch.transfer_length_m = c.transfer_length_m;
    ch.dwell_index = c.dwell_index;
    ch.distance_m = c.distance_m;
    ch.time_s = c.time_s;
    for (const auto& p : c.position_m)
      ch.position.push_back(toPointMessage(p));
    for (const auto& p : c.path_m)
      ch.path.push_back(toPointMessage(p));
    m.channels.push_back(ch);
  }
  return m;
}

delivery::Schedule fromMessage(const DwellSchedule& m) {
  delivery::Schedule s;
  s.plan_id = m.plan_id;
  s.source = m.source;
  s.plan_air_kerma_strength_U = m.plan_air_kerma_strength_U;
  s.current_air_kerma_strength_U = m.current_air_kerma_strength_U;
  s.decay_days = m.decay_days;
  for (const auto& ch : m.channels) {
    delivery::ChannelSchedule c;
    c.channel = ch.channel;
    c.catheter = ch.catheter;
    c.length_m = ch.length_m;
    c.transfer_length_m = ch.transfer_length_m;
    c.dwell_index = ch.dwell_index;
    c.distance_m = ch.distance_m;
    c.time_s = ch.time_s;
    for (const auto& p : ch.position)
      c.position_m.push_back(fromPointMessage(p));
    for (const auto& p : ch.path)
      c.path_m.push_back(fromPointMessage(p));
    s.channels.push_back(c);
  }
  return s;
}

}  // namespace needle_guidance::ros_conversions
