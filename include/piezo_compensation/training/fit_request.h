// What a fit is asked to do: the data (held out by time), the axis, the kind's options, tuning and budget.
#pragma once

#include <yaml-cpp/yaml.h>

#include <cstdint>
#include <functional>
#include <string>

#include "piezo_compensation/io/dataset.h"

namespace piezo::models {
class Model;
}

namespace piezo::training {

class LassoFeatureCache;  // fit_common.h

// Progress of a long fit: done/total in the fit's own unit (epochs, trials, λ values), for the progress bar.
using ProgressFn = std::function<void(double done, double total, const std::string& what)>;

struct FitRequest {
  const io::Dataset* train = nullptr;        // training part (held out by time from validation/test)
  const io::Dataset* validation = nullptr;   // validation part for early stopping / selection (may be null)
  std::string axis = "c";
  YAML::Node options;                        // kind-specific hyperparameters (from --set key=value or a YAML file)
  int tune_trials = 0;                       // >0: hyperparameter search with this many trials
  double time_budget_s = 0.0;                // >0: stop tuning/training when exceeded
  std::uint64_t seed = 1;
  int threads = 2;
  ProgressFn progress;                       // may be empty
  // Optional: the lasso feature sets ("lasso", "voltage_lasso") of fits on the same data, resolved once for all of
  // them (model selection's candidates); null: each fit runs its own lasso. Not owned.
  LassoFeatureCache* lasso_cache = nullptr;
  // Optional, for options that ask for the output map: the same kind fitted on the same data without it
  // (model selection's plain candidate), cloned as the alternation's first fit instead of fitted again. Not
  // owned.
  const models::Model* plain_fit = nullptr;
};

}  // namespace piezo::training
