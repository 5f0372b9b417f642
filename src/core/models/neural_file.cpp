#include "piezo_compensation/models/neural_file.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace piezo::models {

YAML::Node TargetScale::to_yaml() const {
  YAML::Node n;
  n["mean_nm"] = mean_nm;
  n["scale_nm"] = scale_nm;
  if (std::isfinite(output_min_nm)) n["output_min_nm"] = output_min_nm;
  if (std::isfinite(output_max_nm)) n["output_max_nm"] = output_max_nm;
  return n;
}

TargetScale TargetScale::from_yaml(const YAML::Node& node, const std::string& what) {
  if (!node) throw std::runtime_error(what + ": missing key 'target'");
  check_keys(node, {"mean_nm", "scale_nm", "output_min_nm", "output_max_nm"}, what + " target");
  TargetScale t;
  t.mean_nm = yaml_double(node, "mean_nm", what + " target");
  t.scale_nm = yaml_double(node, "scale_nm", what + " target");
  if (!(t.scale_nm > 0.0)) throw std::runtime_error(what + " target: 'scale_nm' must be positive");
  if (node["output_min_nm"]) t.output_min_nm = yaml_double(node, "output_min_nm", what + " target");
  if (node["output_max_nm"]) t.output_max_nm = yaml_double(node, "output_max_nm", what + " target");
  if (!(t.output_min_nm < t.output_max_nm))
    throw std::runtime_error(what + " target: 'output_min_nm' must be below 'output_max_nm'");
  return t;
}

std::string TargetScale::c99_expression(const std::string& z) const {
  std::ostringstream os;
  os.precision(17);
  os << "(" << mean_nm << " + " << scale_nm << " * (" << z << "))";
  std::string e = os.str();
  if (std::isfinite(output_min_nm) && std::isfinite(output_max_nm)) {
    std::ostringstream c;
    c.precision(17);
    c << "fmin(fmax(" << e << ", " << output_min_nm << "), " << output_max_nm << ")";
    e = c.str();
  }
  return e;
}

NeuralFileHeader read_neural_file_header(const YAML::Node& node, const std::string& kind,
                                         const std::vector<std::string>& hyperparameter_keys,
                                         const std::vector<std::string>& extra_keys) {
  const std::string what = kind + " model";
  // The model file adds axis and kind to this node.
  std::vector<std::string> allowed = {"kind", "axis", "sample_rate_hz", "features", "target", "hyperparameters",
                                      "training"};
  allowed.insert(allowed.end(), extra_keys.begin(), extra_keys.end());
  allowed.push_back("weights");
  check_keys(node, allowed, what);
  if (node["kind"] && node["kind"].as<std::string>() != kind)
    throw std::runtime_error(what + ": node is of kind '" + node["kind"].as<std::string>() + "'");
  NeuralFileHeader header;
  header.sample_rate_hz = yaml_double(node, "sample_rate_hz", what);
  if (!(header.sample_rate_hz > 0.0)) throw std::runtime_error(what + ": 'sample_rate_hz' must be positive");
  if (!node["features"]) throw std::runtime_error(what + ": missing key 'features'");
  header.spec = features::FeatureSpec::from_yaml(node["features"]);
  header.target = TargetScale::from_yaml(node["target"], what);
  header.hyperparameters = node["hyperparameters"];
  if (!header.hyperparameters) throw std::runtime_error(what + ": missing key 'hyperparameters'");
  check_keys(header.hyperparameters, hyperparameter_keys, what + " hyperparameters");
  return header;
}

void check_keys(const YAML::Node& node, const std::vector<std::string>& allowed, const std::string& what) {
  if (!node || !node.IsMap()) throw std::runtime_error(what + ": expected a map");
  for (const auto& kv : node) {
    const std::string key = kv.first.as<std::string>();
    if (std::find(allowed.begin(), allowed.end(), key) == allowed.end()) {
      std::string known;
      for (const auto& a : allowed) known += (known.empty() ? "" : ", ") + a;
      throw std::runtime_error(what + ": unknown key '" + key + "' (known: " + known + ")");
    }
  }
}

double yaml_double(const YAML::Node& node, const std::string& key, const std::string& what) {
  const YAML::Node v = node[key];
  if (!v) throw std::runtime_error(what + ": missing key '" + key + "'");
  double d = 0.0;
  try {
    d = v.as<double>();
  } catch (const YAML::Exception&) {
    throw std::runtime_error(what + ": '" + key + "' is not a number");
  }
  if (!std::isfinite(d)) throw std::runtime_error(what + ": '" + key + "' is not finite");
  return d;
}

int yaml_int(const YAML::Node& node, const std::string& key, const std::string& what, int low, int high) {
  const double d = yaml_double(node, key, what);
  if (d != std::floor(d) || d < low || d > high)
    throw std::runtime_error(what + ": '" + key + "' must be an integer in " + std::to_string(low) + ".." +
                             std::to_string(high));
  return static_cast<int>(d);
}

std::vector<double> yaml_doubles(const YAML::Node& node, const std::string& key, const std::string& what,
                                 std::size_t expected_size) {
  const YAML::Node v = node[key];
  if (!v) throw std::runtime_error(what + ": missing key '" + key + "'");
  if (!v.IsSequence()) throw std::runtime_error(what + ": '" + key + "' must be a list of numbers");
  if (v.size() != expected_size) {
    std::ostringstream os;
    os << what << ": '" << key << "' has " << v.size() << " values, expected " << expected_size;
    throw std::runtime_error(os.str());
  }
  std::vector<double> out(expected_size);
  for (std::size_t i = 0; i < expected_size; ++i) {
    try {
      out[i] = v[i].as<double>();
    } catch (const YAML::Exception&) {
      throw std::runtime_error(what + ": '" + key + "' entry " + std::to_string(i) + " is not a number");
    }
    if (!std::isfinite(out[i]))
      throw std::runtime_error(what + ": '" + key + "' entry " + std::to_string(i) + " is not finite");
  }
  return out;
}

YAML::Node flow_sequence(const Eigen::VectorXd& values) {
  YAML::Node seq(YAML::NodeType::Sequence);
  for (Eigen::Index i = 0; i < values.size(); ++i) seq.push_back(values[i]);
  seq.SetStyle(YAML::EmitterStyle::Flow);
  return seq;
}

}  // namespace piezo::models
