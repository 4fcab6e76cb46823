// Scenes: the anatomy, materials, needle, targets, obstacles, imaging and active models of one
// procedure. Everything here is SI: the loader converts file units.
#pragma once

#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/geometry/triangle_mesh.h"

namespace needle_guidance::scene {

using geometry::Point2;
using geometry::Polygon;
using geometry::Segment;

/// Linear elastic tissue (dissertation 2.2.2, 2.3.2).
struct Material {
  std::string name;
  double young_modulus_Pa = 0.0;      ///< E > 0 [Pa]
  double poisson_ratio = 0.0;         ///< -1 < nu < 0.5
  double density_kg_m3 = 1000.0;      ///< > 0 [kg/m^3]
  double rayleigh_alpha_per_s = 0.0;  ///< mass-proportional damping [1/s], >= 0
  double rayleigh_beta_s = 0.0;       ///< stiffness-proportional damping [s], >= 0
};

/// A segmented tissue region (polygon in frame `scene`) made of a named material.
struct Region {
  std::string name;
  std::string material;
  Polygon polygon;     ///< counter-clockwise after loading [m]
  bool rigid = false;  ///< bone: its nodes are fixed (2.3.2)
};

enum class BoundaryCondition { kFree, kFixed };

/// "free" | "fixed", as written in scene files.
std::string toString(BoundaryCondition condition);

/// Outer-boundary nodes lying on `segment` get `condition`; all other outer nodes are free.
struct BoundarySegment {
  std::string name;
  Segment segment;  ///< [m]
  BoundaryCondition condition = BoundaryCondition::kFixed;
};

/// The needle and its tissue interaction. Insertion is along +x of frame `scene`; the tip is at
/// x = depth_m, so the entry face of a tissue scene is the line x = 0.
struct Needle {
  double min_height_m = 0.0;             ///< lowest insertion height (y) allowed [m]
  double max_height_m = 0.0;             ///< highest insertion height allowed [m]
  double max_depth_m = 0.0;              ///< deepest tip x allowed [m]
  double insertion_velocity_m_s = 0.01;  ///< default insertion speed [m/s]
  double cutting_force_N = 0.0;          ///< force to cut cut_length_m of tissue (2.3.4) [N]
  double cut_length_m = 0.0;             ///< b of 2.3.4 [m]
  /// Slip force f_smax per unit length of shaft (2.3.5); each shaft node gets it times its
  /// share of the shaft, so the total does not depend on the mesh [N/m].
  double static_friction_N_per_m = 0.0;
  double kinetic_friction_N_per_m = 0.0;  ///< dissipative force per unit length of shaft [N/m]
  double stick_velocity_m_s = 0.0;        ///< v_s: relative speed below which a node sticks [m/s]
  double radius_of_curvature_m = 0.0;     ///< bevel-tip arc radius; 0 for a rigid needle (5.3) [m]
  /// Needle diameter [m]; the tip pushes the tissue across it (0 = a point tip, as in 2.3.4).
  double diameter_m = 0.0;
  /// A seed within this of its target counts as placed (rigid seed implant) [m].
  double placement_tolerance_m = 1e-4;
  /// Embedded track: the tip cuts the tissue now in front of it (`track: follow_tissue`)
  /// instead of the tissue at rest on its line (`rest_line`); fem::EmbeddedNeedle.
  bool follow_tissue = false;
};

/// A point to reach, with the radius that counts as reached [m].
struct Target {
  std::string name;
  Point2 position = Point2::Zero();  ///< [m]
  double radius_m = 0.0;             ///< >= 0 [m]
};

/// An obstacle the needle must avoid, expanded by clearance_m (Minkowski sum, 5.3).
struct Obstacle {
  std::string name;
  Polygon polygon;           ///< as given, counter-clockwise [m]
  double clearance_m = 0.0;  ///< >= 0 [m]
};

/// Simulated imaging of the slice.
struct Imaging {
  std::string modality = "ultrasound";  ///< "ultrasound" | "fluoroscopy"
  double pixel_size_m = 2e-4;           ///< > 0 [m]
  double frame_rate_hz = 30.0;          ///< > 0 [Hz]
  double noise_std = 0.0;               ///< Gaussian noise, fraction of full intensity, >= 0
  double blur_sigma_m = 0.0;            ///< Gaussian blur, >= 0 [m]
  double drop_probability = 0.0;        ///< in [0, 1)
  std::string reference_image;          ///< optional image file, resolved to an absolute path
};

enum class TissueModel { kNone, kQuasiStatic, kNewmark, kExplicit };

/// "none" | "quasi_static" | "newmark" | "explicit", as written in scene files.
std::string toString(TissueModel model);

/// Which models the scene uses ("model only what a scene needs").
struct Models {
  TissueModel tissue = TissueModel::kNone;
  bool corotational = false;
  /// Element formulation (models.element): false = linear triangles ("linear"), true = averaged
  /// nodal volumetric strain ("averaged_volumetric"), the remedy for locking as nu -> 0.5.
  bool averaged_volumetric = false;
  bool steering = false;
};

/// Element size control for the tissue mesh [m].
struct MeshSpec {
  double max_edge_m = 0.004;
  double min_edge_m = 0.001;
  double grading_length_m = 0.01;
  double min_angle_deg = 25.0;
  bool refine_targets = true;  ///< grade the mesh towards the targets
};

/// Steerable-needle MDP discretisation and motion uncertainty (dissertation 5.3–5.4).
struct Steering {
  double grid_spacing_m = 0.001;    ///< Delta [m]
  int orientations = 40;            ///< N_c, a multiple of 4
  int orientation_subdivision = 1;  ///< s: orientation tracked in alpha / s (1 = 5.4.2)
  double sigma_insert_rad = 0.0;    ///< sigma_i [rad]
  double sigma_flip_rad = 0.0;      ///< sigma_r [rad]
  double start_x_m = 0.0;           ///< feasible start states lie on the line x = start_x_m [m]
  /// How a transition's end point enters the MDP: "rounded" (5.4.2: rounded control-circle
  /// points) or "interpolated" (exact arc end, probability split bilinearly between the four
  /// neighbouring grid points; deflection bins matched to sigma's variance).
  std::string transition_model = "rounded";
  /// Mean |P_s error| the scene needs at its entry line: steering_policy refines the
  /// grid from grid_spacing_m (the coarsest) until its own error estimate meets it. 0 = use
  /// grid_spacing_m as given, with no estimate.
  double ps_tolerance = 0.01;
};

/// A validated scene in SI units.
struct Scene {
  std::string name;
  std::string description;
  std::string source;                     ///< file path or "<embedded:NAME>"
  Point2 workspace_min = Point2::Zero();  ///< workspace rectangle [m]
  Point2 workspace_max = Point2::Zero();
  std::string background_material;  ///< material of the workspace outside all regions ("" = none)
  /// Out-of-plane thickness of the 2-D tissue slice: needle forces act on this much tissue
  /// (plane strain per unit thickness x thickness) [m], > 0.
  double thickness_m = 0.01;
  Models models;
  std::vector<Material> materials;
  std::vector<Region> regions;
  std::vector<BoundarySegment> boundary;
  Needle needle;
  std::vector<Target> targets;
  std::vector<Obstacle> obstacles;
  Imaging imaging;
  MeshSpec mesh;
  std::optional<Steering> steering;  ///< present when models.steering

