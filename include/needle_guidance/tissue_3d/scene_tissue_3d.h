// Scene kind `tissue_3d`: a block of tissue with organ regions given as closed surface meshes
// (read with needle_model::readMesh3, the reader of the 3-D steering scenes), a material per
// region, fixed faces of the block and fixed (bone) regions, the needle and its interaction
// parameters (the `needle:` keys of the 2-D scenes), the insertion robot's workspace (a lateral
// x-y stage or the 5 mm template grid) and the seed targets. Frame scene: +x insertion (the
// perineum at x = block min), +y anterior, +z lateral. The format is in docs/tissue_3d.md.
#pragma once

#include <Eigen/Core>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/fem/linear_elasticity.h"
#include "needle_guidance/needle_model/mesh_3d.h"

namespace needle_guidance::tissue_3d {

using Vector3 = Eigen::Vector3d;

/// A region inside the block: a closed surface, its material, and whether it is held fixed
/// (bone). Later regions take precedence where regions overlap.
struct Region3 {
  std::string name;
  std::string mesh_file;  ///< as written in the scene ("" for a generated shape)
  needle_model::Mesh3 surface;
  fem::Material material;
  bool fixed = false;
};

/// Needle and needle-tissue interaction (dissertation 2.3.4-2.3.6), SI.
struct Needle3 {
  int gauge = 18;
  double diameter_m = 1.27e-3;
  double length_m = 0.2;
  double insertion_velocity_m_s = 5e-3;
  double cutting_force_N = 0.5;            ///< tip force at which the tip cuts (2.3.4)
  double static_friction_N_per_m = 30.0;   ///< per unit length of shaft (2.3.5)
  double kinetic_friction_N_per_m = 20.0;  ///< per unit length of shaft
  double stick_velocity_m_s = 5e-4;        ///< slipping shaft sticks again below this
  double step_s = 0.1;                     ///< simulation step (tissue_sim period)
  double track_spacing_m = 1e-3;           ///< spacing of the shaft's tissue points
  /// Cut track (`needle.track`): true = follow_tissue (default: the tip cuts the tissue now in
  /// front of it; fem::EmbeddedNeedle), false = rest_line (the tissue at rest on its line).
  bool follow_tissue = true;
  /// The needle's forces on the tissue (`needle.load`): false = point (at its tissue points),
  /// true = cross_section (spread over a disc of the needle's radius about each;
  /// fem::EmbeddedNeedleParams::section_load).
  bool section_load = false;
};

/// The insertion robot's reach. Stage: any lateral (y, z) in the box; template: only the
/// grid holes origin + (i, j) * spacing. Depth: tip x up to max_tip_x_m.
struct Workspace3 {
  bool use_template = false;
  double y_min_m = 0.0, y_max_m = 0.0, z_min_m = 0.0, z_max_m = 0.0;  ///< stage range
  Eigen::Vector2d template_origin_m = Eigen::Vector2d::Zero();        ///< hole (0, 0): (y, z)
  double template_spacing_m = 5e-3;
  int template_columns = 13;  ///< along z
  int template_rows = 13;     ///< along y
  double max_tip_x_m = 0.0;   ///< deepest tip position [m]
  /// Lateral positions the robot can reach: inside the stage, or a hole within 1 um.
  bool reaches(const Eigen::Vector2d& lateral_m) const;
  /// The nearest template hole (template mode) or the clamped stage position.
  Eigen::Vector2d nearest(const Eigen::Vector2d& lateral_m) const;
  /// Template mode: the (row, column) of the nearest hole; hole(row, column) its (y, z).
  Eigen::Vector2i holeIndex(const Eigen::Vector2d& lateral_m) const;
  Eigen::Vector2d hole(int row, int column) const;
};

/// Mesh sizes: tetrahedra of size_m, graded to fine_size_m within fine_radius_m of the
/// needle lines through the targets and of the targets.
struct MeshSizing3 {
  double size_m = 8e-3;
  double fine_size_m = 2e-3;
  double fine_radius_m = 6e-3;
  double facet_distance_m = 5e-4;  ///< surface approximation error bound
};

struct Target3 {
  std::string name;
  Vector3 position_m = Vector3::Zero();
};

struct TissueScene3d {
  std::string name, description, source;
  Vector3 block_min_m = Vector3::Zero(), block_max_m = Vector3::Zero();
  fem::Material block_material;  ///< the surrounding tissue
  /// Fixed faces of the block: "x_min", "x_max", "y_min", "y_max", "z_min", "z_max".
  std::vector<std::string> fixed_faces;
  std::vector<Region3> regions;
  Needle3 needle;
  Workspace3 workspace;
  MeshSizing3 sizing;
  std::vector<Target3> targets;
  /// `tissue.model: corotational`: elements follow their rotation (warped stiffness); the
  /// default `linear` is the small-rotation model.
  bool corotational = false;

  /// Material index per region for the FEM: 0 = block, 1 + r = regions[r].
  std::vector<fem::Material> materialTable() const;
};

/// Which region a point lies in, through one AABB tree per region surface.
class RegionLocator3 {
public:
  explicit RegionLocator3(const TissueScene3d& scene);
  /// The last listed region containing p, -1 in the block outside every region, -2 outside
  /// the block.
  int regionAt(const Vector3& p) const;
  /// Unsigned distance from p to the surface of region r [m].
  double distanceToRegion(int r, const Vector3& p) const;

private:
  Vector3 min_, max_;
  std::vector<needle_model::MeshDistance> regions_;
};

/// Loads and validates a `tissue_3d` scene; mesh paths are relative to the file's directory.
/// Throws scene::SceneError naming the file, the key and the value.
TissueScene3d loadTissueScene3d(const std::string& path);
TissueScene3d parseTissueScene3d(const std::string& yaml_text, const std::string& source,
                                 const std::string& base_dir);
/// True if the YAML file says `scene: {kind: tissue_3d}` (check_scene dispatches on it).
bool isTissueScene3dFile(const std::string& path);

}  // namespace needle_guidance::tissue_3d
