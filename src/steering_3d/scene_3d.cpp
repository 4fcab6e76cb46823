// Loading and validation of `steering_3d` scene files (scene_3d.h).
#include "needle_guidance/steering_3d/scene_3d.h"

#include <yaml-cpp/yaml.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include "needle_guidance/scene/scene.h"

namespace needle_guidance::steering_3d {
namespace {

using scene::SceneError;
constexpr double kPi = 3.14159265358979323846;

struct UnitSpec {
  const char* suffix;
  double to_si;
};
const std::vector<UnitSpec> kLength{{"_m", 1.0}, {"_cm", 1e-2}, {"_mm", 1e-3}};
const std::vector<UnitSpec> kAngle{{"_deg", kPi / 180.0}, {"_rad", 1.0}};
const std::vector<UnitSpec> kSpeed{{"_m_s", 1.0}, {"_mm_s", 1e-3}};
const std::vector<UnitSpec> kSpinRate{{"_rad_s", 1.0}, {"_rev_s", 2.0 * kPi}};

std::string text(const YAML::Node& node) {
  YAML::Emitter e;
  e.SetMapFormat(YAML::Flow);
  e.SetSeqFormat(YAML::Flow);
  e << node;
  std::string s = e.c_str();
  return s.size() > 80 ? s.substr(0, 77) + "..." : s;
}

/// One mapping of the file: typed keys with unit suffixes, unknown keys refused.
class Reader {
public:
  Reader(YAML::Node node, std::string path, std::string file)
      : node_(std::move(node)), path_(std::move(path)), file_(std::move(file)) {
    if (node_ && !node_.IsNull() && !node_.IsMap()) {
      fail("", text(node_), "must be a mapping");
    }
  }
  std::string key(const std::string& k) const { return path_.empty() ? k : path_ + "." + k; }
  [[noreturn]] void fail(const std::string& k, const std::string& value,
                         const std::string& reason) const {
    throw SceneError(file_, k.empty() ? path_ : key(k), value, reason);
  }
  YAML::Node get(const std::string& k) {
    known_.insert(k);
    return node_ ? node_[k] : YAML::Node();
  }
  bool has(const std::string& k) {
    const YAML::Node n = get(k);
    return n && !n.IsNull();
  }
  std::string string(const std::string& k) {
    const YAML::Node n = get(k);
    if (!n || n.IsNull()) {
      fail(k, "", "missing");
    }
    if (!n.IsScalar()) {
      fail(k, text(n), "must be a string");
    }
    return n.as<std::string>();
  }
  double number(const std::string& k, const YAML::Node& n) const {
    try {
      const double v = n.as<double>();
      if (std::isfinite(v)) {
        return v;
      }
    } catch (const YAML::Exception&) {
    }
    fail(k, text(n), "must be a finite number");
  }
  /// base + one unit suffix, converted to SI; `fallback` (in SI) if absent and given.
  double quantity(const std::string& base, const std::vector<UnitSpec>& units,
                  std::optional<double> fallback = std::nullopt) {
    std::optional<double> value;
    std::string found;
    for (const UnitSpec& u : units) {
      const std::string k = base + u.suffix;
      const YAML::Node n = get(k);
      if (n && !n.IsNull()) {
        if (value) {
          fail(k, text(n), "given twice: also as '" + key(found) + "'");
        }
        value = number(k, n) * u.to_si;
        found = k;
      }
    }
    if (!value) {
      if (fallback) {
        return *fallback;
      }
      std::string names;
      for (const UnitSpec& u : units) {
        names += (names.empty() ? "" : " | ") + base + u.suffix;
      }
      fail(base, "", "missing (one of " + names + ")");
    }
    last_key_ = found;
    return *value;
  }
  /// quantity() that must be > 0 (positive) or >= 0.
  double bounded(const std::string& base, const std::vector<UnitSpec>& units, bool positive) {
    const double v = quantity(base, units);
    if (positive ? !(v > 0.0) : !(v >= 0.0)) {
      fail(last_key_, std::to_string(v), positive ? "must be > 0" : "must be >= 0");
    }
    return v;
  }
  Vector3 vector(const std::string& base, const std::vector<UnitSpec>& units) {
    for (const UnitSpec& u : units) {
      const std::string k = base + u.suffix;
      const YAML::Node n = get(k);
      if (n && !n.IsNull()) {
        return toVector(k, n) * u.to_si;
      }
    }
    fail(base + units.front().suffix, "", "missing");
  }
  Vector3 plainVector(const std::string& k) {
    const YAML::Node n = get(k);
    if (!n || n.IsNull()) {
      fail(k, "", "missing");
    }
    return toVector(k, n);
  }
  Vector3 toVector(const std::string& k, const YAML::Node& n) const {
    if (!n.IsSequence() || n.size() != 3) {
      fail(k, text(n), "must be a list [x, y, z]");
    }
    return Vector3(number(k, n[0]), number(k, n[1]), number(k, n[2]));
  }
  const std::string& lastKey() const { return last_key_; }
  void finish() const {
    if (!node_ || node_.IsNull()) {
      return;
    }
    for (const auto& kv : node_) {
      const std::string k = kv.first.as<std::string>();
      if (known_.count(k) == 0) {
        fail(k, text(kv.second), "unknown key");
      }
    }
  }
  const std::string& file() const { return file_; }

private:
  YAML::Node node_;
  std::string path_;
  std::string file_;
  std::set<std::string> known_;
  std::string last_key_;
};

NeedleParams3 readNeedle(Reader r, double& step_length_m) {
  NeedleParams3 p;
  p.kappa_max_per_m = 1.0 / r.bounded("radius_of_curvature", kLength, true);
  p.insertion_speed_m_s = r.bounded("insertion_speed", kSpeed, true);
  p.spin_rate_max_rad_s = r.bounded("spin_rate_max", kSpinRate, true);
  p.duty_cycle_length_m = r.bounded("duty_cycle_length", kLength, true);
  step_length_m = r.bounded("step_length", kLength, true);
  if (step_length_m < p.duty_cycle_length_m) {
    r.fail(r.lastKey(), std::to_string(step_length_m),
           "must be >= duty_cycle_length (a step holds whole duty cycles)");
  }
  try {
    p.validate();
  } catch (const std::invalid_argument& e) {
    r.fail("spin_rate_max", std::to_string(p.spin_rate_max_rad_s), e.what());
  }
  r.finish();
  return p;
}

NoiseParams3 readNoise(Reader r) {
  NoiseParams3 n;
  n.sigma_insert_rad = r.bounded("sigma_insert", kAngle, false);
  n.sigma_spin_rad = r.bounded("sigma_spin", kAngle, false);
  n.sigma_roll_rad = r.bounded("sigma_roll", kAngle, false);
  r.finish();
  return n;
}

/// A mesh entry {mesh: FILE, units: m|cm|mm}; a bad mesh is refused naming both files.
Mesh3 readMeshEntry(Reader& r, const std::string& base_dir, std::string& file_out) {
  const std::string file = r.string("mesh");
  const std::string units = r.has("units") ? r.string("units") : "mm";
  double scale = 1e-3;
  if (units == "m") {
    scale = 1.0;
  } else if (units == "cm") {
    scale = 1e-2;
  } else if (units != "mm") {
    r.fail("units", units, "must be one of m | cm | mm");
  }
  const std::filesystem::path p(file);
  file_out = p.is_absolute() ? file : (std::filesystem::path(base_dir) / p).string();
  try {
    return readMesh3(file_out, scale);
  } catch (const std::invalid_argument& e) {
    r.fail("mesh", file, e.what());
  }
}

EntryRegion3 readEntry(Reader r) {
  EntryRegion3 e;
  e.center_m = r.vector("center", kLength);
  const Vector3 dir = r.plainVector("direction");
  if (!(dir.norm() > 0.0)) {
    r.fail("direction", "[0, 0, 0]", "must be non-zero");
  }
  e.direction = dir.normalized();
  e.radius_m = r.bounded("radius", kLength, false);
  e.cone_half_angle_rad = r.quantity("cone_half_angle", kAngle);
  if (!(e.cone_half_angle_rad >= 0.0) || !(e.cone_half_angle_rad < kPi / 2.0)) {
    r.fail(r.lastKey(), std::to_string(e.cone_half_angle_rad), "must be in [0, 90) deg");
  }
  r.finish();
  return e;
}

void readScene(const YAML::Node& root, const std::string& source, const std::string& base_dir,
               Scene3d& s) {
  Reader top(root, "", source);
  Reader head(top.get("scene"), "scene", source);
  s.name = head.string("name");
  const std::string kind = head.string("kind");
  if (kind != "steering_3d") {
    head.fail("kind", kind, "must be steering_3d for a 3-D steering scene");
  }
  s.description = head.has("description") ? head.string("description") : "";
  head.finish();
  s.needle = readNeedle(Reader(top.get("needle"), "needle", source), s.step_length_m);
  s.noise = readNoise(Reader(top.get("noise"), "noise", source));
  Reader tissue(top.get("tissue"), "tissue", source);
  s.tissue = readMeshEntry(tissue, base_dir, s.tissue_file);
  tissue.finish();
  const YAML::Node obstacles = top.get("obstacles");
  if (obstacles && !obstacles.IsNull() && !obstacles.IsSequence()) {
    top.fail("obstacles", text(obstacles), "must be a list");
  }
  std::set<std::string> names;
  for (std::size_t i = 0; obstacles && i < obstacles.size(); ++i) {
    Reader o(obstacles[i], "obstacles[" + std::to_string(i) + "]", source);
    ObstacleMesh3 obstacle;
    obstacle.name = o.string("name");
    if (!names.insert(obstacle.name).second) {
      o.fail("name", obstacle.name, "duplicated obstacle name");
    }
    std::string file;
    obstacle.mesh = readMeshEntry(o, base_dir, file);
    obstacle.clearance_m = o.bounded("clearance", kLength, false);
    o.finish();
    s.obstacles.push_back(std::move(obstacle));
    s.obstacle_files.push_back(file);
  }
  Reader target(top.get("target"), "target", source);
  s.target.center_m = target.vector("center", kLength);
  s.target.radius_m = target.bounded("radius", kLength, true);
  target.finish();
  s.entry = readEntry(Reader(top.get("entry"), "entry", source));
  Reader planner(top.get("planner"), "planner", source);
  s.collision_tolerance_m = planner.quantity("collision_tolerance", kLength, 5e-5);
  if (!(s.collision_tolerance_m > 0.0)) {
    planner.fail("collision_tolerance", std::to_string(s.collision_tolerance_m), "must be > 0");
  }
  planner.finish();
  top.finish();
}

}  // namespace

bool EntryRegion3::allows(const Vector3& p, const Vector3& tangent, double tol_m) const {
  const Vector3 r = p - center_m;
  const double along = r.dot(direction);
  const double radial = (r - along * direction).norm();
  const double cos_angle = tangent.normalized().dot(direction);
  return std::abs(along) <= tol_m && radial <= radius_m + tol_m &&
         cos_angle >= std::cos(cone_half_angle_rad) - 1e-12;
}

CollisionWorld3 Scene3d::collisionWorld() const {
  return CollisionWorld3(tissue, obstacles, collision_tolerance_m);
}

Scene3d parseScene3d(const std::string& yaml_text, const std::string& source,
                     const std::string& base_dir) {
  Scene3d s;
  s.source = source;
  YAML::Node root;
  try {
    root = YAML::Load(yaml_text);
  } catch (const YAML::Exception& e) {
    throw SceneError(source, "", "", std::string("YAML error: ") + e.what());
  }
  if (!root.IsMap()) {
    throw SceneError(source, "", "", "the file must be a YAML mapping");
  }
  readScene(root, source, base_dir, s);
  // The entry must lie in the tissue (on its boundary counts): else no needle can start.
  const CollisionWorld3 world = s.collisionWorld();
  const PointCheck entry = world.classify(s.entry.center_m);
  if (entry.contact == Contact3::kOutsideTissue) {
    std::ostringstream os;
    os << "[" << s.entry.center_m.transpose() * 1e3 << "] mm";
    throw SceneError(source, "entry.center", os.str(),
                     "lies outside the tissue mesh '" + s.tissue_file + "'");
  }
  return s;
}

Scene3d loadScene3d(const std::string& path) {
  std::ifstream in(path);
  if (!in || std::filesystem::is_directory(path)) {
    throw SceneError(path, "", "", "cannot open scene file");
  }
  std::stringstream buffer;
  buffer << in.rdbuf();
  const std::string dir = std::filesystem::path(path).parent_path().string();
  return parseScene3d(buffer.str(), path, dir.empty() ? "." : dir);
}

}  // namespace needle_guidance::steering_3d
