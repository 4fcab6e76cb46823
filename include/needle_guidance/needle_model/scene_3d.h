// Scene kind `steering_3d`: a YAML file naming closed triangle meshes (tissue
// boundary, obstacles with clearances), a target sphere, an entry disc with a cone of entry
// directions, the needle and its noise. Loaded and validated here; a bad file is refused with
// scene::SceneError naming the file, the key and the value (and the mesh file for a bad mesh).
// The format is in docs/scenes.md and config/scenes/steering_3d/*.yaml.
#pragma once

#include <string>
#include <vector>

#include "needle_guidance/needle_model/collision_3d.h"
#include "needle_guidance/needle_model/needle_3d.h"

namespace needle_guidance::needle_model {

/// Success region: the closed ball.
struct Target3 {
  Vector3 center_m = Vector3::Zero();  ///< [m], frame scene
  double radius_m = 0.0;               ///< > 0 [m]
};

/// Allowed entries: tip on the disc of radius_m about center_m perpendicular to direction, with
/// its tangent within cone_half_angle_rad of direction.
struct EntryRegion3 {
  Vector3 center_m = Vector3::Zero();
  Vector3 direction = Vector3::UnitX();  ///< unit
  double radius_m = 0.0;                 ///< >= 0 [m]
  double cone_half_angle_rad = 0.0;      ///< in [0, pi/2) [rad]
  /// True if the point lies on the disc (within tol_m of its plane) and the tangent in the cone.
  bool allows(const Vector3& p_Scene, const Vector3& tangent, double tol_m = 1e-9) const;
};

/// A loaded 3-D steering scene.
struct Scene3d {
  std::string name;
  std::string description;
  std::string source;  ///< the file it came from
  NeedleParams3 needle;
  NoiseParams3 noise;                   ///< the default sigma (the bench's 1x)
  double step_length_m = 5e-3;          ///< insertion between two tip images (5.3's delta) [m]
  double collision_tolerance_m = 5e-5;  ///< CollisionWorld3 tolerance [m]
  std::string tissue_file;
  /// What the mesh loader repaired, one line per mesh file ("tissue.mesh liver.obj: repaired:
  /// 42 unreferenced vertices removed"); empty when every mesh was clean.
  std::vector<std::string> mesh_repairs;
  Mesh3 tissue;
  std::vector<ObstacleMesh3> obstacles;
  std::vector<std::string> obstacle_files;
  Target3 target;
  EntryRegion3 entry;

  /// The collision world of the tissue and obstacles.
  CollisionWorld3 collisionWorld() const;
};

/// Loads and validates a `steering_3d` scene file; mesh paths are relative to its directory.
/// Throws scene::SceneError.
Scene3d loadScene3d(const std::string& path);
/// Parses YAML text; `source` names it in errors and mesh paths resolve against base_dir.
Scene3d parseScene3d(const std::string& yaml_text, const std::string& source,
                     const std::string& base_dir);

}  // namespace needle_guidance::needle_model
