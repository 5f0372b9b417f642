// First-order optimisers over one flat parameter vector (Adam, RMSprop, SGD with optional momentum).
#pragma once

#include <Eigen/Dense>

#include <string>

namespace piezo::training {

enum class OptimizerKind { Adam, RMSprop, SGD };

OptimizerKind parse_optimizer(const std::string& name);  // "adam", "rmsprop", "sgd" (case-insensitive); throws
std::string optimizer_name(OptimizerKind kind);

struct OptimizerConfig {
  OptimizerKind kind = OptimizerKind::Adam;
  double learning_rate = 1e-3;
  double beta1 = 0.9;      // Adam first-moment decay
  double beta2 = 0.999;    // Adam second-moment decay
  double rho = 0.99;       // RMSprop squared-gradient decay (PyTorch default)
  double momentum = 0.0;   // SGD momentum (the study's SGD: plain, 0)
  double epsilon = 1e-8;
};

class Optimizer {
 public:
  Optimizer(const OptimizerConfig& config, Eigen::Index num_params);
  // One update of `params` with gradient `grad` of the loss (minimised).
  void step(Eigen::VectorXd& params, const Eigen::VectorXd& grad);
  // Forget moments (after the parameterisation changed, e.g. a KAN grid update).
  void reset();
  const OptimizerConfig& config() const { return config_; }

 private:
  OptimizerConfig config_;
  Eigen::VectorXd m_, v_;
  long t_ = 0;
};

}  // namespace piezo::training
