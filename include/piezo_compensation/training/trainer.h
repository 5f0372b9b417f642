// Mini-batch training of the neural models: a differentiable objective over independent units (samples for
// the dense network and the KAN, truncated sequences for the LSTM), shuffled per epoch, each mini-batch split
// into `threads` contiguous shards whose gradients are summed in a fixed order (deterministic for a seed and a
// thread count), early stopping on a validation objective with the best parameters restored.
// Also the data preparation the three networks share: one-step feature matrices through the FeatureStream,
// the study's default feature selection and standardisation of features and target.
#pragma once

#include <Eigen/Dense>
#include <yaml-cpp/yaml.h>

#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "piezo_compensation/features/feature_stream.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/neural_file.h"
#include "piezo_compensation/training/fit_request.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/optimizer.h"

namespace piezo::training {

// A loss that is a sum over units. Implementations are const and thread-safe: shards run concurrently.
class Objective {
 public:
  virtual ~Objective() = default;
  virtual std::size_t num_units() const = 0;
  // Number of scored samples in one unit (1 for samples, the scored length for sequences).
  virtual std::size_t samples_per_unit() const { return 1; }
  // Sum over units[0..n) of the squared errors; when grad is non-null, adds the gradient of that sum w.r.t.
  // params into *grad (sized to params).
  virtual double loss_sum(const Eigen::VectorXd& params, const std::size_t* units, std::size_t n,
                          Eigen::VectorXd* grad) const = 0;
};

// Objective over the columns of a feature matrix (units = samples) for a network with
// loss_grad(params, x, y, grad) on a batch of columns (the dense network and the KAN).
template <typename Net>
class ColumnObjective : public Objective {
 public:
  ColumnObjective(const Net& net, const Eigen::MatrixXd& x, const Eigen::VectorXd& y) : net_(net), x_(x), y_(y) {}
  std::size_t num_units() const override { return static_cast<std::size_t>(x_.cols()); }
  double loss_sum(const Eigen::VectorXd& params, const std::size_t* units, std::size_t n,
                  Eigen::VectorXd* grad) const override {
    Eigen::MatrixXd xb(x_.rows(), static_cast<Eigen::Index>(n));
    Eigen::VectorXd yb(static_cast<Eigen::Index>(n));
    for (std::size_t i = 0; i < n; ++i) {
      xb.col(static_cast<Eigen::Index>(i)) = x_.col(static_cast<Eigen::Index>(units[i]));
      yb[static_cast<Eigen::Index>(i)] = y_[static_cast<Eigen::Index>(units[i])];
    }
    return net_.loss_grad(params, xb, yb, grad);
  }

