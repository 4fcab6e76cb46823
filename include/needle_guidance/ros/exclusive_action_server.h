#pragma once

#include <actionlib/server/action_server.h>

#include <functional>
#include <optional>
#include <string>
#include <utility>

namespace needle_guidance {

/// An action server that holds at most one goal and never lets a new goal take over a running
/// one. actionlib's SimpleActionServer preempts the running goal whenever another client sends a
/// goal; for a device that moves a needle in tissue that is unsafe. Here a goal that arrives
/// while `busy()` says a motion runs (on this server or on any other of the device) is rejected
/// with the reason, and the running goal goes on; the running goal stops only on an explicit
/// cancel of that goal. Result types must have `success` and `message` fields.
template <class ActionSpec>
class ExclusiveActionServer {
public:
  ACTION_DEFINITION(ActionSpec)
  using GoalHandle = actionlib::ServerGoalHandle<ActionSpec>;
  /// "" when a new goal may start, else why not (e.g. "a motion is running: ...").
  using BusyCheck = std::function<std::string()>;
  using GoalCallback = std::function<void(const Goal&)>;
  using CancelCallback = std::function<void()>;

  ExclusiveActionServer(ros::NodeHandle nh, const std::string& name, BusyCheck busy,
                        GoalCallback on_goal, CancelCallback on_cancel)
      : name_(name),
        busy_(std::move(busy)),
        on_goal_(std::move(on_goal)),
        on_cancel_(std::move(on_cancel)),
        server_(
            nh, name, [this](GoalHandle g) { onGoal(g); }, [this](GoalHandle g) { onCancel(g); },
            false) {}

  void start() { server_.start(); }
  bool isActive() const { return active_.has_value(); }

  void setSucceeded(const Result& result, const std::string& text) {
    finish([&](GoalHandle& g) { g.setSucceeded(result, text); });
  }
  void setAborted(const Result& result, const std::string& text) {
    finish([&](GoalHandle& g) { g.setAborted(result, text); });
  }
  /// The running goal was cancelled by its client (actionlib state PREEMPTED).
  void setPreempted(const Result& result, const std::string& text) {
    finish([&](GoalHandle& g) { g.setCanceled(result, text); });
  }
  void publishFeedback(const Feedback& feedback) {
    if (active_) {
      active_->publishFeedback(feedback);
    }
  }

private:
  void onGoal(GoalHandle goal) {
    const std::string why = busy_();
    if (!why.empty()) {
      Result result;
      result.success = false;
      result.message = name_ + " goal refused: " + why + "; cancel the running goal first";
      ROS_WARN_STREAM_NAMED("exclusive_action_server", result.message);
      goal.setRejected(result, result.message);
      return;
    }
    goal.setAccepted();
    active_ = goal;
    on_goal_(*goal.getGoal());
  }

  void onCancel(GoalHandle goal) {
    if (active_ && *active_ == goal) {
      on_cancel_();  // the owner stops the motion and calls setPreempted
    }
  }

  template <class F>
  void finish(F&& f) {
    if (!active_) {
      return;
    }
    GoalHandle goal = *active_;
    active_.reset();
    f(goal);
  }

  std::string name_;
  BusyCheck busy_;
  GoalCallback on_goal_;
  CancelCallback on_cancel_;
  std::optional<GoalHandle> active_;
  actionlib::ActionServer<ActionSpec> server_;
};

}  // namespace needle_guidance
