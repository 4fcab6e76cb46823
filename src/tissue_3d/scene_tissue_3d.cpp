// Loading and validation of `tissue_3d` scenes (scene_tissue_3d.h).
#include "needle_guidance/tissue_3d/scene_tissue_3d.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "needle_guidance/scene/interaction_preset.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/scene/yaml_reader.h"

namespace needle_guidance::tissue_3d {
namespace {

namespace fs = std::filesystem;
using scene::SceneError;
using scene::detail::MapReader;
using scene::detail::Quantity;
namespace units = scene::detail;

const std::vector<std::string> kFaces = {"x_min", "x_max", "y_min", "y_max", "z_min", "z_max"};
constexpr double kHoleTol_m = 1e-6;  // a lateral position within 1 um of a hole is that hole

std::string mm(double m) {
  std::ostringstream out;
  out << m * 1e3 << " mm";
  return out.str();
}

class Parser {
public:
  Parser(std::string source, fs::path base_dir)
      : source_(std::move(source)), base_dir_(std::move(base_dir)) {}

  TissueScene3d parse(const YAML::Node& root) {
    MapReader top(root, "", source_);
    MapReader header = top.requiredMap("scene");
    MapReader block = top.requiredMap("block");
    std::vector<MapReader> regions = top.optionalList("regions");
    MapReader needle = top.requiredMap("needle");
    MapReader workspace = top.requiredMap("workspace");
    std::optional<MapReader> mesh = top.optionalMap("mesh");
    std::optional<MapReader> tissue = top.optionalMap("tissue");
    std::vector<MapReader> targets = top.optionalList("targets");
    top.finish();
    s_.source = source_;
    readHeader(header);
    readBlock(block);
    for (MapReader& r : regions) {
      readRegion(r);
    }
    readNeedle(needle);
    readWorkspace(workspace);
    if (mesh) {
      readSizing(*mesh);
    }
    if (tissue) {
      s_.corotational =
          tissue->optionalChoice("model", {"linear", "corotational"}).value_or("linear") ==
          "corotational";
      tissue->finish();
    }
    for (MapReader& t : targets) {
      readTarget(t);
    }
    return std::move(s_);
  }

private:
  void readHeader(MapReader& m) {
    s_.name = m.requiredString("name");
    m.requiredChoice("kind", {"tissue_3d"});
    s_.description = m.optionalString("description").value_or("");
    m.finish();
  }

  fem::Material readMaterial(MapReader m) {
    fem::Material mat;
    const Quantity e = m.requiredQuantity("young_modulus", units::kModulus);
    const Quantity nu = m.requiredQuantity("poisson_ratio", units::kDimensionless);
    m.finish();
    if (!(e.si > 0.0)) {
      m.fail(e.key, e.text, "must be > 0");
    }
    if (!(nu.si > -1.0 && nu.si < 0.5)) {
      m.fail(nu.key, nu.text, "must be in (-1, 0.5)");
    }
    mat.young_modulus_Pa = e.si;
    mat.poisson_ratio = nu.si;
    return mat;
  }

  void readBlock(MapReader& m) {
    std::string min_key, max_key;
    s_.block_min_m = m.requiredPoint3("min", units::kLength, &min_key);
    s_.block_max_m = m.requiredPoint3("max", units::kLength, &max_key);
    if (!((s_.block_max_m - s_.block_min_m).array() > 0.0).all()) {
      m.fail(max_key, "", "every coordinate must exceed block.min's");
    }
    s_.block_material = readMaterial(m.requiredMap("material"));
    const std::string faces = m.optionalString("fixed_faces").value_or("");
    std::istringstream words(faces);
    for (std::string w; words >> w;) {
      if (w.back() == ',') {
        w.pop_back();
      }
      if (std::find(kFaces.begin(), kFaces.end(), w) == kFaces.end()) {
        m.fail(m.keyPath("fixed_faces"), faces,
               "unknown face '" + w + "' (x_min x_max y_min y_max z_min z_max)");
      }
      s_.fixed_faces.push_back(w);
    }
    m.finish();
  }

