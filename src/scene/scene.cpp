// Scene loading and validation. The file format is documented at the top
// of config/scenes/prostate_sagittal.yaml and in docs/scenes.md.
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/package_paths.h"

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <utility>

#include "needle_guidance/format.h"
#include "needle_guidance/scene/embedded_scenes.h"
#include "needle_guidance/scene/interaction_preset.h"
#include "needle_guidance/scene/yaml_reader.h"

namespace needle_guidance::scene {
namespace {

namespace fs = std::filesystem;
using detail::Dimension;
using detail::formatIn;
using detail::MapReader;
using detail::PointList;
using detail::PointValue;
using detail::Quantity;
using detail::Unit;

// Scene coordinates are written to ~0.01 mm; 1 nm absorbs unit-conversion round-off only.
constexpr double kGeometryTol_m = 1e-9;
// Collinearity test for polygons, relative to their bounding-box size.
constexpr double kRelativeCollinearTol = 1e-9;
// Quality bound that geometry::meshDomain accepts.
constexpr double kMaxMinAngle_deg = 30.0;
constexpr double kRadToDeg = 57.29577951308232;
constexpr const char* kEmbeddedPrefix = "<embedded:";

const std::vector<std::string> kTissueModels = {"none", "quasi_static", "newmark", "explicit"};
const std::vector<std::string> kConditions = {"fixed", "free"};
const std::vector<std::string> kModalities = {"ultrasound", "fluoroscopy"};

TissueModel tissueModelFromString(const std::string& text) {
  if (text == "quasi_static") {
    return TissueModel::kQuasiStatic;
  }
  if (text == "newmark") {
    return TissueModel::kNewmark;
  }
  if (text == "explicit") {
    return TissueModel::kExplicit;
  }
  return TissueModel::kNone;
}

/// "[x, y]" in the unit the file used.
std::string pointText(const Point2& p_si, const Unit& unit) {
  std::ostringstream out;
  out << '[' << p_si.x() / unit.to_si << ", " << p_si.y() / unit.to_si << ']';
  return out.str();
}

std::string indexed(const std::string& key, std::size_t i) {
  return key + "[" + std::to_string(i) + "]";
}

/// A preset's needle keys: a number under base + one of dim's suffixes, >= 0 (> 0 when
/// `positive`), or 0 when absent.
double presetValue(MapReader& keys, const std::string& base, const Dimension& dim,
                   bool positive = false) {
  const std::optional<Quantity> q = keys.optionalQuantity(base, dim);
  if (!q) {
    return 0.0;
  }
  if (q->si < 0.0 || (positive && q->si == 0.0)) {
    keys.fail(q->key, q->text, positive ? "must be positive" : "must not be negative", q->line);
  }
  return q->si;
}

/// The `needle:` section of an interaction preset file; its other sections document the fit.
Needle readPresetFile(const std::string& path) {
  YAML::Node root;
  try {
    root = YAML::LoadFile(path);
  } catch (const YAML::Exception& e) {
    throw SceneError(path, "", "", "cannot read the interaction preset: " + e.msg);
  }
  MapReader top(root, "", path);
  MapReader keys = top.requiredMap("needle");
  Needle preset;
  preset.cutting_force_N = presetValue(keys, "cutting_force", detail::kForce);
  preset.cut_length_m = presetValue(keys, "cut_length", detail::kLength, true);
  preset.static_friction_N_per_m = presetValue(keys, "static_friction", detail::kForcePerLength);
  preset.kinetic_friction_N_per_m = presetValue(keys, "kinetic_friction", detail::kForcePerLength);
  preset.stick_velocity_m_s = presetValue(keys, "stick_velocity", detail::kVelocity);
  preset.diameter_m = presetValue(keys, "diameter", detail::kLength);
  keys.finish();
  if (preset.kinetic_friction_N_per_m > preset.static_friction_N_per_m) {
    throw SceneError(path, "needle.kinetic_friction", formatNumber(preset.kinetic_friction_N_per_m),
                     "kinetic friction exceeds static friction (2.3.5)");
  }
  return preset;
}

/// Parses one document into a Scene, validating as it goes, then cross-checks the parts.
class SceneParser {
public:
  SceneParser(std::string source, fs::path base_dir)
      : source_(std::move(source)), base_dir_(std::move(base_dir)) {}

