// KAN: the streaming model and its model-file node.
#include "piezo_compensation/models/kan_model.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <random>
#include <sstream>
#include <stdexcept>

namespace piezo::models {

// ---- model --------------------------------------------------------------------------------------------------

KanModel::KanModel(const features::FeatureSpec& spec, double sample_rate_hz, KanNet net, Eigen::VectorXd params,
                   TargetScale target)
    : stream_(spec, sample_rate_hz), sample_rate_hz_(sample_rate_hz), net_(std::move(net)), params_(std::move(params)),
      target_(target) {
  if (static_cast<int>(spec.size()) != net_.shape().widths.front())
    throw std::runtime_error("kan: the feature spec has " + std::to_string(spec.size()) +
                             " features but the network expects " + std::to_string(net_.shape().widths.front()));
  if (static_cast<std::size_t>(params_.size()) != net_.num_params())
    throw std::runtime_error("kan: weight count does not match the architecture");
  meta.sample_rate_hz = sample_rate_hz;
}

double KanModel::predict(const ModelInput& in) const {
  double x[KanNet::kMaxWidth];
  stream_.compute(in, x);
  return target_.to_nm(net_.forward(params_.data(), x));
}

YAML::Node KanModel::to_yaml() const {
  YAML::Node n;
  n["sample_rate_hz"] = sample_rate_hz_;
  n["features"] = stream_.spec().to_yaml();
  n["target"] = target_.to_yaml();
  YAML::Node widths(YAML::NodeType::Sequence);
  for (int w : net_.shape().widths) widths.push_back(w);
  widths.SetStyle(YAML::EmitterStyle::Flow);
  n["hyperparameters"]["widths"] = widths;
  n["hyperparameters"]["grid"] = net_.shape().grid;
  n["hyperparameters"]["order"] = net_.shape().order;
  if (training_info) n["training"] = training_info;
  YAML::Node grids(YAML::NodeType::Sequence);
  for (const auto& g : net_.grids())
    grids.push_back(yaml_list(Eigen::Map<const Eigen::VectorXd>(g.data(), static_cast<Eigen::Index>(g.size()))));
  n["grids"] = grids;
  n["weights"] = yaml_list(params_);
  return n;
}

std::unique_ptr<KanModel> KanModel::from_yaml(const YAML::Node& node) {
  const std::string what = "kan model";
  const NeuralFileHeader header = read_neural_file_header(node, "kan", {"widths", "grid", "order"}, {"grids"});
  const double rate = header.sample_rate_hz;
  const features::FeatureSpec& spec = header.spec;
  const TargetScale& target = header.target;
  const YAML::Node h = header.hyperparameters;
  KanShape shape;
  if (!h["widths"] || !h["widths"].IsSequence()) throw std::runtime_error(what + ": 'widths' must be a list");
  shape.widths.clear();
  for (const auto& w : h["widths"]) {
    try {
      shape.widths.push_back(w.as<int>());
    } catch (const YAML::Exception&) {
      throw std::runtime_error(what + ": 'widths' entries must be integers");
    }
  }
  shape.grid = yaml_int(h, "grid", 1, 64, "model.hyperparameters");
  shape.order = yaml_int(h, "order", 0, 5, "model.hyperparameters");
  if (shape.widths.empty() || shape.widths.front() != static_cast<int>(spec.size()))
    throw std::runtime_error(what + ": 'widths' must start with the number of features (" +
                             std::to_string(spec.size()) + ")");
  KanNet net(shape);
  const YAML::Node grids = node["grids"];
  if (!grids || !grids.IsSequence() || static_cast<int>(grids.size()) != net.num_layers())
    throw std::runtime_error(what + ": 'grids' must be a list with one entry per layer (" +
                             std::to_string(net.num_layers()) + ")");
  for (int l = 0; l < net.num_layers(); ++l) {
    YAML::Node wrap;
    wrap["g"] = grids[static_cast<std::size_t>(l)];
    std::vector<double> g = yaml_numbers(wrap, "g", static_cast<long>(net.grids()[static_cast<std::size_t>(l)].size()),
                                         "model.grids[" + std::to_string(l) + "]");
    try {
      net.set_grid(l, std::move(g));
    } catch (const std::runtime_error& e) {
      throw std::runtime_error(what + ": " + e.what());
    }
  }
  const std::vector<double> w = yaml_numbers(node, "weights", static_cast<long>(net.num_params()));
  auto m = std::make_unique<KanModel>(spec, rate, std::move(net),
                                      Eigen::Map<const Eigen::VectorXd>(w.data(), static_cast<Eigen::Index>(w.size())),
                                      target);
  if (node["training"]) m->training_info = node["training"];
  return m;
}

}  // namespace piezo::models
