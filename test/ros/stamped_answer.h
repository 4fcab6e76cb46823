// Waiting, in a rostest node, for the message a node published in answer to a stamped input.
#pragma once

#include <ros/ros.h>

#include <mutex>
#include <optional>
#include <vector>

namespace needle_guidance::rostest_support {

/// The first message of `received` (appended by a subscriber callback under `mutex`) whose
/// header is stamped `stamp`, waiting up to `timeout_s` of wall time; nullopt when none arrived.
template <class Msg>
std::optional<Msg> waitForStamp(std::mutex& mutex, const std::vector<Msg>& received,
                                const ros::Time& stamp, double timeout_s) {
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(timeout_s);
  while (ros::WallTime::now() < end) {
    {
      std::lock_guard<std::mutex> lock(mutex);
      for (const Msg& m : received) {
        if (m.header.stamp == stamp) {
          return m;
        }
      }
    }
    ros::WallDuration(0.01).sleep();
  }
  return std::nullopt;
}

}  // namespace needle_guidance::rostest_support