  Scene parse(const YAML::Node& root) {
    MapReader top(root, "", source_);
    // Collect the sections first so that a misspelt section is reported as unknown.
    std::optional<MapReader> header = top.optionalMap("scene");
    std::optional<MapReader> workspace = top.optionalMap("workspace");
    std::optional<MapReader> models = top.optionalMap("models");
    std::vector<MapReader> materials = top.optionalList("materials");
    std::vector<MapReader> regions = top.optionalList("regions");
    std::vector<MapReader> boundary = top.optionalList("boundary");
    std::optional<MapReader> needle = top.optionalMap("needle");
    std::vector<MapReader> targets = top.optionalList("targets");
    std::vector<MapReader> obstacles = top.optionalList("obstacles");
    std::optional<MapReader> imaging = top.optionalMap("imaging");
    std::optional<MapReader> mesh = top.optionalMap("mesh");
    std::optional<MapReader> steering = top.optionalMap("steering");
    top.finish();

    scene_.source = source_;
    readHeader(header ? *header : top.requiredMap("scene"));
    readWorkspace(workspace ? *workspace : top.requiredMap("workspace"));
    readModels(models ? *models : top.requiredMap("models"));
    if (steering && !scene_.models.steering) {
      fail("steering", "", "section given but models.steering is false");
    }
    if (scene_.models.steering && !steering) {
      steering = top.requiredMap("steering");
    }
    for (MapReader& item : materials) {
      readMaterial(item);
    }
    for (MapReader& item : regions) {
      readRegion(item);
    }
    for (MapReader& item : boundary) {
      readBoundary(item);
    }
    readNeedle(needle ? *needle : top.requiredMap("needle"));
    for (MapReader& item : targets) {
      readTarget(item);
    }
    for (MapReader& item : obstacles) {
      readObstacle(item);
    }
    if (imaging) {
      readImaging(*imaging);
    }
    if (mesh) {
      readMesh(*mesh);
    }
    if (steering) {
      readSteering(*steering);
    }

    checkMaterialReferences();
    checkRegionOverlaps();
    checkTissueCoverage();
    checkTargets();
    return std::move(scene_);
  }

private:
  /// Where a list item came from, for checks that run after reading.
  struct Origin {
    std::string path;      ///< e.g. "regions[1]"
    std::string name_key;  ///< e.g. "regions[1].name"
    PointList polygon;     ///< regions and obstacles
    PointValue position;   ///< targets
    Quantity material;     ///< regions: the material reference
  };

  [[noreturn]] void fail(const std::string& key, const std::string& value,
                         const std::string& reason, int line = -1) const {
    throw SceneError(source_, key, value,
                     line >= 0 ? reason + " (line " + std::to_string(line) + ")" : reason);
  }
  [[noreturn]] void fail(const Quantity& q, const std::string& reason) const {
    fail(q.key, q.text, reason, q.line);
  }

  void requirePositive(const Quantity& q) const {
    if (!(q.si > 0.0)) {
      fail(q, "must be positive");
    }
  }
  void requireNonNegative(const Quantity& q) const {
    if (q.si < 0.0) {
      fail(q, "must not be negative");
    }
  }
  double positive(MapReader& m, const std::string& base, const Dimension& dim) {
    const Quantity q = m.requiredQuantity(base, dim);
    requirePositive(q);
    return q.si;
  }
  double positiveOr(MapReader& m, const std::string& base, const Dimension& dim, double fallback) {
    const std::optional<Quantity> q = m.optionalQuantity(base, dim);
    if (!q) {
      return fallback;
    }
    requirePositive(*q);
    return q->si;
  }
  double nonNegativeOr(MapReader& m, const std::string& base, const Dimension& dim,
                       double fallback) {
    const std::optional<Quantity> q = m.optionalQuantity(base, dim);
    if (!q) {
      return fallback;
    }
    requireNonNegative(*q);
    return q->si;
  }

  /// A non-empty name, unique within its list (`names` maps name -> key path).
  std::string readName(MapReader& m, std::map<std::string, std::string>& names) {
    std::string name = m.requiredString("name");
    const std::string key = m.keyPath("name");
    const int line = m.lineOfKey("name");
    if (name.empty()) {
      fail(key, name, "name must not be empty", line);
    }
    const auto [it, inserted] = names.emplace(name, key);
    if (!inserted) {
      fail(key, name, "duplicate name; already used by " + it->second, line);
    }
    return name;
  }

  bool insideWorkspace(const Point2& p, double tol_m = kGeometryTol_m) const {
    return p.x() >= scene_.workspace_min.x() - tol_m && p.x() <= scene_.workspace_max.x() + tol_m &&
           p.y() >= scene_.workspace_min.y() - tol_m && p.y() <= scene_.workspace_max.y() + tol_m;
  }
  std::string workspaceText(const Unit& unit) const {
    return formatIn(scene_.workspace_min, unit) + " to " + formatIn(scene_.workspace_max, unit);
  }

  /// A simple polygon with at least 3 vertices, made counter-clockwise. A closing vertex equal
  /// to the first is accepted and dropped.
  Polygon validPolygon(const PointList& list, const std::string& owner) const {
    std::vector<Point2> vertices = list.points;
    if (vertices.size() >= 2 && vertices.front() == vertices.back()) {
      vertices.pop_back();
    }
    if (vertices.size() < 3) {
      fail(list.key, list.text,
           owner + ": a polygon needs at least 3 distinct vertices, got " +
               std::to_string(vertices.size()),
           list.line);
    }
    const std::size_t n = vertices.size();
    for (std::size_t i = 0; i < n; ++i) {
      const std::size_t j = (i + 1) % n;
      if ((vertices[j] - vertices[i]).norm() <= kGeometryTol_m) {
        fail(indexed(list.key, j), pointText(vertices[j], list.unit),
             owner + ": vertex " + std::to_string(j) + " repeats vertex " + std::to_string(i) +
                 " (zero-length edge)",
             list.line);
      }
    }
    // All vertices on one line. (A zero signed area alone could be a symmetric bow-tie, which
    // the self-intersection test names better.)
    const Polygon polygon(vertices);
    const double extent_m = (polygon.maxCorner() - polygon.minCorner()).maxCoeff();
    Point2 direction = Point2::Zero();
    for (const Point2& v : vertices) {
      if ((v - vertices[0]).norm() > direction.norm()) {
        direction = v - vertices[0];
      }
    }
    direction.normalize();
    double max_offset_m = 0.0;
    for (const Point2& v : vertices) {
      const Point2 d = v - vertices[0];
      max_offset_m =
          std::max(max_offset_m, std::abs(direction.x() * d.y() - direction.y() * d.x()));
    }
    if (max_offset_m <= kRelativeCollinearTol * extent_m) {
      fail(list.key, list.text, owner + ": degenerate polygon with zero area (collinear vertices)",
           list.line);
    }
    if (const std::optional<geometry::SelfIntersection> hit = polygon.selfIntersection()) {
      const auto edge_text = [n](std::size_t e) {
        return "edge " + std::to_string(e) + " (vertex " + std::to_string(e) + " to " +
               std::to_string((e + 1) % n) + ")";
      };
      fail(list.key, list.text,
           owner + ": polygon self-intersects: " + edge_text(hit->edge_a) + " and " +
               edge_text(hit->edge_b) + " meet at " + formatIn(hit->point, list.unit),
           list.line);
    }
    return polygon.counterClockwise();
  }

