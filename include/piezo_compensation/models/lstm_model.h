// LSTM network (stacked layers, linear head) over the standardised feature vector of a FeatureStream, predicting
// the standardised position. Streaming: predict() steps from the committed (h, c) without changing them;
// commit() advances them. Trained by truncated BPTT on sequences that each start after a gradient-free warm-up
// from the zero state (reset() does the same warm-up at rest, so training and streaming start alike). Kind "lstm".
#pragma once

#include <Eigen/Dense>
#include <cstdint>
#include <vector>

#include "piezo_compensation/features/feature_stream.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/neural_file.h"

namespace piezo::models {

struct LstmShape {
  int inputs = 1;
  int layers = 1;
  int hidden = 29;
};

// Parameters per layer: W (4H × in), U (4H × H), b (4H), gate order i, f, g, o; then the head w (H), b (1).
class LstmNet {
 public:
  static constexpr int kMaxHidden = 256;
  static constexpr int kMaxLayers = 8;
  LstmNet() = default;
  explicit LstmNet(const LstmShape& shape);
  const LstmShape& shape() const { return shape_; }
  std::size_t num_params() const { return num_params_; }
  Eigen::VectorXd initial_params(std::uint64_t seed) const;  // uniform ±1/√H, forget-gate bias 1

  // One time step of all layers for one sample. h, c: layers × hidden, read from *_in, written to *_out
  // (may alias). Returns the head output for the new top h. Allocation-free; the same operations in the same
  // order as sequence_loss_grad, so streaming reproduces training bit for bit.
  double step(const double* params, const double* x, const double* h_in, const double* c_in, double* h_out,
              double* c_out) const;

  // Sequences in lock-step: xs[τ] is inputs × B for τ = 0 … warmup + T − 1, ys is T × B (targets of the last T
  // steps). Starts from zero state, runs `warmup` steps without gradient, then scores the last T steps.
  // Returns Σ squared errors; adds the truncated-BPTT gradient to *grad when non-null.
  double sequence_loss_grad(const Eigen::VectorXd& params, const std::vector<Eigen::MatrixXd>& xs,
                            const Eigen::MatrixXd& ys, int warmup, Eigen::VectorXd* grad) const;
  // The same with the inputs in one matrix, inputs × (warmup + T)·B: columns τ·B … τ·B + B − 1 are step τ.
  double sequence_loss_grad(const Eigen::VectorXd& params, const Eigen::MatrixXd& x,
                            const Eigen::MatrixXd& ys, int warmup, Eigen::VectorXd* grad) const;

 private:
  LstmShape shape_;
  std::size_t num_params_ = 0;
  std::vector<Eigen::Index> layer_offset_;
  Eigen::Index head_offset_ = 0;
  std::vector<double>
      gate_coef_;  // 3 × 4H: the activation of each gate row (see the kernels in lstm_model.cpp)
  int layer_inputs(int l) const { return l == 0 ? shape_.inputs : shape_.hidden; }
};

class LstmModel : public Model {
 public:
  LstmModel(const features::FeatureSpec& spec, double sample_rate_hz, const LstmShape& shape, Eigen::VectorXd params,
            TargetScale target, int warmup);
  std::string kind() const override { return "lstm"; }
  void reset(double voltage_v, double position_nm) override;
  double predict(const ModelInput& in) const override;
  void commit(const ModelInput& in, double position_nm) override;
  std::unique_ptr<Model> clone() const override { return std::make_unique<LstmModel>(*this); }
  // The recurrent state carries the model's own history, but positions enter only through features.
  bool uses_position_history() const override { return stream_.spec().uses_positions(); }
  std::string fixed_rate_reason() const override { return kLaggedSamplesReason; }
  std::vector<std::string> aux_inputs() const override { return stream_.spec().aux_signals(); }
  YAML::Node to_yaml() const override;
  std::size_t num_parameters() const override { return net_.num_params(); }
  static std::unique_ptr<LstmModel> from_yaml(const YAML::Node& node);

  const LstmNet& net() const { return net_; }
  const Eigen::VectorXd& params() const { return params_; }
  const std::vector<double>& hidden_state() const { return h_; }
  const std::vector<double>& cell_state() const { return c_; }
  YAML::Node training_info;

 private:
  features::FeatureStream stream_;
  double sample_rate_hz_;
  LstmNet net_;
  Eigen::VectorXd params_;
  TargetScale target_;
  int warmup_;
  std::vector<double> h_, c_;  // committed state, layers × hidden
};

}  // namespace piezo::models
