#include "needle_guidance/scene/yaml_reader.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <sstream>
#include <utility>

namespace needle_guidance::scene::detail {
namespace {

constexpr std::size_t kMaxValueChars = 80;
constexpr std::size_t kMaxSuggestionDistance = 2;

std::string typeName(const YAML::Node& node) {
  if (!node.IsDefined() || node.IsNull()) {
    return "null";
  }
  if (node.IsSequence()) {
    return "a list";
  }
  if (node.IsMap()) {
    return "a mapping";
  }
  return "a scalar";
}

std::size_t editDistance(const std::string& a, const std::string& b) {
  std::vector<std::size_t> row(b.size() + 1);
  for (std::size_t j = 0; j <= b.size(); ++j) {
    row[j] = j;
  }
  for (std::size_t i = 1; i <= a.size(); ++i) {
    std::size_t diagonal = row[0];
    row[0] = i;
    for (std::size_t j = 1; j <= b.size(); ++j) {
      const std::size_t above = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, diagonal + (a[i - 1] == b[j - 1] ? 0 : 1)});
      diagonal = above;
    }
  }
  return row[b.size()];
}

/// "radius_{m,cm,mm}" for a dimensioned key, "radius" for a plain one.
std::string variantsPattern(const std::string& base, const Dimension& dim) {
  if (dim.units.size() == 1) {
    return base + dim.units.front().suffix;
  }
  std::string pattern = base + "_{";
  for (std::size_t i = 0; i < dim.units.size(); ++i) {
    pattern += (i ? "," : "") + std::string(dim.units[i].suffix + 1);
  }
  return pattern + "}";
}

std::string oneLine(std::string text) {
  std::replace(text.begin(), text.end(), '\n', ' ');
  std::replace(text.begin(), text.end(), '\r', ' ');
  return text;
}

}  // namespace

std::string nodeText(const YAML::Node& node) {
  if (!node.IsDefined()) {
    return "";
  }
  if (node.IsNull()) {
    return "null";
  }
  std::string text;
  if (node.IsScalar()) {
    text = node.Scalar();
  } else {
    YAML::Emitter out;
    out.SetMapFormat(YAML::Flow);
    out.SetSeqFormat(YAML::Flow);
    out << node;
    text = out.c_str();
  }
  text = oneLine(text);
  if (text.size() > kMaxValueChars) {
    text = text.substr(0, kMaxValueChars - 3) + "...";
  }
  return text;
}

int lineOf(const YAML::Node& node) {
  if (!node.IsDefined()) {
    return -1;
  }
  const YAML::Mark mark = node.Mark();
  return mark.line >= 0 ? mark.line + 1 : -1;
}

std::string formatIn(double si, const Unit& unit) {
  std::ostringstream out;
  out << si / unit.to_si;
  if (unit.symbol[0] != '\0') {
    out << ' ' << unit.symbol;
  }
  return out.str();
}

std::string formatIn(const Point2& p_si, const Unit& unit) {
  std::ostringstream out;
  out << '(' << p_si.x() / unit.to_si << ", " << p_si.y() / unit.to_si << ')';
  if (unit.symbol[0] != '\0') {
    out << ' ' << unit.symbol;
  }
  return out.str();
}

MapReader::MapReader(const YAML::Node& node, std::string path, std::string file)
    : path_(std::move(path)), file_(std::move(file)) {
  if (!node.IsDefined() || node.IsNull()) {
    node_ = YAML::Node(YAML::NodeType::Map);
  } else if (node.IsMap()) {
    node_ = node;
  } else {
    failAt(path_, node, "expected a mapping of keys, got " + typeName(node));
  }
}

std::string MapReader::keyPath(const std::string& key) const {
  return path_.empty() ? key : path_ + "." + key;
}

void MapReader::fail(const std::string& key_path, const std::string& value,
                     const std::string& reason, int line) const {
  throw SceneError(file_, key_path, value,
                   line >= 0 ? reason + " (line " + std::to_string(line) + ")" : reason);
}

void MapReader::failAt(const std::string& key_path, const YAML::Node& value,
                       const std::string& reason) const {
  fail(key_path, nodeText(value), reason, lineOf(value));
}

int MapReader::lineOfKey(const std::string& key) const {
  const YAML::Node& node = node_;
  return lineOf(node[key]);
}

void MapReader::noteKey(const std::string& key) {
  if (known_.insert(key).second) {
    expected_.push_back(key);
  }
}

bool MapReader::has(const std::string& key) {
  noteKey(key);
  const YAML::Node& node = node_;
  const YAML::Node value = node[key];
  return value.IsDefined() && !value.IsNull();
}

std::optional<std::string> MapReader::optionalString(const std::string& key) {
  noteKey(key);
  const YAML::Node& node = node_;
  const YAML::Node value = node[key];
  if (!value.IsDefined()) {
    return std::nullopt;
  }
  if (!value.IsScalar()) {
    failAt(keyPath(key), value, "expected a string, got " + typeName(value));
  }
  return value.Scalar();
}