  // ---- sections ------------------------------------------------------------------------------

  void readHeader(MapReader m) {
    scene_.name = m.requiredString("name");
    if (scene_.name.empty()) {
      fail(m.keyPath("name"), "", "name must not be empty");
    }
    scene_.description = m.optionalString("description").value_or("");
    m.optionalChoice("kind", {kPlanar});  // other kinds are refused before parsing (parseScene)
    m.finish();
  }

  void readWorkspace(MapReader m) {
    const PointValue min = m.requiredPoint("min", detail::kLength);
    const PointValue max = m.requiredPoint("max", detail::kLength);
    scene_.background_material = m.optionalString("background_material").value_or("");
    scene_.thickness_m = positiveOr(m, "thickness", detail::kLength, scene_.thickness_m);
    background_key_ = m.keyPath("background_material");
    background_line_ = m.lineOfKey("background_material");
    m.finish();
    if (!(max.value.x() > min.value.x() && max.value.y() > min.value.y())) {
      fail(max.key, max.text,
           "workspace max must exceed min " + formatIn(min.value, max.unit) + " in x and y",
           max.line);
    }
    scene_.workspace_min = min.value;
    scene_.workspace_max = max.value;
  }

  void readModels(MapReader m) {
    scene_.models.tissue = tissueModelFromString(m.requiredChoice("tissue", kTissueModels));
    scene_.models.corotational = m.optionalBool("corotational", false);
    scene_.models.averaged_volumetric =
        m.optionalChoice("element", {"linear", "averaged_volumetric"}).value_or("linear") ==
        "averaged_volumetric";
    scene_.models.steering = m.optionalBool("steering", false);
    m.finish();
    if (scene_.models.corotational && !scene_.hasTissue()) {
      fail(m.keyPath("corotational"), "true", "corotational needs a tissue model (tissue is none)",
           m.lineOfKey("corotational"));
    }
  }

  void readMaterial(MapReader& m) {
    Material material;
    material.name = readName(m, material_names_);
    const Quantity young = m.requiredQuantity("young_modulus", detail::kModulus);
    requirePositive(young);
    material.young_modulus_Pa = young.si;
    const Quantity poisson = m.requiredQuantity("poisson_ratio", detail::kDimensionless);
    if (!(poisson.si > -1.0 && poisson.si < 0.5)) {
      fail(poisson, "Poisson ratio must lie in (-1, 0.5)");
    }
    material.poisson_ratio = poisson.si;
    material.density_kg_m3 = positiveOr(m, "density", detail::kDensity, material.density_kg_m3);
    material.rayleigh_alpha_per_s = nonNegativeOr(m, "rayleigh_alpha", detail::kPerTime, 0.0);
    material.rayleigh_beta_s = nonNegativeOr(m, "rayleigh_beta", detail::kTime, 0.0);
    m.finish();
    scene_.materials.push_back(material);
  }

  void readRegion(MapReader& m) {
    Region region;
    Origin origin;
    origin.path = m.path();
    origin.name_key = m.keyPath("name");
    region.name = readName(m, region_names_);
    region.material = m.requiredString("material");
    origin.material.key = m.keyPath("material");
    origin.material.text = region.material;
    origin.material.line = m.lineOfKey("material");
    origin.polygon = m.requiredPointList("polygon", detail::kLength);
    region.rigid = m.optionalBool("rigid", false);
    m.finish();
    const std::string owner = "region '" + region.name + "'";
    region.polygon = validPolygon(origin.polygon, owner);
    for (std::size_t i = 0; i < origin.polygon.points.size(); ++i) {
      const Point2& p = origin.polygon.points[i];
      if (!insideWorkspace(p)) {
        fail(indexed(origin.polygon.key, i), pointText(p, origin.polygon.unit),
             owner + ": vertex lies outside the workspace " + workspaceText(origin.polygon.unit),
             origin.polygon.line);
      }
    }
    scene_.regions.push_back(std::move(region));
    region_origins_.push_back(std::move(origin));
  }