 private:
  const Net& net_;
  const Eigen::MatrixXd& x_;
  const Eigen::VectorXd& y_;
};

struct TrainerConfig {
  OptimizerConfig optimizer;
  int epochs = 50;
  int batch_size = 256;          // units per mini-batch
  int patience = 5;              // epochs without validation improvement before stopping (0 = never stop early)
  double min_rel_improvement = 1e-4;  // a validation loss counts as better below best * (1 - this)
  std::uint64_t seed = 1;
  int threads = 2;
  double time_budget_s = 0.0;    // >0: stop after the epoch that exceeds it (depends on the machine's load)
  long max_steps = 0;            // >0: stop after this many optimiser steps (a budget that is deterministic)
  double grad_clip_norm = 0.0;   // >0: scale the mini-batch gradient down to this norm
  ProgressFn progress;   // called per epoch: (epoch, epochs, "epoch")
  // Called after each epoch; may change params (KAN grid update). Return true when it did: the optimiser
  // moments and the best-so-far record are then reset, since they refer to the old parameterisation.
  std::function<bool(Eigen::VectorXd& params, int epoch)> on_epoch_end;
};

struct TrainResult {
  Eigen::VectorXd params;         // best by validation (or the last when there is no validation)
  double best_validation_mse = std::numeric_limits<double>::infinity();  // standardised units
  double final_train_mse = std::numeric_limits<double>::infinity();
  int epochs_run = 0;
  int best_epoch = 0;
  bool stopped_early = false;
  bool hit_time_budget = false;
  bool hit_step_budget = false;
  long steps = 0;                 // optimiser steps taken
  double seconds = 0.0;
  std::vector<double> train_mse, validation_mse;  // per epoch
};

// Mean squared error of the objective over all its units (parallel over shards, deterministic).
double mean_loss(const Objective& objective, const Eigen::VectorXd& params, int threads);

// Trains from `initial`. validation may be null (then no early stopping; the last parameters are kept).
TrainResult train(const Objective& objective, const Objective* validation, const Eigen::VectorXd& initial,
                  const TrainerConfig& config);

// ---- data preparation shared by the neural kinds ----------------------------------------------------------

// Raw (unstandardised) or standardised one-step features of one axis: column t is the feature vector of sample
// t with measured positions up to t-1 (column-major, size() × n).
Eigen::MatrixXd feature_matrix(const features::FeatureSpec& spec, const io::Dataset& data, const std::string& axis);

// Target standardisation and output rails from the training positions.
models::TargetScale fit_target_scale(const std::vector<double>& position_nm);

// Training and validation parts of a FitRequest: its validation set, or the last `fraction` of train by time.
struct SplitData {
  io::Dataset train, validation;
};
SplitData split_for_validation(const FitRequest& request, double fraction = 0.1);

}  // namespace piezo::training

namespace piezo::training {

// Everything the neural kinds' fit functions need: the standardised feature spec (the request's `features`
// option resolved by fit_common.h's resolve_features, default voltage_lasso: the lasso's survivors among the voltage-only candidates placed on the training data), one-step feature matrices and standardised targets of both parts.
struct PreparedData {
  features::FeatureSpec spec;
  double sample_rate_hz = 11.0;
  models::TargetScale target;
  Eigen::MatrixXd x_train, x_validation;   // features × samples
  Eigen::VectorXd y_train, y_validation;   // standardised positions
};
// The request's options are checked first: the common neural keys plus the kind's `own_keys`.
PreparedData prepare_data(const FitRequest& request, const std::string& kind, const std::vector<std::string>& own_keys);

// Trainer settings from the request and its options (optimizer, learning_rate, epochs, batch_size, patience).
TrainerConfig trainer_config(const FitRequest& request, int default_epochs, int default_batch_size);

// What every neural fit records in the model file's `training:` node, in this order: optimizer, learning_rate,
// the batch size under `batch_key`, `extra` (the kind's own entries), epochs_run, best_epoch, stopped_early,
// validation_rmse_nm, train_seconds. Also stores validation_rmse_nm in m.meta.validation.
YAML::Node record_training(models::Model& m, const TrainerConfig& cfg, const TrainResult& r, double target_scale_nm,
                           const std::string& batch_key,
                           const std::vector<std::pair<std::string, YAML::Node>>& extra = {});
// One trained network of a neural kind and its validation loss: what tune_and_retrain compares.
template <typename M>
struct NeuralTrial {
  std::unique_ptr<M> model;
  double validation_mse = std::numeric_limits<double>::infinity();
};
// The trial of a finished training run, its training_info recorded (record_training's arguments).
template <typename M>
NeuralTrial<M> make_trial(std::unique_ptr<M> model, const TrainerConfig& cfg, const TrainResult& r,
                          double target_scale_nm, const std::string& batch_key,
                          const std::vector<std::pair<std::string, YAML::Node>>& extra = {}) {
  NeuralTrial<M> t;
  t.validation_mse = r.best_validation_mse;
  t.model = std::move(model);
  t.model->training_info = record_training(*t.model, cfg, r, target_scale_nm, batch_key, extra);
  return t;
}
// m.meta from the request (make_meta), keeping the validation figures the fit stored.
void set_fit_meta(models::Model& m, const FitRequest& request);

// Option keys every neural kind accepts (besides its own architecture keys).
std::vector<std::string> common_neural_option_keys();

}  // namespace piezo::training
