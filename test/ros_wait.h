// Shared by the rostests: waits on wall time for what other processes (the nodes
// under test) do.
#pragma once

#include <ros/network.h>
#include <ros/ros.h>
#include <xmlrpcpp/XmlRpcClient.h>

#include <fstream>
#include <limits>
#include <optional>
#include <sstream>
#include <string>

/// Polls pred() every poll_s seconds until it holds or timeout_s seconds of wall time have
/// passed; returns pred() at the end.
template <typename Pred>
bool waitFor(Pred pred, double timeout_s = 10.0, double poll_s = 0.01) {
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(timeout_s);
  while (ros::WallTime::now() < end) {
    if (pred()) {
      return true;
    }
    ros::WallDuration(poll_s).sleep();
  }
  return pred();
}

/// Waits up to timeout_s seconds for `path` to be readable (e.g. a procedure's summary.json).
inline bool waitForFile(const std::string& path, double timeout_s) {
  return waitFor([&path] { return std::ifstream(path).good(); }, timeout_s, 0.5);
}

/// The whole text of `path`; empty when it cannot be read.
inline std::string readText(const std::string& path) {
  std::stringstream text;
  text << std::ifstream(path).rdbuf();
  return text.str();
}

/// The number after "key": in a summary.json text; NaN when the key is missing.
inline double jsonNumber(const std::string& json, const std::string& key) {
  const std::size_t at = json.find("\"" + key + "\": ");
  return at == std::string::npos ? std::numeric_limits<double>::quiet_NaN()
                                 : std::stod(json.substr(at + key.size() + 4));
}

/// The text of `path` once it is readable, or nullopt when it does not appear within timeout_s
/// seconds (a procedure's summary.json, written once the procedure has ended).
inline std::optional<std::string> waitForText(const std::string& path, double timeout_s) {
  if (!waitForFile(path, timeout_s)) {
    return std::nullopt;
  }
  return readText(path);
}

/// The first message a new subscriber to `topic` receives (a latched topic's last message),
/// spinning the global queue; nullopt if none arrives within timeout_s seconds.
template <typename Msg>
std::optional<Msg> firstMessage(const std::string& topic, double timeout_s) {
  ros::NodeHandle nh;
  std::optional<Msg> received;
  ros::Subscriber sub = nh.subscribe<Msg>(
      topic, 1, [&received](const boost::shared_ptr<const Msg>& m) { received = *m; });
  waitFor(
      [&received] {
        ros::spinOnce();
        return received.has_value();
      },
      timeout_s, 0.02);
  return received;
}

/// The pid of `node` (e.g. "/afterloader") from its own XML-RPC getPid, or -1 if it does not
/// answer (for tests that kill a node).
inline int nodePid(const std::string& node) {
  XmlRpc::XmlRpcValue args, result, payload;
  args[0] = ros::this_node::getName();
  args[1] = node;
  if (!ros::master::execute("lookupNode", args, result, payload, true))
    return -1;
  const std::string uri = payload;
  std::string host;
  uint32_t port = 0;
  if (!ros::network::splitURI(uri, host, port))
    return -1;
  XmlRpc::XmlRpcClient rpc(host.c_str(), static_cast<int>(port), "/");
  XmlRpc::XmlRpcValue pid_args, pid_result;
  pid_args[0] = ros::this_node::getName();
  if (!rpc.execute("getPid", pid_args, pid_result) || pid_result.size() < 3)
    return -1;
  return static_cast<int>(pid_result[2]);
}
