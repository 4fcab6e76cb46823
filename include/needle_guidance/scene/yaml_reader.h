// Typed reading of scene YAML: unit-suffixed keys converted to SI, unknown-key detection and
// dotted/indexed key paths for SceneError. Every scene kind is read with it (planar scenes in
// src/scene/, 3-D steering scenes in src/steering_3d/scene_3d.cpp).
#pragma once

#include <yaml-cpp/yaml.h>
#include <Eigen/Core>

#include <optional>
#include <set>
#include <string>
#include <vector>

#include "needle_guidance/scene/scene.h"

namespace needle_guidance::scene::detail {

/// A unit a key may carry as its suffix.
struct Unit {
  const char* suffix;  ///< key suffix, e.g. "_cm" ("" for a dimensionless key)
  const char* symbol;  ///< for messages, e.g. "cm"
  double to_si;        ///< value_SI = value_in_file * to_si
};

/// A physical dimension: the unit suffixes its keys accept. A key names exactly one of them.
struct Dimension {
  const char* name;
  std::vector<Unit> units;
};

inline const Dimension kDimensionless{"dimensionless", {{"", "", 1.0}}};
inline const Dimension kLength{"length",
                               {{"_m", "m", 1.0}, {"_cm", "cm", 1e-2}, {"_mm", "mm", 1e-3}}};
inline const Dimension kModulus{"modulus",
                                {{"_Pa", "Pa", 1.0}, {"_kPa", "kPa", 1e3}, {"_MPa", "MPa", 1e6}}};
inline const Dimension kAngle{"angle",
                              {{"_deg", "deg", 0.017453292519943295}, {"_rad", "rad", 1.0}}};
inline const Dimension kVelocity{
    "velocity", {{"_m_s", "m/s", 1.0}, {"_cm_s", "cm/s", 1e-2}, {"_mm_s", "mm/s", 1e-3}}};
inline const Dimension kForce{"force", {{"_N", "N", 1.0}, {"_mN", "mN", 1e-3}}};
inline const Dimension kForcePerLength{
    "force per length",
    {{"_N_per_m", "N/m", 1.0}, {"_N_per_cm", "N/cm", 1e2}, {"_N_per_mm", "N/mm", 1e3}}};
inline const Dimension kDensity{"density", {{"_kg_m3", "kg/m^3", 1.0}}};
inline const Dimension kFrequency{"frequency", {{"_hz", "Hz", 1.0}}};
inline const Dimension kTime{"time", {{"_s", "s", 1.0}, {"_ms", "ms", 1e-3}}};
inline const Dimension kPerTime{"rate", {{"_per_s", "1/s", 1.0}}};
inline const Dimension kAngularRate{
    "angular rate", {{"_rad_s", "rad/s", 1.0}, {"_rev_s", "rev/s", 6.283185307179586}}};

/// A number read from the file, with where it came from.
struct Quantity {
  double si = 0.0;   ///< value in SI units
  std::string key;   ///< full key path as written, e.g. "needle.max_depth_cm"
  std::string text;  ///< the value as written
  Unit unit{"", "", 1.0};
  int line = -1;  ///< 1-based line, -1 if unknown
};

/// A list of points read from the file, e.g. a polygon.
struct PointList {
  std::vector<Point2> points;  ///< [m]
  std::string key;             ///< e.g. "regions[0].polygon_cm"
  std::string text;            ///< the whole list as written (one line, shortened)
  Unit unit{"", "", 1.0};
  int line = -1;  ///< 1-based line of the list, -1 if unknown
};

/// A 2-D point or a 3-D point/vector read from the file.
template <int N>
struct VectorValue {
  Eigen::Matrix<double, N, 1> value = Eigen::Matrix<double, N, 1>::Zero();  ///< in SI
  std::string key;
  std::string text;
  Unit unit{"", "", 1.0};
  int line = -1;  ///< 1-based line, -1 if unknown
};
using PointValue = VectorValue<2>;    ///< [m]
using Vector3Value = VectorValue<3>;  ///< in SI

/// The YAML node as one line of text (flow style, shortened) for error messages.
std::string nodeText(const YAML::Node& node);
/// 1-based line of a node, -1 if unknown.
int lineOf(const YAML::Node& node);
/// A value in SI shown in `unit`, e.g. "3.3 cm".
std::string formatIn(double si, const Unit& unit);
/// A point in SI shown in `unit`, e.g. "(3.3, 3) cm".
std::string formatIn(const Point2& p_si, const Unit& unit);

/// Reads one YAML mapping. Every key it is asked about becomes "known"; finish() then refuses
/// any other key. All failures throw SceneError naming the file, the key path and the value.
class MapReader {
public:
  /// @param[in] node must be a mapping (a null node counts as an empty mapping)
  /// @param[in] path key path of this mapping ("" for the document root)
  MapReader(const YAML::Node& node, std::string path, std::string file);

