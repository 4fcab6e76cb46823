// The latest message of a topic with a bounded, abortable wait for a newer one (shared by the
// planar and the 3-D steerable procedures).
#pragma once

#include <ros/time.h>

#include <chrono>
#include <condition_variable>
#include <functional>
#include <mutex>
#include <vector>

namespace needle_guidance {

/// The latest message of a topic, with a wait for one stamped at or after a time.
template <class Msg>
class Latest {
public:
  void set(const Msg& msg) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      msg_ = msg;
      has_ = true;
      if (recording_) {
        record_.push_back(msg);
      }
    }
    changed_.notify_all();
  }
  /// Waits (wall time) for a message with header.stamp >= stamp; false on timeout, or at once
  /// (within 0.1 s) when the abort check says a node it depends on died.
  bool waitFor(const ros::Time& stamp, double timeout_s, Msg& out) {
    std::unique_lock<std::mutex> lock(mutex_);
    const auto deadline =
        std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    const auto ready = [&] { return has_ && msg_.header.stamp >= stamp; };
    bool ok = ready();
    while (!ok && std::chrono::steady_clock::now() < deadline && !(abort_ && abort_())) {
      ok = changed_.wait_for(lock, std::chrono::milliseconds(100), ready);
    }
    if (ok) {
      out = msg_;
    }
    return ok;
  }
  void setAbort(std::function<bool()> abort) {
    std::lock_guard<std::mutex> lock(mutex_);
    abort_ = std::move(abort);
  }
  void startRecording() {
    std::lock_guard<std::mutex> lock(mutex_);
    record_.clear();
    recording_ = true;
  }
  std::vector<Msg> stopRecording() {
    std::lock_guard<std::mutex> lock(mutex_);
    recording_ = false;
    return std::move(record_);
  }

private:
  std::mutex mutex_;
  std::condition_variable changed_;
  Msg msg_;
  bool has_ = false;
  bool recording_ = false;
  std::vector<Msg> record_;
  std::function<bool()> abort_;
};

}  // namespace needle_guidance