  void readRegion(MapReader& m) {
    Region3 r;
    r.name = m.requiredString("name");
    const std::optional<std::string> file = m.optionalString("mesh");
    std::optional<MapReader> ellipsoid = m.optionalMap("ellipsoid");
    const std::string units_name = m.optionalChoice("units", {"m", "cm", "mm"}).value_or("m");
    r.fixed = m.optionalBool("fixed", false);
    std::optional<MapReader> material = m.optionalMap("material");
    const std::string where = m.path();
    if (file.has_value() == ellipsoid.has_value()) {
      m.fail(where, r.name, "give exactly one of 'mesh' (a closed surface file) or 'ellipsoid'");
    }
    if (file) {
      const double scale = units_name == "mm" ? 1e-3 : units_name == "cm" ? 1e-2 : 1.0;
      r.mesh_file = *file;
      const fs::path path = fs::path(*file).is_absolute() ? fs::path(*file) : base_dir_ / *file;
      try {
        r.surface = needle_model::readMesh3(path.string(), scale);
      } catch (const std::exception& e) {
        m.fail(m.keyPath("mesh"), *file, e.what());
      }
    } else {
      std::string key;
      const Vector3 c = ellipsoid->requiredPoint3("center", units::kLength);
      const Vector3 a = ellipsoid->requiredPoint3("semi_axes", units::kLength, &key);
      ellipsoid->finish();
      if (!(a.array() > 0.0).all()) {
        m.fail(key, "", "every semi-axis must be > 0");
      }
      r.surface = needle_model::ellipsoidMesh(c, a, 16, 24);
    }
    if (material) {
      r.material = readMaterial(*material);
    } else if (!r.fixed) {
      m.fail(m.keyPath("material"), "", "missing (a region that is not fixed needs a material)");
    } else {
      r.material = s_.block_material;  // a fixed region's nodes never move
    }
    m.finish();
    for (const Vector3& v : r.surface.vertices) {
      if (((v - s_.block_min_m).array() < 0.0).any() ||
          ((s_.block_max_m - v).array() < 0.0).any()) {
        m.fail(where, r.name,
               "the surface leaves the block (vertex at [" + mm(v.x()) + ", " + mm(v.y()) + ", " +
                   mm(v.z()) + "])");
      }
    }
    s_.regions.push_back(std::move(r));
  }

  void readNeedle(MapReader& m) {
    Needle3& n = s_.needle;
    n.gauge = m.optionalInt("gauge").value_or(n.gauge);
    auto positive = [&](const char* base, const units::Dimension& dim, double fallback) {
      const std::optional<Quantity> q = m.optionalQuantity(base, dim);
      if (q && !(q->si > 0.0)) {
        m.fail(q->key, q->text, "must be > 0");
      }
      return q ? q->si : fallback;
    };
    auto nonNegative = [&](const char* base, const units::Dimension& dim, double fallback) {
      const std::optional<Quantity> q = m.optionalQuantity(base, dim);
      if (q && !(q->si >= 0.0)) {
        m.fail(q->key, q->text, "must be >= 0");
      }
      return q ? q->si : fallback;
    };
    // A calibrated interaction preset (the planar scenes' reader) gives the defaults; the
    // scene's own keys override them. Its cut_length has no use here: the 3-D tip cuts
    // continuously.
    if (const std::optional<std::string> preset = m.optionalString("interaction")) {
      scene::Needle p;
      try {
        p = scene::loadInteractionPreset(*preset);
      } catch (const scene::SceneError& e) {
        m.fail(m.keyPath("interaction"), *preset, e.what());
      }
      n.cutting_force_N = p.cutting_force_N > 0.0 ? p.cutting_force_N : n.cutting_force_N;
      n.static_friction_N_per_m = p.static_friction_N_per_m;
      n.kinetic_friction_N_per_m = p.kinetic_friction_N_per_m;
      n.stick_velocity_m_s = p.stick_velocity_m_s;
      n.diameter_m = p.diameter_m > 0.0 ? p.diameter_m : n.diameter_m;
    }
    n.diameter_m = positive("diameter", units::kLength, n.diameter_m);
    n.length_m = positive("length", units::kLength, n.length_m);
    n.insertion_velocity_m_s =
        positive("insertion_velocity", units::kVelocity, n.insertion_velocity_m_s);
    n.cutting_force_N = positive("cutting_force", units::kForce, n.cutting_force_N);
    n.static_friction_N_per_m =
        nonNegative("static_friction", units::kForcePerLength, n.static_friction_N_per_m);
    n.kinetic_friction_N_per_m =
        nonNegative("kinetic_friction", units::kForcePerLength, n.kinetic_friction_N_per_m);
    n.stick_velocity_m_s = nonNegative("stick_velocity", units::kVelocity, n.stick_velocity_m_s);
    n.step_s = positive("step", units::kTime, n.step_s);
    n.track_spacing_m = positive("track_spacing", units::kLength, n.track_spacing_m);
    n.follow_tissue =
        m.optionalChoice("track", {"rest_line", "follow_tissue"}).value_or("follow_tissue") ==
        "follow_tissue";
    n.section_load =
        m.optionalChoice("load", {"point", "cross_section"}).value_or("point") == "cross_section";
    if (n.gauge < 10 || n.gauge > 30) {
      m.fail(m.keyPath("gauge"), std::to_string(n.gauge), "must be in [10, 30]");
    }
    if (n.kinetic_friction_N_per_m > n.static_friction_N_per_m) {
      m.fail(m.keyPath("kinetic_friction"), "",
             "kinetic friction exceeds static friction (2.3.5 needs f_k <= f_s)");
    }
    m.finish();
  }

