#include "piezo_compensation/models/yaml_fields.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <stdexcept>

namespace piezo::models {

namespace {
std::string scalar_of(const YAML::Node& node, const std::string& key, const std::string& where) {
  const YAML::Node v = node[key];
  if (!v) throw std::runtime_error(where + "." + key + ": missing key");
  if (!v.IsScalar()) throw std::runtime_error(where + "." + key + ": expected a scalar");
  return v.Scalar();
}

long parse_int(const YAML::Node& node, const std::string& key, const std::string& where) {
  const std::string s = scalar_of(node, key, where);
  char* end = nullptr;
  const long v = std::strtol(s.c_str(), &end, 10);
  if (s.empty() || *end != '\0') throw std::runtime_error(where + "." + key + ": expected an integer, got '" + s + "'");
  return v;
}
}  // namespace

void check_keys(const YAML::Node& node, const std::vector<std::string>& allowed, const std::string& where) {
  if (!node || !node.IsMap()) throw std::runtime_error(where + ": expected a mapping");
  for (const auto& kv : node) {
    const std::string key = kv.first.as<std::string>();
    if (std::find(allowed.begin(), allowed.end(), key) == allowed.end()) {
      std::string known;
      for (const auto& a : allowed) known += (known.empty() ? "" : ", ") + a;
      throw std::runtime_error(where + ": unknown key '" + key + "' (known: " + known + ")");
    }
  }
}

double yaml_number(const YAML::Node& node, const std::string& key, const std::string& where) {
  const std::string s = scalar_of(node, key, where);
  char* end = nullptr;
  const double v = std::strtod(s.c_str(), &end);
  if (s.empty() || *end != '\0' || !std::isfinite(v))
    throw std::runtime_error(where + "." + key + ": expected a finite number, got '" + s + "'");
  return v;
}

int yaml_int(const YAML::Node& node, const std::string& key, const std::string& where) {
  return static_cast<int>(parse_int(node, key, where));
}

int yaml_int(const YAML::Node& node, const std::string& key, int low, int high, const std::string& where) {
  const long v = parse_int(node, key, where);
  if (v < low || v > high)
    throw std::runtime_error(where + "." + key + ": expected an integer in " + std::to_string(low) + ".." +
                             std::to_string(high) + ", got " + std::to_string(v));
  return static_cast<int>(v);
}

std::string yaml_string(const YAML::Node& node, const std::string& key, const std::string& where) {
  return scalar_of(node, key, where);
}

std::vector<double> yaml_numbers(const YAML::Node& node, const std::string& key, long expected,
                                 const std::string& where) {
  const YAML::Node v = node[key];
  if (!v) throw std::runtime_error(where + "." + key + ": missing key");
  if (!v.IsSequence()) throw std::runtime_error(where + "." + key + ": expected a list of numbers");
  std::vector<double> out;
  for (std::size_t i = 0; i < v.size(); ++i) {
    const std::string s = v[i].IsScalar() ? v[i].Scalar() : "";
    char* end = nullptr;
    const double x = std::strtod(s.c_str(), &end);
    if (s.empty() || *end != '\0' || !std::isfinite(x))
      throw std::runtime_error(where + "." + key + "[" + std::to_string(i) + "]: expected a finite number");
    out.push_back(x);
  }
  if (expected >= 0 && static_cast<long>(out.size()) != expected)
    throw std::runtime_error(where + "." + key + ": expected " + std::to_string(expected) + " entries, got " +
                             std::to_string(out.size()));
  return out;
}

YAML::Node yaml_list(const std::vector<double>& v) {
  return yaml_list(Eigen::Map<const Eigen::VectorXd>(v.data(), static_cast<Eigen::Index>(v.size())));
}

YAML::Node yaml_list(const Eigen::VectorXd& v) {
  YAML::Node n(YAML::NodeType::Sequence);
  for (Eigen::Index i = 0; i < v.size(); ++i) n.push_back(v[i]);
  n.SetStyle(YAML::EmitterStyle::Flow);
  return n;
}

}  // namespace piezo::models