  void readBoundary(MapReader& m) {
    BoundarySegment segment;
    segment.name = readName(m, boundary_names_);
    segment.condition = m.requiredChoice("condition", kConditions) == "free"
                            ? BoundaryCondition::kFree
                            : BoundaryCondition::kFixed;
    const PointValue from = m.requiredPoint("from", detail::kLength);
    const PointValue to = m.requiredPoint("to", detail::kLength);
    m.finish();
    if ((to.value - from.value).norm() <= kGeometryTol_m) {
      fail(to.key, to.text, "boundary segment has zero length", to.line);
    }
    // A segment applies to the outer nodes of the mesh, which lie on the workspace rectangle.
    const auto sides = [this](const Point2& p) {
      const auto near = [](double a, double b) { return std::abs(a - b) <= kGeometryTol_m; };
      int mask = 0;
      if (!insideWorkspace(p)) {
        return mask;
      }
      if (near(p.x(), scene_.workspace_min.x())) {
        mask |= 1;
      }
      if (near(p.x(), scene_.workspace_max.x())) {
        mask |= 2;
      }
      if (near(p.y(), scene_.workspace_min.y())) {
        mask |= 4;
      }
      if (near(p.y(), scene_.workspace_max.y())) {
        mask |= 8;
      }
      return mask;
    };
    if ((sides(from.value) & sides(to.value)) == 0) {
      const bool from_ok = sides(from.value) != 0;
      const PointValue& bad = from_ok ? to : from;
      fail(bad.key, bad.text,
           "boundary segment '" + segment.name + "' must lie along one side of the workspace " +
               workspaceText(bad.unit),
           bad.line);
    }
    segment.segment = Segment{from.value, to.value};
    scene_.boundary.push_back(segment);
  }

  void readNeedle(MapReader m) {
    Needle& needle = scene_.needle;
    const Quantity min_height = m.requiredQuantity("min_height", detail::kLength);
    const Quantity max_height = m.requiredQuantity("max_height", detail::kLength);
    const Quantity max_depth = m.requiredQuantity("max_depth", detail::kLength);
    // A calibrated interaction preset gives the defaults; the scene's own keys override them.
    const Needle preset = readInteractionPreset(m);
    needle.insertion_velocity_m_s =
        positiveOr(m, "insertion_velocity", detail::kVelocity, needle.insertion_velocity_m_s);
    needle.cutting_force_N =
        nonNegativeOr(m, "cutting_force", detail::kForce, preset.cutting_force_N);
    const std::optional<Quantity> cut_length = m.optionalQuantity("cut_length", detail::kLength);
    needle.cut_length_m = preset.cut_length_m;
    needle.static_friction_N_per_m = nonNegativeOr(m, "static_friction", detail::kForcePerLength,
                                                   preset.static_friction_N_per_m);
    needle.kinetic_friction_N_per_m = nonNegativeOr(m, "kinetic_friction", detail::kForcePerLength,
                                                    preset.kinetic_friction_N_per_m);
    needle.stick_velocity_m_s =
        nonNegativeOr(m, "stick_velocity", detail::kVelocity, preset.stick_velocity_m_s);
    needle.diameter_m = nonNegativeOr(m, "diameter", detail::kLength, preset.diameter_m);
    needle.placement_tolerance_m =
        positiveOr(m, "placement_tolerance", detail::kLength, needle.placement_tolerance_m);
    const std::optional<Quantity> radius =
        m.optionalQuantity("radius_of_curvature", detail::kLength);
    const std::optional<std::string> track =
        m.optionalChoice("track", {"rest_line", "follow_tissue"});
    m.finish();
    needle.follow_tissue = track && *track == "follow_tissue";
    if (needle.follow_tissue && !(needle.diameter_m > 0.0)) {
      fail(m.keyPath("track"), *track,
           "a track that follows the tissue needs the tip's size: give needle.diameter > 0");
    }

    const Unit& unit = min_height.unit;
    if (min_height.si > max_height.si) {
      fail(min_height, "min_height is above max_height (" + formatIn(max_height.si, unit) + ")");
    }
    const double y_min = scene_.workspace_min.y();
    const double y_max = scene_.workspace_max.y();
    const std::string y_range =
        "the workspace height range [" + formatIn(y_min, unit) + ", " + formatIn(y_max, unit) + "]";
    if (min_height.si < y_min - kGeometryTol_m || min_height.si > y_max + kGeometryTol_m) {
      fail(min_height, "outside " + y_range);
    }
    if (max_height.si < y_min - kGeometryTol_m || max_height.si > y_max + kGeometryTol_m) {
      fail(max_height, "outside " + y_range);
    }
    if (max_depth.si <= scene_.workspace_min.x() ||
        max_depth.si > scene_.workspace_max.x() + kGeometryTol_m) {
      fail(max_depth, "must lie in the workspace depth range (" +
                          formatIn(scene_.workspace_min.x(), max_depth.unit) + ", " +
                          formatIn(scene_.workspace_max.x(), max_depth.unit) + "]");
    }
    needle.min_height_m = min_height.si;
    needle.max_height_m = max_height.si;
    needle.max_depth_m = max_depth.si;
    if (cut_length) {
      requireNonNegative(*cut_length);
      needle.cut_length_m = cut_length->si;
    }
    if (needle.cutting_force_N > 0.0 && !(needle.cut_length_m > 0.0)) {
      fail(cut_length ? cut_length->key : m.keyPath("cut_length"),
           cut_length ? cut_length->text : "",
           "a positive cutting_force needs a positive cut_length (2.3.4)");
    }
    if (needle.kinetic_friction_N_per_m > needle.static_friction_N_per_m) {
      fail(m.keyPath("kinetic_friction"), formatNumber(needle.kinetic_friction_N_per_m) + " N/m",
           "kinetic friction exceeds static friction (" +
               formatNumber(needle.static_friction_N_per_m) + " N/m) (2.3.5)",
           m.lineOfKey("kinetic_friction"));
    }
    if (radius) {
      requireNonNegative(*radius);
      needle.radius_of_curvature_m = radius->si;
    }
    if (scene_.models.steering && !(needle.radius_of_curvature_m > 0.0)) {
      fail(radius ? radius->key : m.keyPath("radius_of_curvature"), radius ? radius->text : "",
           "a steering scene needs a positive needle radius_of_curvature (5.3)");
    }
  }