  void readWorkspace(MapReader& m) {
    Workspace3& w = s_.workspace;
    std::optional<MapReader> stage = m.optionalMap("stage");
    std::optional<MapReader> grid = m.optionalMap("template");
    const Quantity depth = m.requiredQuantity("max_tip_x", units::kLength);
    m.finish();
    if (stage.has_value() == grid.has_value()) {
      m.fail(m.path(), "", "give exactly one of 'stage' or 'template'");
    }
    if (stage) {
      w.y_min_m = stage->requiredQuantity("y_min", units::kLength).si;
      w.y_max_m = stage->requiredQuantity("y_max", units::kLength).si;
      w.z_min_m = stage->requiredQuantity("z_min", units::kLength).si;
      w.z_max_m = stage->requiredQuantity("z_max", units::kLength).si;
      stage->finish();
      if (!(w.y_min_m < w.y_max_m && w.z_min_m < w.z_max_m)) {
        stage->fail(stage->path(), "", "needs y_min < y_max and z_min < z_max");
      }
    } else {
      w.use_template = true;
      const scene::detail::PointValue o = grid->requiredPoint("origin", units::kLength);
      w.template_origin_m = o.value;
      const Quantity spacing = grid->requiredQuantity("spacing", units::kLength);
      w.template_rows = grid->requiredInt("rows");
      w.template_columns = grid->requiredInt("columns");
      grid->finish();
      if (!(spacing.si > 0.0) || w.template_rows < 1 || w.template_columns < 1) {
        grid->fail(spacing.key, spacing.text, "spacing must be > 0 and rows, columns >= 1");
      }
      w.template_spacing_m = spacing.si;
    }
    if (!(depth.si > s_.block_min_m.x() && depth.si <= s_.block_max_m.x())) {
      m.fail(depth.key, depth.text,
             "must lie in the block's x range (" + mm(s_.block_min_m.x()) + ", " +
                 mm(s_.block_max_m.x()) + "]");
    }
    w.max_tip_x_m = depth.si;
  }

  void readSizing(MapReader& m) {
    MeshSizing3& z = s_.sizing;
    auto positive = [&](const char* base, double fallback) {
      const std::optional<Quantity> q = m.optionalQuantity(base, units::kLength);
      if (q && !(q->si > 0.0)) {
        m.fail(q->key, q->text, "must be > 0");
      }
      return q ? q->si : fallback;
    };
    z.size_m = positive("size", z.size_m);
    z.fine_size_m = positive("fine_size", z.fine_size_m);
    z.fine_radius_m = positive("fine_radius", z.fine_radius_m);
    z.facet_distance_m = positive("facet_distance", z.facet_distance_m);
    m.finish();
    if (z.fine_size_m > z.size_m) {
      m.fail(m.keyPath("fine_size"), mm(z.fine_size_m), "must not exceed size " + mm(z.size_m));
    }
  }