std::string MapReader::requiredString(const std::string& key) {
  const std::optional<std::string> value = optionalString(key);
  if (!value) {
    failMissing(key, kDimensionless);
  }
  return *value;
}

std::optional<std::string> MapReader::optionalChoice(const std::string& key,
                                                     const std::vector<std::string>& choices) {
  std::optional<std::string> value = optionalString(key);
  if (value && std::find(choices.begin(), choices.end(), *value) == choices.end()) {
    std::string list;
    for (const std::string& choice : choices) {
      list += (list.empty() ? "" : ", ") + choice;
    }
    const YAML::Node& node = node_;
    failAt(keyPath(key), node[key], "unknown value; expected one of: " + list);
  }
  return value;
}

std::string MapReader::requiredChoice(const std::string& key,
                                      const std::vector<std::string>& choices) {
  const std::optional<std::string> value = optionalChoice(key, choices);
  if (!value) {
    failMissing(key, kDimensionless);
  }
  return *value;
}

bool MapReader::optionalBool(const std::string& key, bool fallback) {
  noteKey(key);
  const YAML::Node& node = node_;
  const YAML::Node value = node[key];
  if (!value.IsDefined()) {
    return fallback;
  }
  bool result = false;
  if (!value.IsScalar() || value.Tag() == "!" || !YAML::convert<bool>::decode(value, result)) {
    failAt(keyPath(key), value, "expected true or false, got " + typeName(value));
  }
  return result;
}

std::optional<int> MapReader::optionalInt(const std::string& key) {
  noteKey(key);
  const YAML::Node& node = node_;
  const YAML::Node value = node[key];
  if (!value.IsDefined()) {
    return std::nullopt;
  }
  int result = 0;
  if (!value.IsScalar() || value.Tag() == "!" || !YAML::convert<int>::decode(value, result)) {
    failAt(keyPath(key), value, "expected an integer, got " + typeName(value));
  }
  return result;
}

int MapReader::requiredInt(const std::string& key) {
  const std::optional<int> value = optionalInt(key);
  if (!value) {
    failMissing(key, kDimensionless);
  }
  return *value;
}

double MapReader::toNumber(const std::string& key_path, const YAML::Node& node) const {
  if (!node.IsScalar()) {
    failAt(key_path, node, "expected a number, got " + typeName(node));
  }
  if (node.Tag() == "!") {
    failAt(key_path, node, "expected a number, got a quoted string");
  }
  double value = 0.0;
  if (!YAML::convert<double>::decode(node, value)) {
    failAt(key_path, node, "expected a finite number");
  }
  if (!std::isfinite(value)) {
    failAt(key_path, node, "not a finite number (NaN and inf are refused)");
  }
  return value;
}

template <int N>
Eigen::Matrix<double, N, 1> MapReader::toVector(const std::string& key_path, const YAML::Node& node,
                                                double to_si) const {
  static_assert(N == 2 || N == 3, "points are 2-D or 3-D");
  if (!node.IsSequence() || node.size() != static_cast<std::size_t>(N)) {
    failAt(key_path, node,
           std::string(N == 2 ? "expected a point [x, y]" : "expected a list [x, y, z]") +
               ", got " +
               (node.IsSequence() ? "a list of " + std::to_string(node.size()) : typeName(node)));
  }
  Eigen::Matrix<double, N, 1> v;
  for (int i = 0; i < N; ++i) {
    v[i] = toNumber(key_path + "[" + std::to_string(i) + "]", node[i]) * to_si;
  }
  return v;
}

std::optional<MapReader::Variant> MapReader::findVariant(const std::string& base,
                                                         const Dimension& dim) {
  std::optional<Variant> found;
  const YAML::Node& node = node_;
  const std::string pattern = variantsPattern(base, dim);
  if (std::find(expected_.begin(), expected_.end(), pattern) == expected_.end()) {
    expected_.push_back(pattern);
  }
  for (const Unit& unit : dim.units) {
    const std::string key = base + unit.suffix;
    known_.insert(key);
    const YAML::Node value = node[key];
    if (!value.IsDefined()) {
      continue;
    }
    if (found) {
      failAt(keyPath(key), value,
             "conflicts with '" + found->key + "': give " + base + " in one unit only");
    }
    found = Variant{key, value, unit};
  }
  return found;
}

void MapReader::failMissing(const std::string& base, const Dimension& dim) const {
  std::string reason = "required key missing";
  if (dim.units.size() > 1) {
    reason += ": give one of ";
    for (std::size_t i = 0; i < dim.units.size(); ++i) {
      reason += (i ? ", " : "") + base + dim.units[i].suffix;
    }
  }
  // A typo of a required key surfaces here first; name the likely culprit.
  for (const auto& entry : node_) {
    const std::string key = entry.first.as<std::string>("");
    if (known_.count(key)) {
      continue;
    }
    bool similar = key.rfind(base, 0) == 0;
    for (const Unit& unit : dim.units) {
      similar = similar || editDistance(key, base + unit.suffix) <= kMaxSuggestionDistance;
    }
    if (similar) {
      reason += "; found unknown key '" + key + "'";
      break;
    }
  }
  fail(keyPath(dim.units.size() > 1 ? base : base + dim.units.front().suffix), "", reason,
       lineOf(node_));
}

