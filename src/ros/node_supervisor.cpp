#include "needle_guidance/ros/node_supervisor.h"

#include <ros/master.h>
#include <ros/network.h>
#include <xmlrpcpp/XmlRpcClient.h>
#include <xmlrpcpp/XmlRpcValue.h>

#include <chrono>
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
}

std::string NodeSupervisor::ping(const std::string& node, double timeout_s) {
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
  // A killed node's port refuses the connection at once. (XmlRpcClient has no timeout: a
  // stopped, not killed, process would block here; timeout_s is kept for that future case.)
  (void)timeout_s;
  if (!client.execute("getPid", ping_args, ping_result) || client.isFault()) {
    return "no answer to getPid at " + static_cast<std::string>(payload);
  }
  return "";
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
