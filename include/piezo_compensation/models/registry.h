// Model kinds register themselves (loader, trainer, optional C export) so that the model file, `piezo fit`,
// `piezo eval`, `piezo export`, the residual tool and the predictor node handle every kind the same way.
// Registration is static (PIEZO_REGISTER_MODEL_KIND in the kind's .cpp); piezo_core is a shared library,
// so every registrar runs when the library loads.
#pragma once

#include <yaml-cpp/yaml.h>

#include <functional>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"

namespace piezo::models {

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
};

struct ModelKind {
  std::string name;          // "linear", "dense", ...
  std::string description;   // one line for --help
  std::function<ModelPtr(const YAML::Node& model_node)> load;   // from the file's `model:` node; throws on bad keys
  std::function<ModelPtr(const FitRequest&)> fit;               // may be empty for kinds that cannot be fitted alone
  std::function<std::string(const Model&, const std::string& prefix)> export_c99;  // may be empty
};

void register_model_kind(ModelKind kind);
const ModelKind& model_kind(const std::string& name);  // throws std::runtime_error listing the known kinds
std::vector<std::string> model_kind_names();

struct ModelKindRegistrar {
  explicit ModelKindRegistrar(ModelKind kind) { register_model_kind(std::move(kind)); }
};

}  // namespace piezo::models

#define PIEZO_CONCAT_INNER(a, b) a##b
#define PIEZO_CONCAT(a, b) PIEZO_CONCAT_INNER(a, b)
#define PIEZO_REGISTER_MODEL_KIND(...) \
  static const ::piezo::models::ModelKindRegistrar PIEZO_CONCAT(piezo_model_kind_registrar_, __LINE__)(__VA_ARGS__)
