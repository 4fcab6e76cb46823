// The DP look-up table (dissertation 5.4.3, 5.5): look-up, best start state, file I/O.
#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/math.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <iomanip>
#include <sstream>
#include <stdexcept>
#include <utility>

namespace needle_guidance::steering {
namespace {

constexpr char kMagic[8] = {'N', 'G', 'S', 'T', 'E', 'E', 'R', '\0'};
constexpr std::uint32_t kFormatVersion = 1;
/// Angular slack when testing a grid orientation against the start range [rad].
constexpr double kThetaSlack_rad = 1e-9;

std::string hex(std::uint64_t v) {
  std::ostringstream s;
  s << "0x" << std::hex << std::setw(16) << std::setfill('0') << v;
  return s.str();
}

class Checksum {
public:
  void add(const void* data, std::size_t n) {
    const auto* p = static_cast<const unsigned char*>(data);
    for (std::size_t i = 0; i < n; ++i) {
      h_ ^= p[i];
      h_ *= 1099511628211ull;
    }
  }
  std::uint64_t value() const { return h_; }

private:
  std::uint64_t h_ = 14695981039346656037ull;
};

/// The fixed-size header of a table file.
struct Header {
  char magic[8];
  std::uint32_t version;
  std::int32_t nx, ny, nc;
  std::uint64_t hash;
  double origin_x, origin_y, spacing_m, epsilon;
  std::int32_t sweeps;
  std::int32_t converged;
  std::int64_t n_states;
};

}  // namespace

std::string ControlLookup::toString() const {
  std::ostringstream s;
  switch (status) {
    case Status::kOk:
      s << "ok: " << steering::toString(control) << ", P_s = " << probability_of_success;
      break;
    case Status::kOutsideGrid:
      s << "outside grid";
      break;
    case Status::kInTarget:
      s << "in target";
      break;
    case Status::kInObstacle:
      s << "in obstacle";
      break;
  }
  return s.str();
}

std::string BestStart::toString() const {
  if (!found) {
    return message;
  }
  std::ostringstream s;
  s << "best start: y = " << best.pose.p_SceneTip.y()
    << " m, theta = " << best.pose.theta_rad * 180.0 / kPi << " deg, bevel "
    << steering::toString(best.pose.bevel) << ", P_s = " << best.probability_of_success;
  return s.str();
}

StartOptions startOptionsFromScene(const scene::Scene& scene) {
  if (!scene.steering) {
    throw std::invalid_argument("startOptionsFromScene: scene '" + scene.name +
                                "' has no steering section");
  }
  StartOptions o;
  o.start_x_m = scene.steering->start_x_m;
  o.min_height_m = scene.needle.min_height_m;
  o.max_height_m = scene.needle.max_height_m;
  return o;
}

PolicyTable::PolicyTable(GridSpec grid, std::uint64_t problem_hash, std::vector<float> values,
                         std::vector<std::uint64_t> control_bits, std::vector<std::uint8_t> cells,
                         double epsilon, int sweeps, bool converged)
    : grid_(std::move(grid)),
      hash_(problem_hash),
      values_(std::move(values)),
      bits_(std::move(control_bits)),
      cells_(std::move(cells)),
      epsilon_(epsilon),
      sweeps_(sweeps),
      converged_(converged) {
  const std::int64_t n = grid_.numStates();
  if (grid_.nx < 1 || grid_.ny < 1 || grid_.nc < 4 || !(grid_.spacing_m > 0.0) ||
      values_.size() != static_cast<std::size_t>(n) ||
      bits_.size() != static_cast<std::size_t>((n + 63) / 64) ||
      cells_.size() != static_cast<std::size_t>(grid_.numPositions())) {
    throw std::invalid_argument("PolicyTable: sizes (values " + std::to_string(values_.size()) +
                                ", control words " + std::to_string(bits_.size()) + ", cells " +
                                std::to_string(cells_.size()) + ") do not match the grid " +
                                std::to_string(grid_.nx) + " x " + std::to_string(grid_.ny) +
                                " x " + std::to_string(grid_.nc) + " x 2");
  }
}

ControlLookup PolicyTable::lookup(const TipPose& pose) const noexcept {
  ControlLookup out;
  const StateId s = grid_.nearestState(pose);
  if (s < 0) {
    return out;
  }
  out.state = s;
  out.probability_of_success = values_[static_cast<std::size_t>(s)];
  switch (cell(s / (2 * grid_.nc))) {
    case Cell::kTarget:
      out.status = ControlLookup::Status::kInTarget;
      break;
    case Cell::kObstacle:
      out.status = ControlLookup::Status::kInObstacle;
      break;
    case Cell::kFree:
      out.status = ControlLookup::Status::kOk;
      out.control = control(s);
      break;
  }
  return out;
}

std::vector<StartCandidate> PolicyTable::startCandidates(const StartOptions& options) const {
  std::vector<StartCandidate> out;
  const double fx = (options.start_x_m - grid_.origin.x()) / grid_.spacing_m;
  if (!(fx >= -0.5 && fx < grid_.nx + 1.0)) {  // as GridSpec::nearestState
    return out;
  }
  const int ix = std::min(grid_.nx - 1, static_cast<int>(std::floor(fx + 0.5)));
  const double lo_y = std::ceil((options.min_height_m - grid_.origin.y()) / grid_.spacing_m - 1e-9);
  const double hi_y =
      std::floor((options.max_height_m - grid_.origin.y()) / grid_.spacing_m + 1e-9);
  const int iy0 = static_cast<int>(std::max(0.0, lo_y));
  const int iy1 = static_cast<int>(std::min(static_cast<double>(grid_.ny - 1), hi_y));
  for (int b = 0; b < 2; ++b) {
    for (int iy = iy0; iy <= iy1; ++iy) {
      for (int k = 0; k < grid_.nc; ++k) {
        const StateId s = grid_.state(ix, iy, k, static_cast<Bevel>(b));
        const TipPose pose = grid_.pose(s);  // theta in (-pi, pi]
        if (pose.theta_rad < options.min_theta_rad - kThetaSlack_rad ||
            pose.theta_rad > options.max_theta_rad + kThetaSlack_rad) {
          continue;
        }
        out.push_back({pose, s, values_[static_cast<std::size_t>(s)]});
      }
    }
  }
  return out;
}

BestStart PolicyTable::bestStart(const StartOptions& options) const {
  BestStart out;
  const auto candidates = startCandidates(options);
  if (candidates.empty()) {
    out.message =
        "bestStart: no grid state on the entry line x = " + std::to_string(options.start_x_m) +
        " m within the height and angle limits";
    return out;
  }
  out.best = candidates.front();
  for (const auto& c : candidates) {
    if (c.probability_of_success > out.best.probability_of_success) {
      out.best = c;
    }
  }
  out.found = out.best.probability_of_success > 0.0f;
  if (!out.found) {
    out.message = "bestStart: all " + std::to_string(candidates.size()) +
                  " start states on x = " + std::to_string(options.start_x_m) +
                  " m have P_s = 0 (target unreachable from the entry line)";
  }
  return out;
}

void PolicyTable::save(const std::string& path) const {
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  if (!f) {
    throw std::runtime_error("PolicyTable::save: cannot open '" + path + "' for writing");
  }
  Header h{};
  std::memcpy(h.magic, kMagic, sizeof kMagic);
  h.version = kFormatVersion;
  h.nx = grid_.nx;
  h.ny = grid_.ny;
  h.nc = grid_.nc;
  h.hash = hash_;
  h.origin_x = grid_.origin.x();
  h.origin_y = grid_.origin.y();
  h.spacing_m = grid_.spacing_m;
  h.epsilon = epsilon_;
  h.sweeps = sweeps_;
  h.converged = converged_ ? 1 : 0;
  h.n_states = grid_.numStates();
  Checksum sum;
  auto put = [&](const void* data, std::size_t n) {
    sum.add(data, n);
    f.write(static_cast<const char*>(data), static_cast<std::streamsize>(n));
  };
  put(&h, sizeof h);
  put(values_.data(), values_.size() * sizeof(float));
  put(cells_.data(), cells_.size());
  put(bits_.data(), bits_.size() * sizeof(std::uint64_t));
  const std::uint64_t check = sum.value();
  f.write(reinterpret_cast<const char*>(&check), sizeof check);
  f.flush();
  if (!f) {
    throw std::runtime_error("PolicyTable::save: writing '" + path + "' failed");
  }
}

std::string PolicyTable::fileName(const std::string& scene_name, std::uint64_t problem_hash) {
  std::ostringstream s;
  s << scene_name << "_" << std::hex << std::setw(16) << std::setfill('0') << problem_hash
    << ".table";
  return s.str();
}

std::optional<PolicyTable> PolicyTable::load(const std::string& path, std::uint64_t expected_hash,
                                             LoadStatus& status, double max_epsilon) {
  using Code = LoadStatus::Code;
  auto refuse = [&](Code code, const std::string& why) {
    status = LoadStatus(code, "PolicyTable::load: '" + path + "': " + why);
    return std::nullopt;
  };
  std::ifstream f(path, std::ios::binary);
  if (!f) {
    return refuse(Code::kCannotOpen, "cannot open");
  }
  Header h{};
  if (!f.read(reinterpret_cast<char*>(&h), sizeof h)) {
    return refuse(Code::kCorrupt, "shorter than a table header");
  }
  if (std::memcmp(h.magic, kMagic, sizeof kMagic) != 0) {
    return refuse(Code::kCorrupt, "not a steering policy table (bad magic)");
  }
  if (h.version != kFormatVersion) {
    return refuse(Code::kCorrupt, "format version " + std::to_string(h.version) + ", expected " +
                                      std::to_string(kFormatVersion));
  }
  if (h.hash != expected_hash) {
    return refuse(Code::kMismatch, "solved for problem hash " + hex(h.hash) +
                                       " but this scene and these parameters hash to " +
                                       hex(expected_hash) +
                                       " (other scene, target or discretisation); re-solve");
  }
  if (h.epsilon > max_epsilon) {
    return refuse(Code::kTooLoose, "solved to epsilon " + std::to_string(h.epsilon) +
                                       " > requested " + std::to_string(max_epsilon) +
                                       "; re-solve");
  }
  GridSpec g;
  g.origin = Point2(h.origin_x, h.origin_y);
  g.spacing_m = h.spacing_m;
  g.nx = h.nx;
  g.ny = h.ny;
  g.nc = h.nc;
  if (g.nx < 1 || g.ny < 1 || g.nc < 4 || !(g.spacing_m > 0.0) || h.n_states != g.numStates() ||
      h.n_states >= (std::int64_t{1} << 31)) {
    return refuse(Code::kCorrupt, "inconsistent grid in header");
  }
  const auto n = static_cast<std::size_t>(h.n_states);
  std::vector<float> values(n);
  std::vector<std::uint8_t> cells(static_cast<std::size_t>(g.numPositions()));
  std::vector<std::uint64_t> bits((n + 63) / 64);
  std::uint64_t stored = 0;
  f.read(reinterpret_cast<char*>(values.data()), static_cast<std::streamsize>(n * sizeof(float)));
  f.read(reinterpret_cast<char*>(cells.data()), static_cast<std::streamsize>(cells.size()));
  f.read(reinterpret_cast<char*>(bits.data()),
         static_cast<std::streamsize>(bits.size() * sizeof(std::uint64_t)));
  f.read(reinterpret_cast<char*>(&stored), sizeof stored);
  if (!f) {
    return refuse(Code::kCorrupt, "truncated");
  }
  Checksum sum;
  sum.add(&h, sizeof h);
  sum.add(values.data(), n * sizeof(float));
  sum.add(cells.data(), cells.size());
  sum.add(bits.data(), bits.size() * sizeof(std::uint64_t));
  if (sum.value() != stored) {
    return refuse(Code::kCorrupt, "checksum mismatch (file damaged)");
  }
  status = LoadStatus::success("PolicyTable::load: '" + path + "': ok");
  return PolicyTable(g, h.hash, std::move(values), std::move(bits), std::move(cells), h.epsilon,
                     h.sweeps, h.converged != 0);
}

}  // namespace needle_guidance::steering