  /// The needle keys of config/interaction/NAME.yaml for `interaction: NAME` (all zero without
  /// one). Refuses an unknown name, listing the presets there, and bad keys in the preset.
  Needle readInteractionPreset(MapReader& m) {
    const std::optional<std::string> name = m.optionalString("interaction");
    if (!name) {
      return Needle{};
    }
    const fs::path dir = configDir() / "interaction";
    const fs::path file = interactionPresetPath(*name);
    std::error_code error;
    if (name->empty() || name->find_first_of("/\\.") != std::string::npos ||
        !fs::is_regular_file(file, error)) {
      std::vector<std::string> known;
      for (const auto& entry : fs::directory_iterator(dir, error)) {
        if (entry.path().extension() == ".yaml") {
          known.push_back(entry.path().stem().string());
        }
      }
      std::sort(known.begin(), known.end());
      std::string list;
      for (const std::string& k : known) {
        list += (list.empty() ? "" : ", ") + k;
      }
      fail(m.keyPath("interaction"), *name,
           "unknown interaction preset (presets in " + dir.string() + ": " +
               (list.empty() ? "none" : list) + ")",
           m.lineOfKey("interaction"));
    }
    return readPresetFile(file.string());
  }

  void readTarget(MapReader& m) {
    Target target;
    Origin origin;
    origin.path = m.path();
    origin.name_key = m.keyPath("name");
    target.name = readName(m, target_names_);
    origin.position = m.requiredPoint("position", detail::kLength);
    target.position = origin.position.value;
    target.radius_m = nonNegativeOr(m, "radius", detail::kLength, 0.0);
    m.finish();
    scene_.targets.push_back(target);
    target_origins_.push_back(std::move(origin));
  }

  void readObstacle(MapReader& m) {
    Obstacle obstacle;
    obstacle.name = readName(m, obstacle_names_);
    const PointList polygon = m.requiredPointList("polygon", detail::kLength);
    obstacle.clearance_m = nonNegativeOr(m, "clearance", detail::kLength, 0.0);
    m.finish();
    // Obstacles may extend past the workspace: only their part inside it matters.
    obstacle.polygon = validPolygon(polygon, "obstacle '" + obstacle.name + "'");
    scene_.obstacles.push_back(std::move(obstacle));
  }

  void readImaging(MapReader m) {
    Imaging& imaging = scene_.imaging;
    imaging.modality = m.optionalChoice("modality", kModalities).value_or(imaging.modality);
    imaging.pixel_size_m = positiveOr(m, "pixel_size", detail::kLength, imaging.pixel_size_m);
    imaging.frame_rate_hz = positiveOr(m, "frame_rate", detail::kFrequency, imaging.frame_rate_hz);
    imaging.noise_std = nonNegativeOr(m, "noise_std", detail::kDimensionless, imaging.noise_std);
    imaging.blur_sigma_m = nonNegativeOr(m, "blur_sigma", detail::kLength, imaging.blur_sigma_m);
    if (const std::optional<Quantity> drop =
            m.optionalQuantity("drop_probability", detail::kDimensionless)) {
      if (!(drop->si >= 0.0 && drop->si < 1.0)) {
        fail(*drop, "must lie in [0, 1)");
      }
      imaging.drop_probability = drop->si;
    }
    if (const std::optional<std::string> image = m.optionalString("reference_image")) {
      const std::string key = m.keyPath("reference_image");
      if (image->empty()) {
        fail(key, "", "must not be empty (omit the key for no image)");
      }
      fs::path path(*image);
      if (path.is_relative()) {
        path = base_dir_ / path;
      }
      path = path.lexically_normal();
      std::error_code error;
      if (!fs::is_regular_file(path, error)) {
        fail(key, *image, "image file not found: " + path.string());
      }
      imaging.reference_image = path.string();
    }
    m.finish();
  }

