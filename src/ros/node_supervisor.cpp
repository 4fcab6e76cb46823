#include "needle_guidance/ros/node_supervisor.h"

#include <ros/master.h>
#include <ros/network.h>
#include <xmlrpcpp/XmlRpcClient.h>
#include <xmlrpcpp/XmlRpcValue.h>

#include <chrono>
#include <future>
#include <memory>
#include <thread>

namespace needle_guidance {

std::string NodeSupervisor::Death::toString() const {
  return "node " + node + " died (" + reason + ")";
}

NodeSupervisor::NodeSupervisor(ros::NodeHandle nh, std::vector<std::string> nodes, double period_s,
                               double ping_timeout_s)
    : ping_timeout_s_(ping_timeout_s) {
  for (const std::string& n : nodes) {
    nodes_.push_back(nh.resolveName(n, false));
  }
  ros::NodeHandle own(nh);
  own.setCallbackQueue(&queue_);
  timer_ = own.createWallTimer(ros::WallDuration(period_s),
                               [this](const ros::WallTimerEvent&) { checkNow(); });
  spinner_ = std::make_unique<ros::AsyncSpinner>(1, &queue_);
  spinner_->start();
}

NodeSupervisor::~NodeSupervisor() {
  timer_.stop();
  spinner_->stop();
}

std::optional<NodeSupervisor::Death> NodeSupervisor::death() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return death_;
}

void NodeSupervisor::clear() {
  std::lock_guard<std::mutex> lock(mutex_);
  death_.reset();
  confirmed_.reset();
}

std::optional<procedures::Fault> NodeSupervisor::confirmedFault(const ros::WallTime& start,
                                                                double pause_s, int pings) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (confirmed_) {
      return confirmed_;
    }
  }
  const auto d = death();
  if (!d) {
    return std::nullopt;
  }
  for (int i = 0; i < pings; ++i) {
    ros::WallDuration(pause_s).sleep();
    if (ping(d->node, pause_s).empty()) {
      ROS_WARN_STREAM_NAMED(
          "node_supervisor",
          "supervisor: " << d->toString() << " was a false alarm: it answers again");
      clear();
      return std::nullopt;
    }
  }
  std::lock_guard<std::mutex> lock(mutex_);
  confirmed_ = procedures::Fault{d->node, (d->when - start).toSec(), d->reason, d->when.toSec()};
  return confirmed_;
}

namespace {

/// Registration with the master, then getPid on the node's own XML-RPC server; blocks as long
/// as the node takes to answer ("" if it answered, else why not).
std::string pingBlocking(const std::string& node) {
  XmlRpc::XmlRpcValue args, result, payload;
  args[0] = ros::this_node::getName();
  args[1] = node;
  if (!ros::master::execute("lookupNode", args, result, payload, false)) {
    return "not registered with the master";
  }
  std::string host;
  std::uint32_t port = 0;
  if (!ros::network::splitURI(static_cast<std::string>(payload), host, port)) {
    return "the master gave no usable URI";
  }
  XmlRpc::XmlRpcClient client(host.c_str(), static_cast<int>(port), "/");
  XmlRpc::XmlRpcValue ping_args, ping_result;
  ping_args[0] = ros::this_node::getName();
  // A killed node's port refuses the connection at once; a stopped or hung one accepts it and
  // never answers (XmlRpcClient has no timeout: the caller bounds the wait).
  if (!client.execute("getPid", ping_args, ping_result) || client.isFault()) {
    return "no answer to getPid at " + static_cast<std::string>(payload);
  }
  return "";
}

}  // namespace

std::string NodeSupervisor::ping(const std::string& node, double timeout_s) {
  // The blocking ping runs on a thread of its own; a node that does not answer within the
  // timeout (a stopped process) counts as dead, and the thread is left to end when it can.
  auto answer = std::make_shared<std::promise<std::string>>();
  std::future<std::string> result = answer->get_future();
  std::thread([node, answer] { answer->set_value(pingBlocking(node)); }).detach();
  if (result.wait_for(std::chrono::duration<double>(timeout_s)) != std::future_status::ready) {
    return "no answer to getPid within " + std::to_string(timeout_s).substr(0, 4) +
           " s (stopped or hung)";
  }
  return result.get();
}

void NodeSupervisor::checkNow() {
  if (death()) {
    return;
  }
  for (const std::string& node : nodes_) {
    const std::string why = ping(node, ping_timeout_s_);
    if (!why.empty()) {
      const Death d{node, ros::WallTime::now(), why};
      ROS_ERROR_STREAM_NAMED("node_supervisor", "supervisor: " << d.toString());
      std::lock_guard<std::mutex> lock(mutex_);
      death_ = d;
      return;
    }
  }
}

std::vector<std::string> NodeSupervisor::waitForAll(double timeout_s) {
  const ros::WallTime deadline = ros::WallTime::now() + ros::WallDuration(timeout_s);
  std::vector<std::string> missing;
  do {
    missing.clear();
    for (const std::string& node : nodes_) {
      if (!ping(node, ping_timeout_s_).empty()) {
        missing.push_back(node);
      }
    }
    if (missing.empty()) {
      return missing;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  } while (ros::ok() && ros::WallTime::now() < deadline);
  return missing;
}

}  // namespace needle_guidance