  const std::string& path() const { return path_; }
  const std::string& file() const { return file_; }
  /// Key path of a key of this mapping, e.g. "needle" + "max_depth_cm".
  std::string keyPath(const std::string& key) const;

  /// 1-based line of the key's value, -1 if absent.
  int lineOfKey(const std::string& key) const;

  /// True if the key is present (and not null).
  bool has(const std::string& key);

  std::string requiredString(const std::string& key);
  std::optional<std::string> optionalString(const std::string& key);
  /// One of `choices`; throws naming them otherwise.
  std::string requiredChoice(const std::string& key, const std::vector<std::string>& choices);
  std::optional<std::string> optionalChoice(const std::string& key,
                                            const std::vector<std::string>& choices);
  bool optionalBool(const std::string& key, bool fallback);
  int requiredInt(const std::string& key);
  std::optional<int> optionalInt(const std::string& key);

  /// A finite number under base + one of dim's suffixes, converted to SI. Both `radius_cm` and
  /// `radius_mm` present is an error.
  Quantity requiredQuantity(const std::string& base, const Dimension& dim);
  std::optional<Quantity> optionalQuantity(const std::string& base, const Dimension& dim);
  /// A point [x, y] under base + one of dim's suffixes.
  PointValue requiredPoint(const std::string& base, const Dimension& dim) {
    return requiredVectorValue<2>(base, dim);
  }
  /// A list [x, y, z] under base + one of dim's suffixes (kDimensionless: the key `base`).
  Vector3Value requiredVector3(const std::string& base, const Dimension& dim) {
    return requiredVectorValue<3>(base, dim);
  }
  /// A 3-D point [x, y, z] under base + one of dim's suffixes, in SI; its key path goes to
  /// *key_path if given.
  Eigen::Vector3d requiredPoint3(const std::string& base, const Dimension& dim,
                                 std::string* key_path = nullptr);
  /// A list of points [[x, y], ...] under base + one of dim's suffixes.
  PointList requiredPointList(const std::string& base, const Dimension& dim);

  MapReader requiredMap(const std::string& key);
  std::optional<MapReader> optionalMap(const std::string& key);
  /// A list of mappings; a missing or null key is an empty list.
  std::vector<MapReader> optionalList(const std::string& key);

  /// Refuses keys that were never asked about, and duplicated keys.
  void finish() const;

  /// Throws SceneError for this file; " (line N)" is appended to the reason if line >= 0.
  [[noreturn]] void fail(const std::string& key_path, const std::string& value,
                         const std::string& reason, int line = -1) const;
  /// Throws SceneError with the node's text as value and its line appended to the reason.
  [[noreturn]] void failAt(const std::string& key_path, const YAML::Node& value,
                           const std::string& reason) const;

private:
  struct Variant {
    std::string key;
    YAML::Node node;
    Unit unit;
  };
  /// The single present variant of base + dim's suffixes, or nullopt.
  std::optional<Variant> findVariant(const std::string& base, const Dimension& dim);
  [[noreturn]] void failMissing(const std::string& base, const Dimension& dim) const;
  double toNumber(const std::string& key_path, const YAML::Node& node) const;
  /// The list [x, y] (N = 2) or [x, y, z] (N = 3) scaled by to_si.
  template <int N>
  Eigen::Matrix<double, N, 1> toVector(const std::string& key_path, const YAML::Node& node,
                                       double to_si) const;
  template <int N>
  VectorValue<N> requiredVectorValue(const std::string& base, const Dimension& dim);

  /// Marks a plain key as known.
  void noteKey(const std::string& key);

  YAML::Node node_;
  std::string path_;
  std::string file_;
  std::set<std::string> known_;        ///< every accepted key, all unit variants
  std::vector<std::string> expected_;  ///< accepted keys for messages, "radius_{m,cm,mm}"
};

}  // namespace needle_guidance::scene::detail