  void readMesh(MapReader m) {
    MeshSpec& mesh = scene_.mesh;
    const std::optional<Quantity> max_edge = m.optionalQuantity("max_edge", detail::kLength);
    const std::optional<Quantity> min_edge = m.optionalQuantity("min_edge", detail::kLength);
    if (max_edge) {
      requirePositive(*max_edge);
      mesh.max_edge_m = max_edge->si;
    }
    if (min_edge) {
      requirePositive(*min_edge);
      mesh.min_edge_m = min_edge->si;
    }
    mesh.grading_length_m = positiveOr(m, "grading_length", detail::kLength, mesh.grading_length_m);
    if (const std::optional<Quantity> angle = m.optionalQuantity("min_angle", detail::kAngle)) {
      const double angle_deg = angle->si * kRadToDeg;
      if (!(angle_deg > 0.0 && angle_deg <= kMaxMinAngle_deg + 1e-9)) {
        fail(*angle, "must lie in (0, 30] deg (Delaunay refinement bound)");
      }
      mesh.min_angle_deg = angle_deg;
    }
    mesh.refine_targets = m.optionalBool("refine_targets", mesh.refine_targets);
    m.finish();
    if (mesh.min_edge_m > mesh.max_edge_m) {
      const Quantity& bad = min_edge ? *min_edge : *max_edge;
      fail(bad, "min_edge must not exceed max_edge");
    }
  }

  void readSteering(MapReader m) {
    Steering steering;
    steering.grid_spacing_m = positive(m, "grid_spacing", detail::kLength);
    steering.orientations = m.requiredInt("orientations");
    const std::string orientations_key = m.keyPath("orientations");
    const int orientations_line = m.lineOfKey("orientations");
    const Quantity sigma_insert = m.requiredQuantity("sigma_insert", detail::kAngle);
    const Quantity sigma_flip = m.requiredQuantity("sigma_flip", detail::kAngle);
    const std::optional<int> subdivision = m.optionalInt("orientation_subdivision");
    const std::string subdivision_key = m.keyPath("orientation_subdivision");
    const int subdivision_line = m.lineOfKey("orientation_subdivision");
    const std::optional<Quantity> start_x = m.optionalQuantity("start_x", detail::kLength);
    const std::optional<std::string> transition = m.optionalString("transition_model");
    const std::optional<Quantity> ps_tolerance =
        m.optionalQuantity("ps_tolerance", detail::kDimensionless);
    const std::string transition_key = m.keyPath("transition_model");
    const int transition_line = m.lineOfKey("transition_model");
    m.finish();
    if (transition) {
      if (*transition != "rounded" && *transition != "interpolated") {
        fail(transition_key, *transition, "transition_model must be rounded or interpolated",
             transition_line);
      }
      steering.transition_model = *transition;
    }
    if (steering.orientations < 4 || steering.orientations % 4 != 0) {
      fail(orientations_key, std::to_string(steering.orientations),
           "orientations N_c must be a positive multiple of 4 (5.4.2)", orientations_line);
    }
    if (subdivision) {
      if (*subdivision < 1 || *subdivision > 64) {
        fail(subdivision_key, std::to_string(*subdivision),
             "orientation_subdivision must be an integer in [1, 64]", subdivision_line);
      }
      steering.orientation_subdivision = *subdivision;
    }
    requireNonNegative(sigma_insert);
    requireNonNegative(sigma_flip);
    steering.sigma_insert_rad = sigma_insert.si;
    steering.sigma_flip_rad = sigma_flip.si;
    if (ps_tolerance) {
      if (!(ps_tolerance->si >= 0.0 && ps_tolerance->si < 1.0)) {
        fail(*ps_tolerance, "ps_tolerance must be in [0, 1) (0: the grid spacing as given)");
      }
      steering.ps_tolerance = ps_tolerance->si;
    }
    steering.start_x_m = scene_.workspace_min.x();
    if (start_x) {
      if (start_x->si < scene_.workspace_min.x() - kGeometryTol_m ||
          start_x->si >= scene_.workspace_max.x()) {
        fail(*start_x, "must lie in the workspace depth range [" +
                           formatIn(scene_.workspace_min.x(), start_x->unit) + ", " +
                           formatIn(scene_.workspace_max.x(), start_x->unit) + ")");
      }
      steering.start_x_m = start_x->si;
    }
    scene_.steering = steering;
  }

  // ---- cross-checks --------------------------------------------------------------------------

  void checkMaterialReferences() const {
    const auto known = [this](const std::string& name) { return material_names_.count(name) > 0; };
    if (!scene_.background_material.empty() && !known(scene_.background_material)) {
      fail(background_key_, scene_.background_material, "unknown material (not in materials)",
           background_line_);
    }
    for (const Origin& origin : region_origins_) {
      if (!known(origin.material.text)) {
        fail(origin.material, "unknown material (not in materials)");
      }
    }
  }

  void checkRegionOverlaps() const {
    for (std::size_t j = 0; j < scene_.regions.size(); ++j) {
      for (std::size_t i = 0; i < j; ++i) {
        if (geometry::polygonsOverlap(scene_.regions[i].polygon, scene_.regions[j].polygon)) {
          const PointList& polygon = region_origins_[j].polygon;
          fail(polygon.key, polygon.text,
               "region '" + scene_.regions[j].name + "' overlaps region '" +
                   scene_.regions[i].name + "' (" + region_origins_[i].path + ")",
               polygon.line);
        }
      }
    }
  }

