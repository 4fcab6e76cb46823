// Sends an action goal and waits for its result, bounded and supervised (shared by the planar
// and the 3-D steerable procedures).
#pragma once

#include <actionlib/client/simple_action_client.h>
#include <ros/ros.h>

#include <functional>
#include <optional>
#include <string>

namespace needle_guidance {

/// Sends `goal` and waits at most timeout_s (wall) for its result. `death` is asked every 0.1 s:
/// a cause cancels the goal at once (a dead server never answers a cancel either: nothing waits
/// for one). `message` is the result's message, the cause, or "no result within the timeout".
/// True if the goal succeeded.
template <class Client, class Goal>
bool runGoal(Client& client, const Goal& goal, double timeout_s,
             const std::function<std::optional<std::string>()>& death, std::string& message) {
  client.sendGoal(goal);
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(timeout_s);
  while (!client.waitForResult(ros::Duration(0.1))) {
    const std::optional<std::string> dead = death ? death() : std::nullopt;
    if (dead || ros::WallTime::now() > end || !ros::ok()) {
      client.cancelGoal();
      message = dead ? *dead : "no result within the timeout";
      return false;
    }
  }
  const auto state = client.getState();
  message = client.getResult() ? client.getResult()->message : state.toString();
  return state == actionlib::SimpleClientGoalState::SUCCEEDED;
}

}  // namespace needle_guidance
