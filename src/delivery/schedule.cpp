#include "needle_guidance/delivery/schedule.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <set>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::delivery {

double ir192DecayFactor(double days) {
  if (!std::isfinite(days) || days < 0.0) {
    throw std::invalid_argument("days since source calibration must be finite and >= 0, got " +
                                std::to_string(days));
  }
  return std::exp(-std::log(2.0) * days / kIr192HalfLifeDays);
}

double parseUtcSeconds(const std::string& text) {
  int y = 0, mo = 0, d = 0, h = 0, mi = 0, s = 0, used = 0;
  const char* t = text.c_str();
  bool ok = false;
  if (std::sscanf(t, "%4d-%2d-%2dT%2d:%2d:%2d%n", &y, &mo, &d, &h, &mi, &s, &used) == 6 &&
      used == static_cast<int>(text.size())) {
    ok = true;
  } else if (s = 0; std::sscanf(t, "%4d-%2d-%2dT%2d:%2d%n", &y, &mo, &d, &h, &mi, &used) == 5 &&
                    used == static_cast<int>(text.size())) {
    ok = true;
  } else if (h = mi = 0; std::sscanf(t, "%4d-%2d-%2d%n", &y, &mo, &d, &used) == 3 &&
                         used == static_cast<int>(text.size())) {
    ok = true;
  }
  static const int kDays[] = {31, 29, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31};
  if (!ok || y < 1970 || mo < 1 || mo > 12 || d < 1 || d > kDays[mo - 1] || h > 23 || mi > 59 ||
      s > 59 || h < 0 || mi < 0 || s < 0) {
    throw std::invalid_argument("'" + text +
                                "' is not a UTC date YYYY-MM-DD or YYYY-MM-DDTHH:MM[:SS]");
  }
  std::tm tm{};
  tm.tm_year = y - 1900;
  tm.tm_mon = mo - 1;
  tm.tm_mday = d;
  tm.tm_hour = h;
  tm.tm_min = mi;
  tm.tm_sec = s;
  const std::time_t seconds = timegm(&tm);
  std::tm back{};
  gmtime_r(&seconds, &back);
  if (back.tm_mday != d)
    throw std::invalid_argument("'" + text + "': no such day");
  return static_cast<double>(seconds);
}

namespace {

double pathLength(const std::vector<Point3>& path) {
  double length = 0.0;
  for (std::size_t k = 1; k < path.size(); ++k)
    length += (path[k] - path[k - 1]).norm();
  return length;
}

/// Point at arc length `arc` from the path's first point (extended straight past its last).
Point3 pointAtArc(const std::vector<Point3>& path, double arc, Point3* axis_to_tip = nullptr) {
  if (path.size() < 2) {
    if (axis_to_tip)
      *axis_to_tip = Point3::UnitZ();
    return path.empty() ? Point3::Zero() : path.front();
  }
  double walked = 0.0;
  for (std::size_t k = 1; k < path.size(); ++k) {
    const Point3 seg = path[k] - path[k - 1];
    const double len = seg.norm();
    if (len <= 0.0)
      continue;
    if (walked + len >= arc || k + 1 == path.size()) {
      if (axis_to_tip)
        *axis_to_tip = -seg / len;
      return path[k - 1] + seg * ((arc - walked) / len);
    }
    walked += len;
  }
  return path.back();
}

/// Arc length from the path's first point of the point of the path closest to p, and the distance.
double arcOfClosest(const std::vector<Point3>& path, const Point3& p, double& off_m) {
  double walked = 0.0, best_arc = 0.0;
  off_m = path.empty() ? HUGE_VAL : (p - path.front()).norm();
  for (std::size_t k = 1; k < path.size(); ++k) {
    const Point3 seg = path[k] - path[k - 1];
    const double len2 = seg.squaredNorm();
    const double u = len2 > 0.0 ? std::clamp((p - path[k - 1]).dot(seg) / len2, 0.0, 1.0) : 0.0;
    const double off = (path[k - 1] + u * seg - p).norm();
    if (off < off_m) {
      off_m = off;
      best_arc = walked + u * std::sqrt(len2);
    }
    walked += std::sqrt(len2);
  }
  return best_arc;
}

void mix(std::uint64_t& h, long long v) {
  for (int b = 0; b < 8; ++b) {
    h ^= static_cast<std::uint64_t>((v >> (8 * b)) & 0xff);
    h *= 1099511628211ULL;
  }
}

}  // namespace

