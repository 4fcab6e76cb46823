// Read-once parameter readers: every value is validated, echoed once at INFO, and a missing or
// out-of-range value stops the node with a message naming it.
#pragma once

#include <ros/ros.h>

#include <cmath>
#include <cstdlib>
#include <sstream>
#include <stdexcept>
#include <string>

namespace needle_guidance::ros_params {

/// The parameter `name` of `nh` in [lower, upper], or `fallback` when unset. Throws
/// std::runtime_error naming the parameter for a wrong type, NaN or a value out of range.
inline double number(const ros::NodeHandle& nh, const std::string& name, double fallback,
                     double lower, double upper, const std::string& unit) {
  double value = fallback;
  if (nh.hasParam(name) && !nh.getParam(name, value)) {
    int as_int = 0;
    if (!nh.getParam(name, as_int)) {
      throw std::runtime_error("parameter '" + nh.resolveName(name) + "' is not a number");
    }
    value = as_int;
  }
  if (!std::isfinite(value) || value < lower || value > upper) {
    std::ostringstream out;
    out << "parameter '" << nh.resolveName(name) << "' = " << value << " " << unit
        << " is outside [" << lower << ", " << upper << "] " << unit;
    throw std::runtime_error(out.str());
  }
  ROS_INFO_STREAM("  " << nh.resolveName(name) << " = " << value << " " << unit);
  return value;
}

/// The string parameter `name`, or `fallback` when unset; throws for a wrong type, or for an
/// empty value when `required`.
inline std::string text(const ros::NodeHandle& nh, const std::string& name,
                        const std::string& fallback, bool required = false) {
  std::string value = fallback;
  if (nh.hasParam(name) && !nh.getParam(name, value)) {
    throw std::runtime_error("parameter '" + nh.resolveName(name) + "' is not a string");
  }
  if (required && value.empty()) {
    throw std::runtime_error("parameter '" + nh.resolveName(name) + "' is required");
  }
  ROS_INFO_STREAM("  " << nh.resolveName(name) << " = '"
                       << (value.size() > 80 ? value.substr(0, 77) + "..." : value) << "'");
  return value;
}

/// A choice parameter: the string `name` (`fallback` when unset or empty, as a launch file's ""
/// default passes it) parsed by `parse` (text -> std::optional of an enum); throws naming the
/// parameter, its value and the `choices` otherwise.
template <class Parse>
auto choice(const ros::NodeHandle& nh, const std::string& name, const std::string& fallback,
            Parse parse, const std::string& choices) {
  const std::string value = text(nh, name, fallback);
  const auto parsed = parse(value.empty() ? fallback : value);
  if (!parsed) {
    throw std::runtime_error("parameter '" + nh.resolveName(name) + "' = '" + value + "' is not " +
                             choices);
  }
  return *parsed;
}

/// A boolean parameter (0 / 1 accepted), or `fallback` when unset; echoed once; a wrong type
/// throws naming it.
inline bool flag(const ros::NodeHandle& nh, const std::string& name, bool fallback) {
  bool value = fallback;
  if (nh.hasParam(name) && !nh.getParam(name, value)) {
    int as_int = 0;
    if (!nh.getParam(name, as_int) || (as_int != 0 && as_int != 1)) {
      throw std::runtime_error("parameter '" + nh.resolveName(name) + "' is not a bool");
    }
    value = as_int == 1;
  }
  ROS_INFO_STREAM("  " << nh.resolveName(name) << " = " << (value ? "true" : "false"));
  return value;
}

/// number() that must also be a whole number.
inline long integer(const ros::NodeHandle& nh, const std::string& name, long fallback, long lower,
                    long upper, const std::string& unit) {
  const double value = number(nh, name, static_cast<double>(fallback), static_cast<double>(lower),
                              static_cast<double>(upper), unit);
  if (value != std::floor(value)) {
    throw std::runtime_error("parameter '" + nh.resolveName(name) + "' = " + std::to_string(value) +
                             " is not a whole number");
  }
  return static_cast<long>(value);
}

/// A relative path is taken relative to ROS_HOME (default ~/.ros), as roslaunch does for logs.
inline std::string rosHomePath(const std::string& path) {
  if (path.empty() || path.front() == '/') {
    return path;
  }
  const char* ros_home = std::getenv("ROS_HOME");
  const char* home = std::getenv("HOME");
  const std::string base = ros_home ? ros_home : std::string(home ? home : ".") + "/.ros";
  return base + "/" + path;
}

}  // namespace needle_guidance::ros_params
