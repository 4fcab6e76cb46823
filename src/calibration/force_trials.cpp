#include "needle_guidance/calibration/force_trials.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/format.h"

namespace needle_guidance::calibration {
namespace {

namespace fs = std::filesystem;
constexpr const char* kHeader = "t_s,depth_mm,force_N";
constexpr double kMmToM = 1e-3;

[[noreturn]] void fail(const std::string& path, int line, const std::string& what) {
  throw std::invalid_argument(path + ":" + std::to_string(line) + ": " + what);
}

std::string trimmed(std::string text) {
  while (!text.empty() && (text.back() == '\r' || text.back() == ' ' || text.back() == '\t')) {
    text.pop_back();
  }
  const std::size_t first = text.find_first_not_of(" \t");
  return first == std::string::npos ? std::string() : text.substr(first);
}

double number(const std::string& field, const std::string& path, int line, const char* column) {
  std::size_t used = 0;
  double value = 0.0;
  try {
    value = std::stod(trimmed(field), &used);
  } catch (const std::exception&) {
    fail(path, line, std::string(column) + " '" + field + "' is not a number");
  }
  if (used != trimmed(field).size()) {
    fail(path, line, std::string(column) + " '" + field + "' is not a number");
  }
  if (!std::isfinite(value)) {
    fail(path, line, std::string(column) + " '" + field + "' is not finite");
  }
  return value;
}

}  // namespace

ForceTrial readForceTrial(const std::string& path) {
  std::ifstream in(path);
  if (!in) {
    throw std::invalid_argument(path + ": cannot open the force trial");
  }
  ForceTrial trial;
  trial.path = path;
  trial.name = fs::path(path).stem().string();
  std::string text;
  int line = 0;
  bool header = false;
  while (std::getline(in, text)) {
    ++line;
    text = trimmed(text);
    if (text.empty()) {
      continue;
    }
    if (!header) {
      if (text != kHeader) {
        fail(path, line, "header '" + text + "' is not '" + kHeader + "'");
      }
      header = true;
      continue;
    }
    std::vector<std::string> fields;
    std::stringstream row(text);
    for (std::string field; std::getline(row, field, ',');) {
      fields.push_back(field);
    }
    if (fields.size() != 3) {
      fail(path, line,
           "expected 3 fields t_s,depth_mm,force_N, found " + std::to_string(fields.size()));
    }
    const double t = number(fields[0], path, line, "t_s");
    if (!trial.t_s.empty() && !(t > trial.t_s.back())) {
      fail(path, line,
           "time " + formatNumber(t) + " s does not increase (previous " +
               formatNumber(trial.t_s.back()) + " s)");
    }
    trial.t_s.push_back(t);
    trial.depth_m.push_back(number(fields[1], path, line, "depth_mm") * kMmToM);
    trial.force_N.push_back(number(fields[2], path, line, "force_N"));
  }
  if (!header) {
    fail(path, std::max(line, 1), "empty file: expected the header '" + std::string(kHeader) + "'");
  }
  if (trial.t_s.size() < 2) {
    fail(path, line, "fewer than two samples");
  }
  return trial;
}

std::vector<ForceTrial> readForceTrials(const std::string& folder) {
  if (!fs::is_directory(folder)) {
    throw std::invalid_argument(folder + ": not a folder of force trials");
  }
  std::vector<std::string> paths;
  for (const auto& entry : fs::directory_iterator(folder)) {
    if (entry.is_regular_file() && entry.path().extension() == ".csv") {
      paths.push_back(entry.path().string());
    }
  }
  if (paths.empty()) {
    throw std::invalid_argument(folder + ": no *.csv force trials");
  }
  std::sort(paths.begin(), paths.end());
  std::vector<ForceTrial> trials;
  trials.reserve(paths.size());
  for (const std::string& path : paths) {
    trials.push_back(readForceTrial(path));
  }
  return trials;
}

double maxDepth(const ForceTrial& trial) {
  return *std::max_element(trial.depth_m.begin(), trial.depth_m.end());
}

std::vector<double> insertionForceAt(const ForceTrial& trial, const std::vector<double>& depths_m) {
  std::vector<double> force(depths_m.size());
  std::size_t i = 0;
  double reached = -1e300;  // running maximum depth: jitter never moves a depth backwards
  double prev_depth = 0.0;
  double prev_force = 0.0;
  for (std::size_t s = 0; s < trial.t_s.size() && i < depths_m.size(); ++s) {
    const double depth = std::max(reached, trial.depth_m[s]);
    while (i < depths_m.size() && depth >= depths_m[i]) {
      const double span = depth - prev_depth;
      const double w = s == 0 || span <= 0.0 ? 1.0 : (depths_m[i] - prev_depth) / span;
      force[i] = (1.0 - w) * prev_force + w * trial.force_N[s];
      ++i;
    }
    reached = depth;
    prev_depth = depth;
    prev_force = trial.force_N[s];
  }
  if (i < depths_m.size()) {
    throw std::invalid_argument(trial.path + ": the insertion reaches " +
                                formatNumber(maxDepth(trial) / kMmToM) + " mm, short of the " +
                                formatNumber(depths_m[i] / kMmToM) + " mm the fit compares at");
  }
  return force;
}

std::vector<double> depthGrid(double first_m, double last_m, double step_m) {
  if (!(step_m > 0.0) || !(first_m > 0.0) || !(last_m >= first_m)) {
    throw std::invalid_argument("depthGrid: need 0 < first <= last and step > 0 (first " +
                                formatNumber(first_m) + " m, last " + formatNumber(last_m) +
                                " m, step " + formatNumber(step_m) + " m)");
  }
  std::vector<double> grid;
  const long n = std::lround(std::floor((last_m - first_m) / step_m + 1e-9));
  for (long k = 0; k <= n; ++k) {
    grid.push_back(first_m + static_cast<double>(k) * step_m);
  }
  return grid;
}

double rmse(const std::vector<double>& a, const std::vector<double>& b) {
  if (a.empty() || a.size() != b.size()) {
    throw std::invalid_argument("rmse: curves of " + std::to_string(a.size()) + " and " +
                                std::to_string(b.size()) + " points");
  }
  double sum = 0.0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    sum += (a[i] - b[i]) * (a[i] - b[i]);
  }
  return std::sqrt(sum / static_cast<double>(a.size()));
}

