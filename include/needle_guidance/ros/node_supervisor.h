#pragma once

#include <ros/callback_queue.h>
#include <ros/ros.h>

#include <memory>
#include <mutex>

#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/procedures/fault.h"

namespace needle_guidance {

/// Watches the nodes a procedure depends on. A node counts as alive while the master knows it
/// and its own XML-RPC server answers `getPid` (what `rosnode ping` asks) within the ping
/// timeout; a killed node stays registered with the master, so the ping is what catches it (its
/// port refuses at once). A timer checks every node each `period_s` (0.5 s by default), so a
/// killed node is seen within about 0.5 s and a stopped (hung) one, which accepts the connection
/// but never answers, within period + ping timeout (1.5 s by default) <= 2 s. Once a node is found
/// dead it stays reported dead (the first death is the cause a report names), even if a respawned
/// node of the same name answers later; `clear()` forgets it when the procedure has dealt with the
/// restart.
class NodeSupervisor {
public:
  struct Death {
    std::string node;    ///< full name, e.g. /afterloader
    ros::WallTime when;  ///< when the supervisor saw it dead
    std::string reason;  ///< e.g. "not registered with the master" or "no answer to getPid"
    std::string toString() const;
  };

  /// `nodes`: full node names ("/steering_policy") or relative ones, resolved in `nh`'s
  /// namespace. Checking starts at once.
  NodeSupervisor(ros::NodeHandle nh, std::vector<std::string> nodes, double period_s = 0.5,
                 double ping_timeout_s = 1.5);
  ~NodeSupervisor();

  /// Blocks until every node answers or `timeout_s` passes; the names that did not answer.
  std::vector<std::string> waitForAll(double timeout_s);
  /// The first node found dead, if any (checked by the timer; `checkNow` checks at once).
  std::optional<Death> death() const;
  /// The first death, confirmed: on a loaded machine one master lookup or getPid can fail for
  /// a live node (seen: "not registered" at load 8 on 2 cores), so a death counts once `pings`
  /// more pings, `pause_s` apart, fail too; otherwise it is forgotten as a false alarm. As a
  /// procedure's Fault timed from `start`; kept once confirmed. Detection stays within
  /// period + pings * pause (about 1 s).
  std::optional<procedures::Fault> confirmedFault(const ros::WallTime& start, double pause_s = 0.2,
                                                  int pings = 2);
  void checkNow();
  /// Forgets the death (and a confirmed fault).
  void clear();
  const std::vector<std::string>& nodes() const { return nodes_; }

  /// Whether `node` is registered and answers getPid within `timeout_s` ("" if alive, else why).
  static std::string ping(const std::string& node, double timeout_s);

private:
  std::vector<std::string> nodes_;
  double ping_timeout_s_;
  mutable std::mutex mutex_;
  std::optional<Death> death_;
  std::optional<procedures::Fault> confirmed_;
  // The pings run on a queue and thread of their own, so that a slow ping never delays the
  // procedure's own callbacks (action feedback, tips).
  ros::CallbackQueue queue_;
  ros::WallTimer timer_;
  std::unique_ptr<ros::AsyncSpinner> spinner_;
};

}  // namespace needle_guidance