  void readTarget(MapReader& m) {
    Target3 t;
    t.name = m.requiredString("name");
    std::string key;
    t.position_m = m.requiredPoint3("position", units::kLength, &key);
    m.finish();
    if (((t.position_m - s_.block_min_m).array() <= 0.0).any() ||
        ((s_.block_max_m - t.position_m).array() <= 0.0).any()) {
      m.fail(key, t.name, "outside the tissue block");
    }
    s_.targets.push_back(std::move(t));
  }

  std::string source_;
  fs::path base_dir_;
  TissueScene3d s_;
};

}  // namespace

bool Workspace3::reaches(const Eigen::Vector2d& p) const {
  return (nearest(p) - p).norm() <= kHoleTol_m;
}

Eigen::Vector2d Workspace3::nearest(const Eigen::Vector2d& p) const {
  if (!use_template) {
    return Eigen::Vector2d(std::clamp(p.x(), y_min_m, y_max_m),
                           std::clamp(p.y(), z_min_m, z_max_m));
  }
  const Eigen::Vector2i k = holeIndex(p);
  return hole(k.x(), k.y());
}

Eigen::Vector2i Workspace3::holeIndex(const Eigen::Vector2d& p) const {
  const Eigen::Vector2d k = ((p - template_origin_m) / template_spacing_m).array().round();
  return {static_cast<int>(std::clamp(k.x(), 0.0, static_cast<double>(template_rows - 1))),
          static_cast<int>(std::clamp(k.y(), 0.0, static_cast<double>(template_columns - 1)))};
}

Eigen::Vector2d Workspace3::hole(int row, int column) const {
  return template_origin_m + template_spacing_m * Eigen::Vector2d(row, column);
}

std::vector<fem::Material> TissueScene3d::materialTable() const {
  std::vector<fem::Material> table{block_material};
  for (const Region3& r : regions) {
    table.push_back(r.material);
  }
  return table;
}

RegionLocator3::RegionLocator3(const TissueScene3d& scene)
    : min_(scene.block_min_m), max_(scene.block_max_m) {
  for (const Region3& r : scene.regions) {
    regions_.emplace_back(r.surface);
  }
}

int RegionLocator3::regionAt(const Vector3& p) const {
  if (((p - min_).array() < 0.0).any() || ((max_ - p).array() < 0.0).any()) {
    return -2;
  }
  for (int r = static_cast<int>(regions_.size()) - 1; r >= 0; --r) {
    const needle_model::MeshDistance& d = regions_[static_cast<std::size_t>(r)];
    if (((p - d.minCorner()).array() >= 0.0).all() && ((d.maxCorner() - p).array() >= 0.0).all() &&
        d.insideOrOn(p)) {
      return r;
    }
  }
  return -1;
}

double RegionLocator3::distanceToRegion(int r, const Vector3& p) const {
  return regions_.at(static_cast<std::size_t>(r)).distance(p);
}

TissueScene3d parseTissueScene3d(const std::string& yaml_text, const std::string& source,
                                 const std::string& base_dir) {
  YAML::Node root;
  try {
    root = YAML::Load(yaml_text);
  } catch (const YAML::Exception& e) {
    throw SceneError(source, "", "", std::string("not valid YAML: ") + e.what());
  }
  return Parser(source, base_dir).parse(root);
}

TissueScene3d loadTissueScene3d(const std::string& path) {
  std::ifstream in(path);
  if (!in) {
    throw SceneError(path, "", "", "cannot read the file");
  }
  std::stringstream text;
  text << in.rdbuf();
  return parseTissueScene3d(text.str(), path, fs::path(path).parent_path().string());
}

bool isTissueScene3dFile(const std::string& path) {
  try {
    const YAML::Node root = YAML::LoadFile(path);
    return root.IsMap() && root["scene"] && root["scene"].IsMap() && root["scene"]["kind"] &&
           root["scene"]["kind"].as<std::string>() == "tissue_3d";
  } catch (const std::exception&) {
    return false;
  }
}

}  // namespace needle_guidance::tissue_3d