Point3 ChannelSchedule::sourcePosition(double distance) const {
  return pointAtArc(path_m, length_m - distance);
}

std::size_t Schedule::dwellCount() const {
  std::size_t n = 0;
  for (const auto& c : channels)
    n += c.time_s.size();
  return n;
}

double Schedule::totalDwellTime() const {
  double t = 0.0;
  for (const auto& c : channels)
    for (double x : c.time_s)
      t += x;
  return t;
}

int Schedule::channelIndex(int channel) const {
  for (std::size_t k = 0; k < channels.size(); ++k)
    if (channels[k].channel == channel)
      return static_cast<int>(k);
  return -1;
}

std::uint64_t Schedule::contentHash() const {
  std::uint64_t h = 1469598103934665603ULL;
  for (const auto& c : channels) {
    mix(h, c.channel);
    mix(h, std::llround(c.length_m * 1e7));
    for (std::size_t k = 0; k < c.time_s.size(); ++k) {
      mix(h, k < c.dwell_index.size() ? c.dwell_index[k] : -1);
      mix(h, k < c.distance_m.size() ? std::llround(c.distance_m[k] * 1e7) : 0);
      mix(h, std::llround(c.time_s[k] * 1e6));
    }
  }
  return h;
}

Schedule makeSchedule(const dose::HdrCase& c, const std::vector<double>& times_s,
                      const std::string& plan_id, const ScheduleOptions& options) {
  if (times_s.size() != c.dwells.size()) {
    throw std::invalid_argument("makeSchedule: " + std::to_string(times_s.size()) +
                                " dwell times for " + std::to_string(c.dwells.size()) +
                                " dwell positions");
  }
  if (!(options.transfer_length_m >= 0.0) || !std::isfinite(options.transfer_length_m)) {
    throw std::invalid_argument("makeSchedule: transfer length must be finite and >= 0");
  }
  Schedule s;
  s.plan_id = plan_id;
  s.source = c.source;
  s.plan_air_kerma_strength_U = c.air_kerma_strength_U;
  s.decay_days = options.days_since_calibration;
  s.current_air_kerma_strength_U = options.calibration_air_kerma_strength_U > 0.0
                                       ? options.calibration_air_kerma_strength_U *
                                             ir192DecayFactor(options.days_since_calibration)
                                       : c.air_kerma_strength_U;
  if (!(s.current_air_kerma_strength_U >= 0.01 * s.plan_air_kerma_strength_U)) {
    throw std::invalid_argument("makeSchedule: the source's current air-kerma strength " +
                                std::to_string(s.current_air_kerma_strength_U) +
                                " U is under 1 % of the plan's " +
                                std::to_string(s.plan_air_kerma_strength_U) + " U");
  }
  const double scale = s.plan_air_kerma_strength_U / s.current_air_kerma_strength_U;
  for (std::size_t k = 0; k < c.catheters.size(); ++k) {
    const auto& cath = c.catheters[k];
    ChannelSchedule ch;
    ch.channel = options.first_channel + static_cast<int>(k);
    ch.catheter = cath.name;
    ch.path_m = cath.points_m;
    ch.transfer_length_m = options.transfer_length_m;
    ch.length_m = options.transfer_length_m + pathLength(cath.points_m);
    // Dwells of this catheter, tip first.
    std::vector<std::pair<double, std::size_t>> order;
    for (std::size_t j = 0; j < c.dwells.size(); ++j) {
      if (c.dwells[j].catheter != static_cast<int>(k))
        continue;
      const double t = times_s[j];
      if (!std::isfinite(t) || t < 0.0) {
        throw std::invalid_argument("makeSchedule: dwell " + std::to_string(j) + " has time " +
                                    std::to_string(t) + " s (must be finite and >= 0)");
      }
      if (t <= options.min_dwell_s)
        continue;
      double off = 0.0;
      const double arc = arcOfClosest(cath.points_m, c.dwells[j].position_m, off);
      if (off > 1e-4) {
        throw std::invalid_argument("makeSchedule: dwell " + std::to_string(j) + " lies " +
                                    std::to_string(off * 1e3) + " mm off catheter " + cath.name);
      }
      order.emplace_back(arc, j);
    }
    if (order.empty())
      continue;
    std::sort(order.begin(), order.end());
    for (const auto& [arc, j] : order) {
      ch.dwell_index.push_back(c.dwells[j].index);
      ch.distance_m.push_back(ch.length_m - arc);
      ch.time_s.push_back(times_s[j] * scale);
      ch.position_m.push_back(c.dwells[j].position_m);
    }
    s.channels.push_back(std::move(ch));
  }
  return s;
}

