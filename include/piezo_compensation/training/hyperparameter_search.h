// Native tree-structured Parzen estimator (TPE) search, univariate like Optuna's default sampler: random
// start-up trials, then each parameter drawn from the density of the best γ fraction of trials divided by the
// density of the rest. N trials within a time budget, deterministic for a seed (no Python in the loop).
#pragma once

#include <cstdint>
#include <functional>
#include <limits>
#include <map>
#include <string>
#include <vector>

#include "piezo_compensation/models/registry.h"

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
  models::ProgressFn progress;  // (trial, trials, "trial")
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

}  // namespace piezo::training