  void checkTissueCoverage() const {
    if (!scene_.hasTissue() || !scene_.background_material.empty()) {
      return;
    }
    const double workspace_area_m2 = scene_.workspacePolygon().area();
    double covered_m2 = 0.0;
    for (const Region& region : scene_.regions) {
      covered_m2 += region.polygon.area();
    }
    // Regions are disjoint and inside the workspace, so the areas add up.
    if (covered_m2 < workspace_area_m2 * (1.0 - 1e-9)) {
      std::ostringstream reason;
      reason << "a tissue scene (models.tissue " << toString(scene_.models.tissue)
             << ") needs a background_material or regions covering the workspace; regions cover "
             << 100.0 * covered_m2 / workspace_area_m2 << "% of it";
      fail(background_key_, "", reason.str());
    }
  }

  void checkTargets() const {
    for (std::size_t t = 0; t < scene_.targets.size(); ++t) {
      const Target& target = scene_.targets[t];
      const PointValue& position = target_origins_[t].position;
      const std::string owner = "target '" + target.name + "'";
      if (!insideWorkspace(target.position)) {
        fail(position.key, position.text,
             owner + " lies outside the workspace " + workspaceText(position.unit), position.line);
      }
      if (scene_.hasTissue()) {
        for (const Region& region : scene_.regions) {
          if (region.rigid && region.polygon.contains(target.position)) {
            fail(position.key, position.text,
                 owner + " lies inside rigid region '" + region.name + "', not in soft tissue",
                 position.line);
          }
        }
      }
      for (const Obstacle& obstacle : scene_.obstacles) {
        if (obstacle.polygon.contains(target.position) ||
            obstacle.polygon.distanceToBoundary(target.position) <= obstacle.clearance_m) {
          fail(position.key, position.text,
               owner + " lies inside obstacle '" + obstacle.name + "' (expanded by its clearance " +
                   formatIn(obstacle.clearance_m, position.unit) + ")",
               position.line);
        }
      }
    }
  }