std::optional<Quantity> MapReader::optionalQuantity(const std::string& base, const Dimension& dim) {
  const std::optional<Variant> variant = findVariant(base, dim);
  if (!variant) {
    return std::nullopt;
  }
  Quantity quantity;
  quantity.key = keyPath(variant->key);
  quantity.si = toNumber(quantity.key, variant->node) * variant->unit.to_si;
  quantity.text = nodeText(variant->node);
  quantity.unit = variant->unit;
  quantity.line = lineOf(variant->node);
  return quantity;
}

Quantity MapReader::requiredQuantity(const std::string& base, const Dimension& dim) {
  std::optional<Quantity> quantity = optionalQuantity(base, dim);
  if (!quantity) {
    failMissing(base, dim);
  }
  return *quantity;
}

template <int N>
VectorValue<N> MapReader::requiredVectorValue(const std::string& base, const Dimension& dim) {
  const std::optional<Variant> variant = findVariant(base, dim);
  if (!variant) {
    failMissing(base, dim);
  }
  VectorValue<N> v;
  v.key = keyPath(variant->key);
  v.text = nodeText(variant->node);
  v.unit = variant->unit;
  v.line = lineOf(variant->node);
  v.value = toVector<N>(v.key, variant->node, variant->unit.to_si);
  return v;
}
template VectorValue<2> MapReader::requiredVectorValue<2>(const std::string&, const Dimension&);
template VectorValue<3> MapReader::requiredVectorValue<3>(const std::string&, const Dimension&);

Eigen::Vector3d MapReader::requiredPoint3(const std::string& base, const Dimension& dim,
                                          std::string* key_path) {
  const Vector3Value v = requiredVector3(base, dim);
  if (key_path != nullptr) {
    *key_path = v.key;
  }
  return v.value;
}

PointList MapReader::requiredPointList(const std::string& base, const Dimension& dim) {
  const std::optional<Variant> variant = findVariant(base, dim);
  if (!variant) {
    failMissing(base, dim);
  }
  PointList list;
  list.key = keyPath(variant->key);
  list.text = nodeText(variant->node);
  list.unit = variant->unit;
  list.line = lineOf(variant->node);
  if (!variant->node.IsSequence()) {
    failAt(list.key, variant->node,
           "expected a list of points [[x, y], ...], got " + typeName(variant->node));
  }
  for (std::size_t i = 0; i < variant->node.size(); ++i) {
    list.points.push_back(toVector<2>(list.key + "[" + std::to_string(i) + "]", variant->node[i],
                                      variant->unit.to_si));
  }
  return list;
}

std::optional<MapReader> MapReader::optionalMap(const std::string& key) {
  noteKey(key);
  const YAML::Node& node = node_;
  const YAML::Node value = node[key];
  if (!value.IsDefined()) {
    return std::nullopt;
  }
  return MapReader(value, keyPath(key), file_);
}

MapReader MapReader::requiredMap(const std::string& key) {
  std::optional<MapReader> map = optionalMap(key);
  if (!map) {
    failMissing(key, kDimensionless);
  }
  return *map;
}

std::vector<MapReader> MapReader::optionalList(const std::string& key) {
  noteKey(key);
  const YAML::Node& node = node_;
  const YAML::Node value = node[key];
  std::vector<MapReader> items;
  if (!value.IsDefined() || value.IsNull()) {
    return items;
  }
  if (!value.IsSequence()) {
    failAt(keyPath(key), value, "expected a list, got " + typeName(value));
  }
  for (std::size_t i = 0; i < value.size(); ++i) {
    items.emplace_back(value[i], keyPath(key) + "[" + std::to_string(i) + "]", file_);
  }
  return items;
}

void MapReader::finish() const {
  std::map<std::string, int> seen;
  for (const auto& entry : node_) {
    if (!entry.first.IsScalar()) {
      failAt(path_, entry.first, "keys must be plain names");
    }
    const std::string key = entry.first.Scalar();
    if (++seen[key] > 1) {
      failAt(keyPath(key), entry.second, "duplicate key");
    }
    if (known_.count(key)) {
      continue;
    }
    // Closest known key; ties go to the one of the same length (a mistyped letter).
    std::string best;
    std::size_t best_distance = kMaxSuggestionDistance + 1;
    for (const std::string& candidate : known_) {
      const std::size_t distance = editDistance(key, candidate);
      const bool same_length = candidate.size() == key.size();
      if (distance < best_distance ||
          (distance == best_distance && same_length && best.size() != key.size())) {
        best = candidate;
        best_distance = distance;
      }
    }
    std::string reason = "unknown key";
    if (!best.empty()) {
      reason += " (did you mean '" + best + "'?)";
    }
    std::string expected;
    for (const std::string& pattern : expected_) {
      expected += (expected.empty() ? "" : ", ") + pattern;
    }
    reason += "; allowed here: " + expected;
    fail(keyPath(key), nodeText(entry.second), reason, lineOf(entry.first));
  }
}

}  // namespace needle_guidance::scene::detail
