// Native tree-structured Parzen estimator (TPE) search, univariate like Optuna's default sampler: random
// start-up trials, then each parameter drawn from the density of the best γ fraction of trials divided by the
// density of the rest. N trials within a time budget, deterministic for a seed (no Python in the loop).
#pragma once

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <functional>
#include <limits>
#include <map>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "piezo_compensation/training/fit_request.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/trainer.h"

namespace piezo::training {

struct ParamDef {
  enum class Type { Int, Float, LogFloat, Categorical };
  std::string name;
  Type type = Type::Float;
  double low = 0.0, high = 1.0;        // inclusive bounds (Int, Float, LogFloat)
  std::vector<std::string> choices;    // Categorical
};

struct TrialParams {
  std::map<std::string, double> number;       // Int (integral value), Float, LogFloat
  std::map<std::string, std::string> choice;  // Categorical
  std::string to_string() const;              // "depth=1 lr=0.001 optimizer=adam"
};

struct TrialRecord {
  TrialParams params;
  double value = std::numeric_limits<double>::infinity();  // objective (lower is better); inf = failed
  double seconds = 0.0;
};

struct SearchConfig {
  int trials = 20;
  double time_budget_s = 0.0;   // >0: no new trial starts after this
  std::uint64_t seed = 1;
  int startup_trials = 8;       // random trials before TPE
  double gamma = 0.25;          // fraction of trials counted as good
  int candidates = 24;          // samples from the good density scored per parameter
  ProgressFn progress;  // (trial, trials, "trial")
};

struct SearchResult {
  std::vector<TrialRecord> trials;
  std::size_t best = 0;  // index into trials
  const TrialRecord& best_trial() const { return trials.at(best); }
};

// The objective gets the trial's parameters, its index and the seconds left of the budget (inf without one);
// it returns the value to minimise (a failed trial may throw or return inf; it then counts as the worst).
using TrialObjective = std::function<double(const TrialParams&, int trial, double seconds_left)>;

SearchResult tpe_search(const std::vector<ParamDef>& space, const SearchConfig& config, const TrialObjective& objective);

// The study's spaces (Table 2): dense depth 1–5, width 1–20; LSTM layers 1–5, hidden 4–64; optimiser
// {adam, rmsprop, sgd}; learning rate 1e-5…1e-1 log. KAN: hidden width 1–10, grid 3–20, spline order 1–4.
std::vector<ParamDef> dense_search_space();
std::vector<ParamDef> lstm_search_space();
std::vector<ParamDef> kan_search_space();

// `cfg` with the trial's optimiser (when the space has one) and learning rate.
inline TrainerConfig with_trial_optimizer(TrainerConfig cfg, const TrialParams& p) {
  if (p.choice.count("optimizer")) cfg.optimizer.kind = parse_optimizer(p.choice.at("optimizer"));
  cfg.optimizer.learning_rate = p.number.at("learning_rate");
  return cfg;
}

// The neural kinds' tuning: TPE over `space` with trials of `tune_epochs` (option; default the full epochs),
// then the winner retrained with the full `cfg.epochs` while time is left, keeping the better of the two.
// `train(params, config)` applies the trial's shape and optimiser from `params` and trains with `config`, whose
// epochs, seed (request seed + trial), time budget and (no) progress are already set; it returns a trial with
// `model` (a pointer) and `validation_mse`. The search is recorded in the winner's training_info["tuning"].
template <typename Train>
auto tune_and_retrain(const std::string& kind, const std::vector<ParamDef>& space, const FitRequest& request,
                      const TrainerConfig& cfg, Train&& train) {
  using Trial = std::invoke_result_t<Train&, const TrialParams&, TrainerConfig>;
  Trial best;
  SearchConfig sc;
  sc.trials = request.tune_trials;
  sc.time_budget_s = request.time_budget_s;
  sc.seed = request.seed;
  sc.progress = request.progress;
  const int tune_epochs = option_int(request.options, "tune_epochs", cfg.epochs);
  const auto t0 = std::chrono::steady_clock::now();
  auto run = [&](const TrialParams& p, int trial, int epochs, double left) {
    TrainerConfig c = cfg;
    c.epochs = epochs;
    c.progress = nullptr;
    c.seed = request.seed + static_cast<std::uint64_t>(trial);
    c.time_budget_s = std::isfinite(left) ? std::max(left, 1e-3) : 0.0;
    return train(p, std::move(c));
  };
  const auto search = tpe_search(space, sc, [&](const TrialParams& p, int trial, double left) {
    Trial t = run(p, trial, tune_epochs, left);
    const double v = t.validation_mse;
    if (v < best.validation_mse) best = std::move(t);
    return v;
  });
  if (!best.model) throw std::runtime_error(kind + ": every tuning trial failed");
  if (tune_epochs < cfg.epochs) {
    const double used = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const double left =
        request.time_budget_s > 0.0 ? request.time_budget_s - used : std::numeric_limits<double>::infinity();
    if (left > 0.0) {
      Trial t = run(search.best_trial().params, static_cast<int>(search.best), cfg.epochs, left);
      if (t.validation_mse < best.validation_mse) best = std::move(t);
    }
  }
  best.model->training_info["tuning"]["trials"] = static_cast<int>(search.trials.size());
  best.model->training_info["tuning"]["best"] = search.best_trial().params.to_string();
  return best;
}

// A neural kind's fit: one run of `train_default(cfg)`, or with request.tune_trials > 0 tune_and_retrain with
// `train_trial`; the model's meta is set from the request. Returns the model.
template <typename TrainDefault, typename TrainTrial>
auto fit_or_tune(const std::string& kind, const std::vector<ParamDef>& space, const FitRequest& request,
                 const TrainerConfig& cfg, TrainDefault&& train_default, TrainTrial&& train_trial) {
  auto model = request.tune_trials <= 0 ? train_default(cfg).model
                                        : tune_and_retrain(kind, space, request, cfg, train_trial).model;
  set_fit_meta(*model, request);
  return model;
}

}  // namespace piezo::training
