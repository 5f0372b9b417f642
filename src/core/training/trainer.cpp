#include "piezo_compensation/training/trainer.h"

#include "piezo_compensation/models/yaml_fields.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <numeric>
#include <random>
#include <sstream>
#include <stdexcept>

namespace piezo::training {

namespace {

using Clock = std::chrono::steady_clock;

double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// Shards of a contiguous unit list: at least 2 (so results do not change between 1 and 2 threads), more with
// more threads; few shards keep each one's matrices large enough to be efficient.
int shard_count(int threads, std::size_t n) {
  const int s = std::max(2, threads);
  return static_cast<int>(std::min<std::size_t>(static_cast<std::size_t>(s), std::max<std::size_t>(n, 1)));
}

// Sum of losses (and gradients) over units split into shards computed concurrently, summed in shard order.
double sharded_loss(const Objective& obj, const Eigen::VectorXd& params, const std::size_t* units, std::size_t n,
                    Eigen::VectorXd* grad, int threads, std::vector<Eigen::VectorXd>& shard_grads) {
  const int shards = shard_count(threads, n);
  std::vector<double> loss(static_cast<std::size_t>(shards), 0.0);
  if (grad) shard_grads.resize(static_cast<std::size_t>(shards));
  const int nthreads = std::max(1, std::min(threads, shards));
#pragma omp parallel for num_threads(nthreads) schedule(static, 1)
  for (int s = 0; s < shards; ++s) {
    const std::size_t b = n * static_cast<std::size_t>(s) / static_cast<std::size_t>(shards);
    const std::size_t e = n * static_cast<std::size_t>(s + 1) / static_cast<std::size_t>(shards);
    Eigen::VectorXd* g = nullptr;
    if (grad) {
      shard_grads[static_cast<std::size_t>(s)].setZero(params.size());
      g = &shard_grads[static_cast<std::size_t>(s)];
    }
    loss[static_cast<std::size_t>(s)] = e > b ? obj.loss_sum(params, units + b, e - b, g) : 0.0;
  }
  double total = 0.0;
  for (int s = 0; s < shards; ++s) {
    total += loss[static_cast<std::size_t>(s)];
    if (grad) *grad += shard_grads[static_cast<std::size_t>(s)];
  }
  return total;
}

}  // namespace

double mean_loss(const Objective& objective, const Eigen::VectorXd& params, int threads) {
  const std::size_t n = objective.num_units();
  if (n == 0) return std::numeric_limits<double>::quiet_NaN();
  std::vector<std::size_t> units(n);
  std::iota(units.begin(), units.end(), std::size_t{0});
  // Fixed chunks summed in order: the same value for 1 or 2 threads.
  const std::size_t chunk = 8192;
  double total = 0.0;
  std::vector<Eigen::VectorXd> unused;
  for (std::size_t b = 0; b < n; b += chunk) {
    const std::size_t e = std::min(n, b + chunk);
    total += sharded_loss(objective, params, units.data() + b, e - b, nullptr, threads, unused);
  }
  return total / static_cast<double>(n * objective.samples_per_unit());
}

TrainResult train(const Objective& objective, const Objective* validation, const Eigen::VectorXd& initial,
                  const TrainerConfig& config) {
  if (config.epochs < 1) throw std::runtime_error("training: epochs must be at least 1");
  if (config.batch_size < 1) throw std::runtime_error("training: batch_size must be at least 1");
  const std::size_t n = objective.num_units();
  if (n == 0) throw std::runtime_error("training: no training samples (data shorter than the feature windows?)");
  if (validation && validation->num_units() == 0) validation = nullptr;

  const auto t0 = Clock::now();
  const int threads = std::max(1, config.threads);
  TrainResult result;
  Eigen::VectorXd params = initial;
  Optimizer opt(config.optimizer, params.size());
  std::mt19937_64 rng(config.seed);
  std::vector<std::size_t> order(n);
  std::iota(order.begin(), order.end(), std::size_t{0});
  std::vector<Eigen::VectorXd> shard_grads;
  Eigen::VectorXd grad(params.size());
  const std::size_t batch = static_cast<std::size_t>(config.batch_size);
  int since_best = 0;
  result.params = params;

  for (int epoch = 1; epoch <= config.epochs; ++epoch) {
    // Fisher–Yates with our own draws: the same order on every standard library.
    for (std::size_t i = n - 1; i > 0; --i) std::swap(order[i], order[rng() % (i + 1)]);
    double train_sum = 0.0;
    std::size_t seen = 0;
    std::size_t batches = 0;
    for (std::size_t b = 0; b < n; b += batch) {
      const std::size_t e = std::min(n, b + batch);
      grad.setZero();
      train_sum += sharded_loss(objective, params, order.data() + b, e - b, &grad, threads, shard_grads);
      seen += e - b;
      grad /= static_cast<double>((e - b) * objective.samples_per_unit());
      if (!grad.allFinite()) throw std::runtime_error("training diverged: non-finite gradient (lower the learning rate)");
      if (config.grad_clip_norm > 0.0) {
        const double norm = grad.norm();
        if (norm > config.grad_clip_norm) grad *= config.grad_clip_norm / norm;
      }
      opt.step(params, grad);
      ++result.steps;
      if (config.max_steps > 0 && result.steps >= config.max_steps) {
        result.hit_step_budget = true;
        break;
      }
      if (config.time_budget_s > 0.0 && (++batches % 64) == 0 && seconds_since(t0) > config.time_budget_s) {
        result.hit_time_budget = true;
        break;
      }
    }
    const double train_mse = train_sum / static_cast<double>(seen * objective.samples_per_unit());
    result.train_mse.push_back(train_mse);
    result.final_train_mse = train_mse;
    result.epochs_run = epoch;

    bool reparameterised = false;
    if (config.on_epoch_end) reparameterised = config.on_epoch_end(params, epoch);
    if (reparameterised) {
      opt.reset();
      result.best_validation_mse = std::numeric_limits<double>::infinity();
      since_best = 0;
    }

    if (validation) {
      const double val = mean_loss(*validation, params, threads);
      result.validation_mse.push_back(val);
      if (!std::isfinite(val)) throw std::runtime_error("training diverged: non-finite validation loss");
      if (val < result.best_validation_mse * (1.0 - config.min_rel_improvement)) {
        result.best_validation_mse = val;
        result.best_epoch = epoch;
        result.params = params;
        since_best = 0;
      } else if (val < result.best_validation_mse) {
        // Small gain: keep the better weights but count towards patience.
        result.best_validation_mse = val;
        result.best_epoch = epoch;
        result.params = params;
        ++since_best;
      } else {
        ++since_best;
      }
    } else {
      result.params = params;
      result.best_epoch = epoch;
    }
    if (config.progress) config.progress(epoch, config.epochs, "epoch");
    if (result.hit_time_budget || result.hit_step_budget) break;
    if (config.time_budget_s > 0.0 && seconds_since(t0) > config.time_budget_s) {
      result.hit_time_budget = true;
      break;
    }
    if (validation && config.patience > 0 && since_best >= config.patience) {
      result.stopped_early = true;
      break;
    }
  }
  result.seconds = seconds_since(t0);
  return result;
}

// ---- data preparation ---------------------------------------------------------------------------------------

Eigen::MatrixXd feature_matrix(const features::FeatureSpec& spec, const io::Dataset& data, const std::string& axis) {
  const io::AxisSeries& ax = data.axis(axis);
  const std::size_t n = data.size();
  AuxRows aux(data, spec.aux_signals(), axis);  // the one resolver (models/model_stream.h)
  features::FeatureStream stream(spec, data.sample_rate_hz());
  Eigen::MatrixXd x(static_cast<Eigen::Index>(stream.size()), static_cast<Eigen::Index>(n));
  if (n == 0) return x;
  stream.reset(ax.voltage_v[0], ax.position_nm[0]);
  for (std::size_t t = 0; t < n; ++t) {
    if (t > 0 && data.starts_recording(t)) stream.reset(ax.voltage_v[t], ax.position_nm[t]);  // its own history
    features::ModelInput in{ax.voltage_v[t], aux.at(t)};
    stream.compute(in, x.col(static_cast<Eigen::Index>(t)).data());
    stream.commit(in, ax.position_nm[t]);
  }
  return x;
}

models::TargetScale fit_target_scale(const std::vector<double>& position_nm) {
  if (position_nm.empty()) throw std::runtime_error("no target samples");
  models::TargetScale s;
  double sum = 0.0;
  for (double p : position_nm) sum += p;
  s.mean_nm = sum / static_cast<double>(position_nm.size());
  double ss = 0.0;
  for (double p : position_nm) ss += (p - s.mean_nm) * (p - s.mean_nm);
  const double sd = std::sqrt(ss / static_cast<double>(position_nm.size()));
  s.scale_nm = sd > 1e-9 ? sd : 1.0;
  const auto [lo, hi] = std::minmax_element(position_nm.begin(), position_nm.end());
  const double half_span = 0.5 * std::max(*hi - *lo, s.scale_nm);
  s.output_min_nm = *lo - half_span;
  s.output_max_nm = *hi + half_span;
  return s;
}

SplitData split_for_validation(const FitRequest& request, double fraction) {
  if (!request.train) throw std::runtime_error("fit: no training data");
  SplitData out;
  if (request.validation && !request.validation->empty()) {
    out.train = *request.train;
    out.validation = *request.validation;
    return out;
  }
  const std::size_t n = request.train->size();
  const std::size_t cut = n - static_cast<std::size_t>(static_cast<double>(n) * fraction);
  if (cut < 2 || cut >= n) throw std::runtime_error("fit: too few training samples to hold out a validation part");
  out.train = request.train->slice(0, cut);
  out.validation = request.train->slice(cut, n);
  return out;
}

}  // namespace piezo::training

