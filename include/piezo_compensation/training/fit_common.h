// Shared pieces of every fit: running the feature stream over a data set in one-step mode, standardisation,
// sufficient statistics (Gram sums) per contiguous time block, design matrices, and the feature choice of a
// FitRequest. Used by the linear, physics and neural kinds alike.
#pragma once

#include <Eigen/Dense>

#include <functional>
#include <map>
#include <mutex>
#include <string>
#include <vector>

#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/features/feature_stream.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/training/fit_request.h"

namespace piezo::training {

// The aux columns a feature spec reads, per sample in ModelInput::aux order: the one resolver of models/, for the
// modelled axis (its own position is never an input; another axis' is read as the latest known reading).
class AuxRows : public models::InputResolver {
 public:
  AuxRows(const io::Dataset& data, const std::vector<std::string>& names, const std::string& own_axis)
      : models::InputResolver(data, names, own_axis) {}
};

// Streams `spec` over data[begin, end) of one axis in one-step mode (positions committed are the measured
// ones), calling fn(i, features, target_nm) per sample. The stream starts from reset(V_begin, D_begin).
void for_each_sample(const features::FeatureSpec& spec, const io::Dataset& data, const std::string& axis,
                     const std::function<void(std::size_t, const double*, double)>& fn, std::size_t begin = 0,
                     std::size_t end = SIZE_MAX);

// Returns spec with mean/scale set from the raw features over data (scale = std, 1 for constant features).
features::FeatureSpec fit_standardisation(features::FeatureSpec spec, const io::Dataset& data, const std::string& axis);

// Sufficient statistics of y = Xβ + b over some samples.
struct GramStats {
  double n = 0, sy = 0, syy = 0;
  Eigen::VectorXd sx, sxy;
  Eigen::MatrixXd sxx;
  explicit GramStats(std::size_t p = 0);
  GramStats& operator+=(const GramStats& o);
  GramStats& operator-=(const GramStats& o);
  Eigen::VectorXd mean_x() const { return sx / n; }
  double mean_y() const { return sy / n; }
  Eigen::MatrixXd centered_xx() const { return sxx - sx * sx.transpose() / n; }
  Eigen::VectorXd centered_xy() const { return sxy - sx * (sy / n); }
  // Σ (y − b − xᵀβ)² over these samples.
  double sse(const Eigen::VectorXd& beta, double b) const;
};

// Gram sums of the (standardised) features of `spec` over `blocks` contiguous time blocks of equal length
// (one block = all data). Computed in chunks, never holding the N×p matrix.
std::vector<GramStats> block_gram(const features::FeatureSpec& spec, const io::Dataset& data, const std::string& axis,
                                  int blocks, const ProgressFn& progress = {});

// Features and measured targets as dense arrays (one-step mode), every `stride`-th sample.
struct Design {
  Eigen::MatrixXd X;  // rows = samples
  Eigen::VectorXd y;  // measured position [nm]
};
Design build_design(const features::FeatureSpec& spec, const io::Dataset& data, const std::string& axis,
                    std::size_t stride = 1);

// Solves (G + ridge·I) β = c robustly (LDLT, falls back to a pseudo-inverse for singular G).
Eigen::VectorXd solve_normal(const Eigen::MatrixXd& G, const Eigen::VectorXd& c, double ridge);

// The feature spec a fit uses: options["features"] may be a set name ("study", "candidates", "physics",
// "voltage_history": placed on req.train),
// "lasso" (lasso with time-block CV over the candidates placed on req.train; the λ_1se survivors), "voltage_lasso"
// (the same over the candidates that read no position: the neural kinds' default), or a full spec mapping.
// Missing = `default_set`. The result is standardised on req.train.
// With req.lasso_cache, a lasso set already resolved on the same data (same set, axis and data fingerprint) is
// taken from it instead of running the lasso again.
features::FeatureSpec resolve_features(const FitRequest& req, const std::string& default_set);

// The lasso's survivors per (set, axis, training data), before standardisation: several fits on one data set
// (dense, KAN and LSTM all default to voltage_lasso; model selection fits them on the training part and again on
// its first half) run each lasso once. Keyed by the data's fingerprint (its values, not its address), so another
// slice is another entry and a fold never sees a selection made on rows it holds out.
class LassoFeatureCache {
 public:
  // The spec resolved for `key`, or the result of resolve() stored under it (resolve's exceptions pass, nothing
  // is stored then).
  features::FeatureSpec get(const std::string& key, const std::function<features::FeatureSpec()>& resolve);
  std::size_t lassos_run() const {  // how many times resolve() was called
    std::lock_guard<std::mutex> lock(mutex_);
    return runs_;
  }

 private:
  mutable std::mutex mutex_;
  std::map<std::string, features::FeatureSpec> specs_;
  std::size_t runs_ = 0;
};

// Meta common to all kinds: axis, rate, fingerprint and source of the training data, creation time.
models::ModelMeta make_meta(const FitRequest& req);
std::string utc_now_iso8601();

// Small typed accessors for FitRequest::options with clear errors ("option 'lambda': expected a number").
double option_num(const YAML::Node& options, const std::string& key, double def);
int option_int(const YAML::Node& options, const std::string& key, int def);
std::string option_str(const YAML::Node& options, const std::string& key, const std::string& def);
bool option_bool(const YAML::Node& options, const std::string& key, bool def);  // "true" or "false", else throws
// Least-squares y ≈ βᵀx + intercept over the columns of x (features × samples, standardised), with a tiny
// fixed ridge that only settles collinear columns: the linear start of the dense and KAN kinds.
struct ColumnLinearFit {
  Eigen::VectorXd beta;
  double intercept = 0.0;
};
ColumnLinearFit linear_fit_columns(const Eigen::MatrixXd& x, const Eigen::VectorXd& y);

// Option `init` of the dense and KAN kinds: "linear" (default: start at the least-squares linear fit of the
// features) → true, "random" (the plain random start) → false; throws naming the option otherwise.
bool neural_linear_init(const YAML::Node& options);

// Whether validation prefers the variant with errors a over the one with errors b (per sample, same rows): with at
// least 4 blocks of `block` samples, only when a's mean paired difference is lower by more than twice its standard
// error over the block means (errors of a free run are correlated over minutes), so a choice is not made on noise;
// with fewer blocks the paired test has no power and the lower mean error wins, as a plain validation choice.
bool validation_prefers(const std::vector<double>& a, const std::vector<double>& b, std::size_t block);

}  // namespace piezo::training
