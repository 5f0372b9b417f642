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
#include <string>
#include <vector>

#include "piezo_compensation/features/feature_stream.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/registry.h"
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

struct TrainerConfig {
  OptimizerConfig optimizer;
  int epochs = 50;
  int batch_size = 256;          // units per mini-batch
  int patience = 5;              // epochs without validation improvement before stopping (0 = never stop early)
  double min_rel_improvement = 1e-4;  // a validation loss counts as better below best * (1 - this)
  std::uint64_t seed = 1;
  int threads = 2;
  double time_budget_s = 0.0;    // >0: stop after the epoch that exceeds it
  double grad_clip_norm = 0.0;   // >0: scale the mini-batch gradient down to this norm
  models::ProgressFn progress;   // called per epoch: (epoch, epochs, "epoch")
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

struct TargetScale {
  double mean_nm = 0.0;
  double scale_nm = 1.0;
  // Output rails: the training range widened by half its span each side. Networks extrapolate without bound;
  // fed back in free-run they can run away to ±inf, so outputs are held to physically plausible values.
  double output_min_nm = -std::numeric_limits<double>::infinity();
  double output_max_nm = std::numeric_limits<double>::infinity();
  double to_nm(double z) const {
    const double y = mean_nm + scale_nm * z;
    return y < output_min_nm ? output_min_nm : (y > output_max_nm ? output_max_nm : y);
  }
  double to_z(double nm) const { return (nm - mean_nm) / scale_nm; }
  YAML::Node to_yaml() const;
  static TargetScale from_yaml(const YAML::Node& node, const std::string& what);  // rails optional
  std::string c99_expression(const std::string& z) const;  // to_nm in C
};
TargetScale fit_target_scale(const std::vector<double>& position_nm);

// Training and validation parts of a FitRequest: its validation set, or the last `fraction` of train by time.
struct SplitData {
  io::Dataset train, validation;
};
SplitData split_for_validation(const models::FitRequest& request, double fraction = 0.1);

// ---- small YAML helpers for the kinds' loaders ------------------------------------------------------------

// Throws naming `what` and the offending key when node has a key outside `allowed`.
void check_keys(const YAML::Node& node, const std::vector<std::string>& allowed, const std::string& what);
// Required finite scalar / vector under key.
double yaml_double(const YAML::Node& node, const std::string& key, const std::string& what);
// Required integer in [low, high] under key.
int yaml_int(const YAML::Node& node, const std::string& key, const std::string& what, int low, int high);
std::vector<double> yaml_doubles(const YAML::Node& node, const std::string& key, const std::string& what,
                                 std::size_t expected_size);
YAML::Node flow_sequence(const Eigen::VectorXd& values);

// What every neural kind's model-file node shares, read and checked in one place: the kind, the sample rate, the
// feature spec, the target scale and the hyperparameters map (keys checked against `hyperparameter_keys`).
// `extra_keys` are the kind's own further top-level keys (e.g. KAN's "grids"). Errors name "<kind> model".
struct NeuralFileHeader {
  double sample_rate_hz = 0.0;
  features::FeatureSpec spec;
  TargetScale target;
  YAML::Node hyperparameters;
};
NeuralFileHeader read_neural_file_header(const YAML::Node& node, const std::string& kind,
                                         const std::vector<std::string>& hyperparameter_keys,
                                         const std::vector<std::string>& extra_keys = {});

}  // namespace piezo::training

namespace piezo::training {

// Everything the neural kinds' fit functions need: the standardised feature spec (the request's `features`
// option resolved by fit_common.h's resolve_features, default the study's selection), one-step feature matrices and standardised targets of both parts.
struct PreparedData {
  features::FeatureSpec spec;
  double sample_rate_hz = 11.0;
  TargetScale target;
  Eigen::MatrixXd x_train, x_validation;   // features × samples
  Eigen::VectorXd y_train, y_validation;   // standardised positions
};
PreparedData prepare_data(const models::FitRequest& request);

// Trainer settings from the request and its options (optimizer, learning_rate, epochs, batch_size, patience).
TrainerConfig trainer_config(const models::FitRequest& request, int default_epochs, int default_batch_size);

// Option keys every neural kind accepts (besides its own architecture keys).
std::vector<std::string> common_neural_option_keys();

}  // namespace piezo::training
