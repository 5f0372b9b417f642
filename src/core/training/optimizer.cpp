#include "piezo_compensation/training/optimizer.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <stdexcept>

namespace piezo::training {

OptimizerKind parse_optimizer(const std::string& name) {
  std::string n = name;
  std::transform(n.begin(), n.end(), n.begin(), [](unsigned char c) { return std::tolower(c); });
  if (n == "adam") return OptimizerKind::Adam;
  if (n == "rmsprop") return OptimizerKind::RMSprop;
  if (n == "sgd") return OptimizerKind::SGD;
  throw std::runtime_error("unknown optimizer '" + name + "' (known: adam, rmsprop, sgd)");
}

std::string optimizer_name(OptimizerKind kind) {
  switch (kind) {
    case OptimizerKind::Adam: return "adam";
    case OptimizerKind::RMSprop: return "rmsprop";
    case OptimizerKind::SGD: return "sgd";
  }
  return "adam";
}

Optimizer::Optimizer(const OptimizerConfig& config, Eigen::Index num_params) : config_(config) {
  if (!(config.learning_rate > 0.0) || !std::isfinite(config.learning_rate))
    throw std::runtime_error("optimizer learning_rate must be a positive number");
  m_ = Eigen::VectorXd::Zero(num_params);
  v_ = Eigen::VectorXd::Zero(num_params);
}

void Optimizer::reset() {
  m_.setZero();
  v_.setZero();
  t_ = 0;
}

void Optimizer::step(Eigen::VectorXd& params, const Eigen::VectorXd& grad) {
  const double lr = config_.learning_rate;
  switch (config_.kind) {
    case OptimizerKind::Adam: {
      ++t_;
      m_ = config_.beta1 * m_ + (1.0 - config_.beta1) * grad;
      v_ = config_.beta2 * v_ + (1.0 - config_.beta2) * grad.cwiseAbs2();
      const double c1 = 1.0 - std::pow(config_.beta1, static_cast<double>(t_));
      const double c2 = 1.0 - std::pow(config_.beta2, static_cast<double>(t_));
      params.array() -= lr * (m_.array() / c1) / ((v_.array() / c2).sqrt() + config_.epsilon);
      break;
    }
    case OptimizerKind::RMSprop:
      v_ = config_.rho * v_ + (1.0 - config_.rho) * grad.cwiseAbs2();
      params.array() -= lr * grad.array() / (v_.array().sqrt() + config_.epsilon);
      break;
    case OptimizerKind::SGD:
      if (config_.momentum > 0.0) {
        m_ = config_.momentum * m_ + grad;
        params -= lr * m_;
      } else {
        params -= lr * grad;
      }
      break;
  }
}

}  // namespace piezo::training
