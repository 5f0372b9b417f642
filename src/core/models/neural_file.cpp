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

TargetScale TargetScale::from_yaml(const YAML::Node& node, const std::string& where) {
  if (!node) throw std::runtime_error(where + ": missing key");
  check_keys(node, {"mean_nm", "scale_nm", "output_min_nm", "output_max_nm"}, where);
  TargetScale t;
  t.mean_nm = yaml_number(node, "mean_nm", where);
  t.scale_nm = yaml_number(node, "scale_nm", where);
  if (!(t.scale_nm > 0.0)) throw std::runtime_error(where + ".scale_nm: must be positive");
  if (node["output_min_nm"]) t.output_min_nm = yaml_number(node, "output_min_nm", where);
  if (node["output_max_nm"]) t.output_max_nm = yaml_number(node, "output_max_nm", where);
  if (!(t.output_min_nm < t.output_max_nm))
    throw std::runtime_error(where + ".output_min_nm: must be below output_max_nm");
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
  // The model file adds axis and kind to this node.
  std::vector<std::string> allowed = {"kind", "axis", "sample_rate_hz", "features", "target", "hyperparameters",
                                      "training"};
  allowed.insert(allowed.end(), extra_keys.begin(), extra_keys.end());
  allowed.push_back("weights");
  check_keys(node, allowed, "model");
  if (node["kind"] && node["kind"].as<std::string>() != kind)
    throw std::runtime_error("model.kind: node is of kind '" + node["kind"].as<std::string>() + "', expected '" + kind +
                             "'");
  NeuralFileHeader header;
  header.sample_rate_hz = yaml_number(node, "sample_rate_hz");
  if (!(header.sample_rate_hz > 0.0)) throw std::runtime_error("model.sample_rate_hz: must be positive");
  if (!node["features"]) throw std::runtime_error("model.features: missing key");
  header.spec = features::FeatureSpec::from_yaml(node["features"]);
  header.target = TargetScale::from_yaml(node["target"], "model.target");
  header.hyperparameters = node["hyperparameters"];
  if (!header.hyperparameters) throw std::runtime_error("model.hyperparameters: missing key");
  check_keys(header.hyperparameters, hyperparameter_keys, "model.hyperparameters");
  return header;
}

}  // namespace piezo::models
