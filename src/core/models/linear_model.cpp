#include "piezo_compensation/models/linear_model.h"

#include <cmath>
#include <stdexcept>

#include "piezo_compensation/models/c_export.h"
#include "piezo_compensation/models/model_file.h"

namespace piezo::models {

LinearModel::LinearModel(features::FeatureSpec spec, double sample_rate_hz, Eigen::VectorXd weights, double bias_nm,
                         std::string method)
    : stream_(spec, sample_rate_hz), w_(std::move(weights)), b_(bias_nm), method_(std::move(method)),
      rate_hz_(sample_rate_hz) {
  if (static_cast<std::size_t>(w_.size()) != stream_.size())
    throw std::runtime_error("linear model: " + std::to_string(w_.size()) + " weights for " +
                             std::to_string(stream_.size()) + " features");
  if (!w_.allFinite() || !std::isfinite(b_)) throw std::runtime_error("linear model: non-finite weights");
  meta.sample_rate_hz = sample_rate_hz;
}

double LinearModel::predict(const ModelInput& in) const {
  const std::size_t n = stream_.size();
  double buf[64];
  std::vector<double> big;
  double* x = buf;
  if (n > 64) {
    big.resize(n);
    x = big.data();
  }
  stream_.compute(in, x);
  double y = b_;
  for (std::size_t j = 0; j < n; ++j) y += w_[j] * x[j];
  return y;
}

bool LinearModel::is_affine_in_voltage() const {
  for (std::size_t j = 0; j < stream_.size(); ++j) {
    const std::string& t = stream_.spec().features[j].type;
    if ((t == "play" || t == "stop" || t == "play_lowpass" || t == "play_hinge" || t == "voltage_sq") && w_[j] != 0) return false;
  }
  return true;
}

YAML::Node LinearModel::to_yaml() const {
  YAML::Node n;
  n["method"] = method_;
  n["features"] = stream_.spec().to_yaml();
  n["bias_nm"] = b_;
  n["weights"] = yaml_list(std::vector<double>(w_.data(), w_.data() + w_.size()));
  YAML::Node names(YAML::NodeType::Sequence);
  for (const auto& f : stream_.spec().features) names.push_back(f.name());
  n["feature_names"] = names;  // informative only
  return n;
}

ModelPtr LinearModel::load(const YAML::Node& node) {
  const double rate = yaml_number(node, "sample_rate_hz");
  if (!node["features"]) throw std::runtime_error("model.features: missing key");
  features::FeatureSpec spec;
  try {
    spec = features::FeatureSpec::from_yaml(node["features"]);
  } catch (const std::exception& e) {
    throw std::runtime_error(std::string("model.features.") + e.what());
  }
  const auto w = yaml_numbers(node, "weights", static_cast<long>(spec.size()));
  const double b = yaml_number(node, "bias_nm");
  const std::string method = node["method"] ? yaml_string(node, "method") : "ols";
  auto m = std::make_unique<LinearModel>(spec, rate, Eigen::Map<const Eigen::VectorXd>(w.data(), w.size()), b, method);
  return m;
}

}  // namespace piezo::models