namespace piezo::training {

PreparedData prepare_data(const FitRequest& request, const std::string& kind, const std::vector<std::string>& own_keys) {
  std::vector<std::string> keys = common_neural_option_keys();
  keys.insert(keys.end(), own_keys.begin(), own_keys.end());
  if (request.options && request.options.IsMap()) models::check_keys(request.options, keys, kind + " options");
  const double fraction = option_num(request.options, "validation_fraction", 0.1);
  if (!(fraction > 0.0 && fraction < 0.9)) throw std::runtime_error("option 'validation_fraction' must be in (0, 0.9)");
  const SplitData split = split_for_validation(request, fraction);
  PreparedData p;
  p.sample_rate_hz = split.train.sample_rate_hz();
  p.spec = resolve_features(request, "voltage_lasso");
  if (p.spec.size() == 0) throw std::runtime_error("fit: the feature spec has no features");
  p.target = fit_target_scale(split.train.axis(request.axis).position_nm);
  auto targets = [&](const io::Dataset& d) {
    const auto& pos = d.axis(request.axis).position_nm;
    Eigen::VectorXd y(static_cast<Eigen::Index>(pos.size()));
    for (std::size_t i = 0; i < pos.size(); ++i) y[static_cast<Eigen::Index>(i)] = p.target.to_z(pos[i]);
    return y;
  };
  p.x_train = feature_matrix(p.spec, split.train, request.axis);
  p.y_train = targets(split.train);
  p.x_validation = feature_matrix(p.spec, split.validation, request.axis);
  p.y_validation = targets(split.validation);
  if (!p.x_train.allFinite()) throw std::runtime_error("fit: non-finite training features");
  return p;
}

TrainerConfig trainer_config(const FitRequest& request, int default_epochs, int default_batch_size) {
  TrainerConfig c;
  c.optimizer.kind = parse_optimizer(option_str(request.options, "optimizer", "adam"));
  c.optimizer.learning_rate = option_num(request.options, "learning_rate", 1e-3);
  if (!(c.optimizer.learning_rate > 0.0)) throw std::runtime_error("option 'learning_rate' must be positive");
  c.max_steps = option_int(request.options, "steps", 0);
  if (c.max_steps < 0) throw std::runtime_error("option 'steps' must be ≥ 0 (0: no step budget)");
  // A step budget alone: as many epochs as it takes (the data's size sets the steps per epoch, not the budget).
  const bool epochs_given = request.options && request.options.IsMap() && request.options["epochs"];
  c.epochs = option_int(request.options, "epochs", c.max_steps > 0 && !epochs_given ? 1000000 : default_epochs);
  if (c.epochs < 1) throw std::runtime_error("option 'epochs' must be at least 1");
  c.batch_size = option_int(request.options, "batch_size", default_batch_size);
  if (c.batch_size < 1) throw std::runtime_error("option 'batch_size' must be at least 1");
  c.patience = option_int(request.options, "patience", 5);
  c.grad_clip_norm = option_num(request.options, "grad_clip_norm", 0.0);
  c.seed = request.seed;
  c.threads = std::max(1, request.threads);
  c.time_budget_s = request.time_budget_s;
  c.progress = request.progress;
  return c;
}

YAML::Node record_training(models::Model& m, const TrainerConfig& cfg, const TrainResult& r, double target_scale_nm,
                           const std::string& batch_key,
                           const std::vector<std::pair<std::string, YAML::Node>>& extra) {
  YAML::Node info;
  info["optimizer"] = optimizer_name(cfg.optimizer.kind);
  info["learning_rate"] = cfg.optimizer.learning_rate;
  info[batch_key] = cfg.batch_size;
  for (const auto& [key, value] : extra) info[key] = value;
  info["epochs_run"] = r.epochs_run;
  info["best_epoch"] = r.best_epoch;
  info["stopped_early"] = r.stopped_early;
  if (cfg.max_steps > 0) info["steps"] = static_cast<long long>(r.steps);
  info["validation_rmse_nm"] = std::sqrt(r.best_validation_mse) * target_scale_nm;
  info["train_seconds"] = r.seconds;
  m.meta.validation["validation_rmse_nm"] = std::sqrt(r.best_validation_mse) * target_scale_nm;
  return info;
}

void set_fit_meta(models::Model& m, const FitRequest& request) {
  const auto validation = m.meta.validation;
  m.meta = make_meta(request);
  m.meta.validation = validation;
}

std::vector<std::string> common_neural_option_keys() {
  return {"features", "optimizer", "learning_rate", "epochs", "batch_size", "patience", "grad_clip_norm",
          "validation_fraction", "tune_epochs", "steps"};
}

}  // namespace piezo::training
