// Dense (fully connected) network with leaky ReLU hidden layers and a linear output, predicting the
// standardised position from the standardised feature vector of a FeatureStream. Kind "dense".
#pragma once

#include <Eigen/Dense>

#include <cstdint>

#include "piezo_compensation/features/feature_stream.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/neural_file.h"

namespace piezo::models {

struct DenseShape {
  int inputs = 1;
  int depth = 1;             // hidden layers
  int width = 10;            // neurons per hidden layer
  double leaky_slope = 0.01;
};

// The network alone, on a flat parameter vector: per layer W (out × in, column-major) then b.
class DenseNet {
 public:
  static constexpr int kMaxWidth = 256;
  DenseNet() = default;
  explicit DenseNet(const DenseShape& shape);  // throws on a shape out of range
  const DenseShape& shape() const { return shape_; }
  std::size_t num_params() const { return num_params_; }
  // He-initialised parameters, deterministic for the seed.
  Eigen::VectorXd initial_params(std::uint64_t seed) const;
  // One sample, no allocation.
  double forward(const double* params, const double* x) const;
  // Outputs for the columns of x.
  Eigen::VectorXd forward_batch(const Eigen::VectorXd& params, const Eigen::MatrixXd& x) const;
  // Σ (out - y)² over the columns of x; adds its gradient to *grad when non-null.
  double loss_grad(const Eigen::VectorXd& params, const Eigen::MatrixXd& x, const Eigen::VectorXd& y,
                   Eigen::VectorXd* grad) const;

 private:
  DenseShape shape_;
  std::size_t num_params_ = 0;
  std::vector<int> sizes_;  // inputs, width × depth, 1
};

class DenseModel : public Model {
 public:
  DenseModel(const features::FeatureSpec& spec, double sample_rate_hz, const DenseShape& shape,
             Eigen::VectorXd params, TargetScale target);
  std::string kind() const override { return "dense"; }
  void reset(double voltage_v, double position_nm) override { stream_.reset(voltage_v, position_nm); }
  double predict(const ModelInput& in) const override;
  void commit(const ModelInput& in, double position_nm) override { stream_.commit(in, position_nm); }
  std::unique_ptr<Model> clone() const override { return std::make_unique<DenseModel>(*this); }
  bool uses_position_history() const override { return stream_.spec().uses_positions(); }
  std::string fixed_rate_reason() const override { return kLaggedSamplesReason; }
  std::vector<std::string> aux_inputs() const override { return stream_.spec().aux_signals(); }
  YAML::Node to_yaml() const override;
  std::size_t num_parameters() const override { return net_.num_params(); }

  static std::unique_ptr<DenseModel> from_yaml(const YAML::Node& node);
  // The network alone on the standardised feature vector: `static double <prefix>_network(const double* z)`.
  std::string export_c99_network(const std::string& prefix) const;
  // The streaming header (see neural_c99_header).
  std::string export_c99(const std::string& prefix) const;

  const DenseNet& net() const { return net_; }
  const Eigen::VectorXd& params() const { return params_; }
  const TargetScale& target() const { return target_; }
  YAML::Node training_info;  // optimiser, epochs, losses: written to the file for the record

 private:
  features::FeatureStream stream_;
  double sample_rate_hz_;
  DenseNet net_;
  Eigen::VectorXd params_;
  TargetScale target_;
};

// A complete streaming C99 header (c_export.h's API: <p>_state, <p>_init, <p>_predict, <p>_commit, <p>_step) for a
// network on a feature vector: the feature engine comes from the linear exporter (prefix <p>_feat, its own
// predict/step/inverse removed), `network_code` must define `static double <p>_network(const double* z)` on the
// standardised features. Throws for specs the engine cannot export (aux signals).
std::string neural_c99_header(const features::FeatureSpec& spec, double sample_rate_hz, const std::string& prefix,
                              const std::string& network_code);

}  // namespace piezo::models