std::vector<double> leaveOneOutSpread(const std::vector<std::vector<double>>& curves) {
  if (curves.size() < 2) {
    throw std::invalid_argument("leaveOneOutSpread: the spread needs at least two trials");
  }
  const std::size_t n = curves.size();
  std::vector<double> total(curves.front().size(), 0.0);
  for (const auto& curve : curves) {
    for (std::size_t i = 0; i < total.size(); ++i) {
      total[i] += curve.at(i);
    }
  }
  std::vector<double> spread;
  for (const auto& curve : curves) {
    std::vector<double> others(total.size());
    for (std::size_t i = 0; i < total.size(); ++i) {
      others[i] = (total[i] - curve[i]) / static_cast<double>(n - 1);
    }
    spread.push_back(rmse(curve, others));
  }
  return spread;
}

double percentile(std::vector<double> values, double p) {
  if (values.empty()) {
    throw std::invalid_argument("percentile of no values");
  }
  std::sort(values.begin(), values.end());
  const double r = std::clamp(p, 0.0, 100.0) / 100.0 * static_cast<double>(values.size() - 1);
  const std::size_t lo = static_cast<std::size_t>(std::floor(r));
  const std::size_t hi = std::min(lo + 1, values.size() - 1);
  return values[lo] + (r - static_cast<double>(lo)) * (values[hi] - values[lo]);
}

}  // namespace needle_guidance::calibration