  std::string source_;
  fs::path base_dir_;
  Scene scene_;
  std::string background_key_ = "workspace.background_material";
  int background_line_ = -1;
  std::map<std::string, std::string> material_names_, region_names_, boundary_names_, target_names_,
      obstacle_names_;
  std::vector<Origin> region_origins_;
  std::vector<Origin> target_origins_;
};

std::string oneLine(std::string text) {
  std::replace(text.begin(), text.end(), '\n', ' ');
  std::replace(text.begin(), text.end(), '\r', ' ');
  return text;
}

}  // namespace

// ---- SceneError ------------------------------------------------------------------------------

SceneError::SceneError(const std::string& file, const std::string& key, const std::string& value,
                       const std::string& reason)
    : std::invalid_argument(oneLine(file + ": key '" + key + "' value '" + value + "': " + reason)),
      file_(file),
      key_(key),
      value_(value),
      reason_(reason) {}

// ---- Scene -----------------------------------------------------------------------------------

std::string toString(BoundaryCondition condition) {
  return condition == BoundaryCondition::kFree ? "free" : "fixed";
}

std::string toString(TissueModel model) {
  switch (model) {
    case TissueModel::kQuasiStatic:
      return "quasi_static";
    case TissueModel::kNewmark:
      return "newmark";
    case TissueModel::kExplicit:
      return "explicit";
    case TissueModel::kNone:
      break;
  }
  return "none";
}

const Material& Scene::material(const std::string& material_name) const {
  for (const Material& m : materials) {
    if (m.name == material_name) {
      return m;
    }
  }
  throw std::out_of_range("Scene::material: no material '" + material_name + "' in scene '" + name +
                          "'");
}

const Target& Scene::target(const std::string& target_name) const {
  for (const Target& t : targets) {
    if (t.name == target_name) {
      return t;
    }
  }
  throw std::out_of_range("Scene::target: no target '" + target_name + "' in scene '" + name + "'");
}

std::vector<geometry::MeshRegion> Scene::meshRegions() const {
  std::vector<geometry::MeshRegion> out;
  out.reserve(regions.size());
  for (const Region& region : regions) {
    out.push_back({region.name, region.polygon});
  }
  return out;
}

Polygon Scene::workspacePolygon() const {
  return Polygon({workspace_min, Point2(workspace_max.x(), workspace_min.y()), workspace_max,
                  Point2(workspace_min.x(), workspace_max.y())});
}

bool Scene::inWorkspace(const Point2& p) const {
  return p.x() >= workspace_min.x() && p.x() <= workspace_max.x() && p.y() >= workspace_min.y() &&
         p.y() <= workspace_max.y();
}

BoundaryCondition Scene::boundaryConditionAt(const Point2& p, double tol_m) const {
  for (const BoundarySegment& segment : boundary) {
    if (segment.condition == BoundaryCondition::kFixed &&
        geometry::pointSegmentDistance(p, segment.segment.a, segment.segment.b) <= tol_m) {
      return BoundaryCondition::kFixed;
    }
  }
  return BoundaryCondition::kFree;
}

// ---- loading ---------------------------------------------------------------------------------

Scene parseScene(const std::string& yaml_text, const std::string& source) {
  YAML::Node root;
  try {
    root = YAML::Load(yaml_text);
  } catch (const YAML::ParserException& e) {
    throw SceneError(source, "", "",
                     "YAML syntax error: " + e.msg + " (line " + std::to_string(e.mark.line + 1) +
                         ", column " + std::to_string(e.mark.column + 1) + ")");
  }
  // Relative paths in the file (imaging.reference_image) are relative to the file's directory.
  std::error_code error;
  fs::path base_dir = fs::current_path(error);
  if (source.rfind('<', 0) != 0) {
    base_dir = fs::absolute(fs::path(source), error).parent_path();
  }
  // A scene of another kind is named as such before its keys are taken for planar ones.
  if (root.IsMap() && root["scene"].IsMap() && root["scene"]["kind"].IsScalar() &&
      root["scene"]["kind"].Scalar() != kPlanar) {
    const std::string kind = root["scene"]["kind"].Scalar();
    throw SceneError(source, "scene.kind", kind,
                     "this reader takes planar scenes; a scene of kind '" + kind +
                         "' is read by its own module (check_scene reads every kind)");
  }
  try {
    return SceneParser(source, base_dir).parse(root);
  } catch (const SceneError&) {
    throw;
  } catch (const YAML::Exception& e) {
    throw SceneError(source, "", "", std::string("YAML error: ") + e.what());
  }
}

Scene loadScene(const std::string& path) {
  std::ifstream file(path, std::ios::binary);
  std::error_code error;
  const std::string absolute = fs::absolute(fs::path(path), error).string();
  if (!file) {
    throw SceneError(path, "", "",
                     "cannot open scene file '" + absolute + "': " + std::strerror(errno));
  }
  if (fs::is_directory(path, error)) {
    throw SceneError(path, "", "", "cannot open scene file '" + absolute + "': is a directory");
  }
  std::ostringstream text;
  text << file.rdbuf();
  return parseScene(text.str(), path);
}

std::vector<std::string> defaultSceneNames() {
  std::vector<std::string> names;
  for (const auto& [name, text] : embeddedSceneFiles()) {
    names.push_back(name);
  }
  return names;
}

Scene defaultScene(const std::string& name) {
  for (const auto& [file_name, text] : embeddedSceneFiles()) {
    if (file_name == name) {
      return parseScene(text, kEmbeddedPrefix + name + ">");
    }
  }
  std::string known;
  for (const std::string& n : defaultSceneNames()) {
    known += (known.empty() ? "" : ", ") + n;
  }
  throw std::invalid_argument("defaultScene: no embedded scene '" + name + "' (known: " + known +
                              ")");
}

std::string sceneKind(const std::string& spec) {
  std::error_code error;
  if (!fs::exists(spec, error)) {
    const std::vector<std::string> names = defaultSceneNames();
    if (std::find(names.begin(), names.end(), spec) != names.end()) {
      return kPlanar;  // the embedded scenes are planar
    }
    loadSceneSpec(spec);  // throws the loader's message for a missing file or unknown name
  }
  YAML::Node root;
  try {
    root = YAML::LoadFile(spec);
  } catch (const YAML::ParserException& e) {
    throw SceneError(spec, "", "",
                     "YAML syntax error: " + e.msg + " (line " + std::to_string(e.mark.line + 1) +
                         ", column " + std::to_string(e.mark.column + 1) + ")");
  } catch (const YAML::Exception& e) {
    throw SceneError(spec, "", "", std::string("cannot read: ") + e.what());
  }
  const YAML::Node kind =
      root.IsMap() && root["scene"].IsMap() ? root["scene"]["kind"] : YAML::Node();
  if (!kind.IsDefined() || kind.IsNull()) {
    return kPlanar;
  }
  if (!kind.IsScalar()) {
    throw SceneError(spec, "scene.kind", detail::nodeText(kind), "must be a name");
  }
  return kind.Scalar();
}

Scene loadSceneSpec(const std::string& spec) {
  std::error_code error;
  if (fs::exists(spec, error)) {
    return loadScene(spec);
  }
  const std::vector<std::string> names = defaultSceneNames();
  if (std::find(names.begin(), names.end(), spec) != names.end()) {
    return defaultScene(spec);
  }
  const bool looks_like_path = spec.find('/') != std::string::npos ||
                               fs::path(spec).extension() == ".yaml" ||
                               fs::path(spec).extension() == ".yml";
  if (looks_like_path) {
    return loadScene(spec);  // reports the missing file
  }
  std::string known;
  for (const std::string& n : names) {
    known += (known.empty() ? "" : ", ") + n;
  }
  throw SceneError(
      spec, "", "",
      "no such scene file and no embedded scene of that name (embedded: " + known + ")");
}

std::string interactionPresetPath(const std::string& name) {
  return (configDir() / "interaction" / (name + ".yaml")).string();
}

std::string interactionPresetFile(const std::string& name_or_path) {
  const bool is_path =
      name_or_path.find('/') != std::string::npos || fs::path(name_or_path).extension() == ".yaml";
  return is_path ? name_or_path : interactionPresetPath(name_or_path);
}

Needle loadInteractionPreset(const std::string& name_or_path) {
  const std::string path = interactionPresetFile(name_or_path);
  std::error_code error;
  if (!fs::is_regular_file(path, error)) {
    throw SceneError(path, "", name_or_path, "no such interaction preset");
  }
  return readPresetFile(path);
}

}  // namespace needle_guidance::scene
