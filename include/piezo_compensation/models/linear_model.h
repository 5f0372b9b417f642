// Kind "linear": position = bias + Σ w_j · feature_j (standardised features of a FeatureSpec), fitted (training/fit_linear.cpp) by OLS,
// ridge or lasso (λ from time-block CV). Affine in the voltage whenever every feature is (no play/stop).
#pragma once

#include <Eigen/Dense>

#include <string>

#include "piezo_compensation/features/feature_stream.h"
#include "piezo_compensation/models/model.h"

namespace piezo::models {

class LinearModel : public Model {
 public:
  LinearModel(features::FeatureSpec spec, double sample_rate_hz, Eigen::VectorXd weights, double bias_nm,
               std::string method = "ols");

  std::string kind() const override { return "linear"; }
  void reset(double voltage_v, double position_nm) override { stream_.reset(voltage_v, position_nm); }
  double predict(const ModelInput& in) const override;
  void commit(const ModelInput& in, double position_nm) override { stream_.commit(in, position_nm); }
  std::unique_ptr<Model> clone() const override { return std::make_unique<LinearModel>(*this); }
  bool uses_position_history() const override { return stream_.spec().uses_positions(); }
  std::string fixed_rate_reason() const override { return kLaggedSamplesReason; }
  bool is_affine_in_voltage() const override;
  std::vector<std::string> aux_inputs() const override { return stream_.spec().aux_signals(); }
  YAML::Node to_yaml() const override;
  std::size_t num_parameters() const override { return static_cast<std::size_t>(w_.size()) + 1; }

  const features::FeatureSpec& spec() const { return stream_.spec(); }
  const Eigen::VectorXd& weights() const { return w_; }
  double bias_nm() const { return b_; }
  const std::string& method() const { return method_; }
  double sample_rate_hz() const { return rate_hz_; }

  static ModelPtr load(const YAML::Node& node);  // fitted by training::fit_linear (training/fitters.h)

 private:
  features::FeatureStream stream_;
  Eigen::VectorXd w_;
  double b_;
  std::string method_;
  double rate_hz_;
};

}  // namespace piezo::models