  /// The material with this name; throws std::out_of_range if absent.
  const Material& material(const std::string& name) const;
  /// The regions as meshing input (name and polygon, in order: mesh region index i + 1).
  std::vector<geometry::MeshRegion> meshRegions() const;
  /// The workspace rectangle as a counter-clockwise polygon [m].
  Polygon workspacePolygon() const;
  /// True if p lies in tissue: inside the workspace (tissue scenes) [m].
  bool inWorkspace(const Point2& p) const;

  /// True if the scene has a FEM tissue model (models.tissue != none).
  bool hasTissue() const { return models.tissue != TissueModel::kNone; }
  /// The target with this name; throws std::out_of_range if absent.
  const Target& target(const std::string& name) const;
  /// Condition of an outer-boundary point p [m]: kFixed if p lies within tol_m of any fixed
  /// boundary segment (fixed wins where segments meet, e.g. at corners), else kFree.
  BoundaryCondition boundaryConditionAt(const Point2& p, double tol_m = 1e-9) const;
};

/// A scene file that cannot be used. what() is one line:
/// "FILE: key 'KEY' value 'VALUE': REASON".
class SceneError : public std::invalid_argument {
public:
  SceneError(const std::string& file, const std::string& key, const std::string& value,
             const std::string& reason);
  const std::string& file() const { return file_; }
  const std::string& key() const { return key_; }
  const std::string& value() const { return value_; }
  const std::string& reason() const { return reason_; }

private:
  std::string file_, key_, value_, reason_;
};

/// Loads and validates a scene file; throws SceneError (also for a missing or unreadable file).
Scene loadScene(const std::string& path);
/// Parses and validates YAML text; `source` names it in errors. Relative paths in the text
/// (imaging.reference_image) resolve against source's directory, or against the working
/// directory when source is not a path (it starts with '<', e.g. "<embedded:NAME>").
/// Throws SceneError.
Scene parseScene(const std::string& yaml_text, const std::string& source);
/// An embedded default scene by name ("prostate_sagittal", "steering_workspace"); throws
/// std::invalid_argument for an unknown name.
Scene defaultScene(const std::string& name);
/// Names of the embedded scenes.
std::vector<std::string> defaultSceneNames();
/// The kind of planar scenes: `scene.kind` absent or "planar".
inline constexpr const char* kPlanar = "planar";
/// The `scene.kind` of the file `spec` ("planar" when absent; the embedded scenes are planar), so
/// that one scene parameter can be dispatched to the reader of its kind ("steering_3d":
/// needle_model::loadScene3d). Throws SceneError for a missing or unreadable file, an unknown
/// embedded name or a kind that is not a name; the kind itself is not validated here.
std::string sceneKind(const std::string& spec);
/// Loads `spec`: a path to a YAML file, or the name of an embedded scene. An existing file wins
/// over an embedded name. Throws SceneError if it is neither.
Scene loadSceneSpec(const std::string& spec);

}  // namespace needle_guidance::scene