bool isValidPlanId(const std::string& id) {
  return !id.empty() && id.size() <= 100 && id.front() != '.' &&
         id.find_first_not_of(kPlanIdCharacters) == std::string::npos;
}

std::vector<std::string> validateSchedule(const Schedule& s, const DeviceLimits& limits) {
  std::vector<std::string> problems;
  if (!isValidPlanId(s.plan_id)) {
    problems.push_back("plan_id '" + s.plan_id +
                       "' must be 1-100 characters of [A-Za-z0-9_.-], not starting with '.'");
  }
  std::set<int> seen;
  double total = 0.0;
  for (const auto& c : s.channels) {
    const std::string where = "channel " + std::to_string(c.channel);
    if (c.channel < 1 || c.channel > limits.channels) {
      problems.push_back(where + ": unknown (the afterloader has channels 1-" +
                         std::to_string(limits.channels) + ")");
    }
    if (!seen.insert(c.channel).second)
      problems.push_back(where + ": listed twice");
    if (!std::isfinite(c.length_m) || c.length_m <= 0.0 || c.length_m > limits.max_length_m) {
      problems.push_back(where + ": length " + std::to_string(c.length_m) + " m outside (0, " +
                         std::to_string(limits.max_length_m) + "] m");
    }
    if (!std::isfinite(c.transfer_length_m) || c.transfer_length_m < 0.0 ||
        c.transfer_length_m >= c.length_m) {
      problems.push_back(where + ": transfer length " + std::to_string(c.transfer_length_m) +
                         " m not in [0, length)");
    }
    const std::size_t n = c.time_s.size();
    if (c.distance_m.size() != n || c.dwell_index.size() != n) {
      problems.push_back(where + ": " + std::to_string(n) + " times, " +
                         std::to_string(c.distance_m.size()) + " distances and " +
                         std::to_string(c.dwell_index.size()) + " dwell indices");
      continue;
    }
    for (std::size_t k = 0; k < n; ++k) {
      const std::string dwell = where + " dwell " + std::to_string(k);
      const double t = c.time_s[k], d = c.distance_m[k];
      if (!std::isfinite(t) || t < 0.0 || t > limits.max_dwell_s) {
        problems.push_back(dwell + ": time " + std::to_string(t) + " s outside [0, " +
                           std::to_string(limits.max_dwell_s) + "] s");
      } else {
        total += t;
      }
      if (!std::isfinite(d) || d <= 0.0 || d > c.length_m) {
        problems.push_back(dwell + ": distance " + std::to_string(d) + " m outside (0, length]");
      } else if (k > 0 && !(d < c.distance_m[k - 1])) {
        problems.push_back(dwell + ": distances must decrease from the tip (" + std::to_string(d) +
                           " m after " + std::to_string(c.distance_m[k - 1]) + " m)");
      }
    }
  }
  if (problems.empty() && !(total > 0.0))
    problems.push_back("the schedule has no dwell time");
  return problems;
}

double tripTransitSeconds(const ChannelSchedule& channel, double speed_m_s) {
  double distal = 0.0;
  for (std::size_t k = 0; k < channel.time_s.size() && k < channel.distance_m.size(); ++k) {
    if (channel.time_s[k] > 0.0)
      distal = std::max(distal, channel.distance_m[k]);
  }
  return 2.0 * std::max(0.0, distal - channel.transfer_length_m) / speed_m_s;
}

std::vector<TransitSample> tripTransitSamples(const ChannelSchedule& channel, double speed_m_s,
                                              double step_m) {
  std::vector<TransitSample> samples;
  const double in_patient = tripTransitSeconds(channel, speed_m_s) * speed_m_s / 2.0;
  const int n = static_cast<int>(std::ceil(in_patient / step_m - 1e-9));
  for (int k = 0; k < n; ++k) {
    const double len = std::min(step_m, in_patient - k * step_m);
    const double distance = channel.transfer_length_m + k * step_m + 0.5 * len;
    TransitSample t;
    t.position_m = pointAtArc(channel.path_m, channel.length_m - distance, &t.axis);
    t.time_s = 2.0 * len / speed_m_s;
    samples.push_back(t);
  }
  return samples;
}

}  // namespace needle_guidance::delivery
