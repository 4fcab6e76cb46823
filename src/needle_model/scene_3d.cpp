// Loading and validation of `steering_3d` scene files (scene_3d.h).
#include "needle_guidance/needle_model/scene_3d.h"
#include "needle_guidance/math.h"

#include <yaml-cpp/yaml.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include "needle_guidance/scene/scene.h"
#include "needle_guidance/scene/yaml_reader.h"

namespace needle_guidance::needle_model {
namespace {

using scene::SceneError;
using scene::detail::kAngle;
using scene::detail::kAngularRate;
using scene::detail::kDimensionless;
using scene::detail::kLength;
using scene::detail::kVelocity;
using scene::detail::MapReader;
using scene::detail::Quantity;

/// A quantity that must be > 0 (positive) or >= 0; refused naming its key otherwise.
Quantity bounded(MapReader& r, const std::string& base, const scene::detail::Dimension& dim,
                 bool positive) {
  const Quantity q = r.requiredQuantity(base, dim);
  if (positive ? !(q.si > 0.0) : !(q.si >= 0.0)) {
    r.fail(q.key, q.text, positive ? "must be > 0" : "must be >= 0", q.line);
  }
  return q;
}

NeedleParams3 readNeedle(MapReader r, double& step_length_m) {
  NeedleParams3 p;
  p.kappa_max_per_m = 1.0 / bounded(r, "radius_of_curvature", kLength, true).si;
  p.insertion_speed_m_s = bounded(r, "insertion_speed", kVelocity, true).si;
  p.spin_rate_max_rad_s = bounded(r, "spin_rate_max", kAngularRate, true).si;
  p.duty_cycle_length_m = bounded(r, "duty_cycle_length", kLength, true).si;
  const Quantity step = bounded(r, "step_length", kLength, true);
  step_length_m = step.si;
  if (step_length_m < p.duty_cycle_length_m) {
    r.fail(step.key, step.text, "must be >= duty_cycle_length (a step holds whole duty cycles)",
           step.line);
  }
  try {
    p.validate();
  } catch (const std::invalid_argument& e) {
    r.fail(r.keyPath("spin_rate_max"), std::to_string(p.spin_rate_max_rad_s), e.what());
  }
  r.finish();
  return p;
}

NoiseParams3 readNoise(MapReader r) {
  NoiseParams3 n;
  n.sigma_insert_rad = bounded(r, "sigma_insert", kAngle, false).si;
  n.sigma_spin_rad = bounded(r, "sigma_spin", kAngle, false).si;
  n.sigma_roll_rad = bounded(r, "sigma_roll", kAngle, false).si;
  r.finish();
  return n;
}

/// A mesh entry {mesh: FILE, units: m|cm|mm}; a bad mesh is refused naming both files. What the
/// loader repaired is appended to `repairs` as "KEY FILE: repaired: ...".
Mesh3 readMeshEntry(MapReader& r, const std::string& base_dir, std::string& file_out,
                    std::vector<std::string>& repairs) {
  const std::string file = r.requiredString("mesh");
  const std::string units = r.optionalChoice("units", {"m", "cm", "mm"}).value_or("mm");
  const double scale = units == "m" ? 1.0 : units == "cm" ? 1e-2 : 1e-3;
  const std::filesystem::path p(file);
  file_out = p.is_absolute() ? file : (std::filesystem::path(base_dir) / p).string();
  try {
    MeshRepairs3 repaired;
    Mesh3 mesh = readMesh3(file_out, scale, &repaired);
    if (!repaired.empty()) {
      repairs.push_back(r.keyPath("mesh") + " " + file + ": repaired: " + repaired.toString());
    }
    return mesh;
  } catch (const std::invalid_argument& e) {
    r.fail(r.keyPath("mesh"), file, e.what());
  }
}

EntryRegion3 readEntry(MapReader r) {
  EntryRegion3 e;
  e.center_m = r.requiredVector3("center", kLength).value;
  const scene::detail::Vector3Value dir = r.requiredVector3("direction", kDimensionless);
  if (!(dir.value.norm() > 0.0)) {
    r.fail(dir.key, dir.text, "must be non-zero", dir.line);
  }
  e.direction = dir.value.normalized();
  e.radius_m = bounded(r, "radius", kLength, false).si;
  const Quantity cone = r.requiredQuantity("cone_half_angle", kAngle);
  e.cone_half_angle_rad = cone.si;
  if (!(e.cone_half_angle_rad >= 0.0) || !(e.cone_half_angle_rad < kPi / 2.0)) {
    r.fail(cone.key, cone.text, "must be in [0, 90) deg", cone.line);
  }
  r.finish();
  return e;
}

void readScene(const YAML::Node& root, const std::string& source, const std::string& base_dir,
               Scene3d& s) {
  MapReader top(root, "", source);
  MapReader head = top.requiredMap("scene");
  s.name = head.requiredString("name");
  const std::string kind = head.requiredString("kind");
  if (kind != "steering_3d") {
    head.fail(head.keyPath("kind"), kind, "must be steering_3d for a 3-D steering scene");
  }
  s.description = head.optionalString("description").value_or("");
  head.finish();
  s.needle = readNeedle(top.requiredMap("needle"), s.step_length_m);
  s.noise = readNoise(top.requiredMap("noise"));
  MapReader tissue = top.requiredMap("tissue");
  s.tissue = readMeshEntry(tissue, base_dir, s.tissue_file, s.mesh_repairs);
  tissue.finish();
  std::set<std::string> names;
  for (MapReader o : top.optionalList("obstacles")) {
    ObstacleMesh3 obstacle;
    obstacle.name = o.requiredString("name");
    if (!names.insert(obstacle.name).second) {
      o.fail(o.keyPath("name"), obstacle.name, "duplicated obstacle name");
    }
    std::string file;
    obstacle.mesh = readMeshEntry(o, base_dir, file, s.mesh_repairs);
    obstacle.clearance_m = bounded(o, "clearance", kLength, false).si;
    o.finish();
    s.obstacles.push_back(std::move(obstacle));
    s.obstacle_files.push_back(file);
  }
  MapReader target = top.requiredMap("target");
  s.target.center_m = target.requiredVector3("center", kLength).value;
  s.target.radius_m = bounded(target, "radius", kLength, true).si;
  target.finish();
  s.entry = readEntry(top.requiredMap("entry"));
  if (std::optional<MapReader> planner = top.optionalMap("planner")) {
    if (const auto tol = planner->optionalQuantity("collision_tolerance", kLength)) {
      if (!(tol->si > 0.0)) {
        planner->fail(tol->key, tol->text, "must be > 0", tol->line);
      }
      s.collision_tolerance_m = tol->si;
    }
    planner->finish();
  }
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

}  // namespace needle_guidance::needle_model
