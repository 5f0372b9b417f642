#include "piezo_compensation/models/registry.h"

#include <map>
#include <stdexcept>

#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/c_export.h"
#include "piezo_compensation/models/dense_model.h"
#include "piezo_compensation/models/kan_model.h"
#include "piezo_compensation/models/linear_model.h"
#include "piezo_compensation/models/lstm_model.h"
#include "piezo_compensation/models/pi_creep_play_model.h"
#include "piezo_compensation/models/pi_model.h"

namespace piezo::models {

namespace {

// C export of a kind whose model class M has export_c99(prefix).
template <typename M>
std::function<std::string(const Model&, const std::string&)> export_of(const std::string& kind) {
  return [kind](const Model& m, const std::string& prefix) {
    const auto* k = dynamic_cast<const M*>(&m);
    if (!k) throw std::runtime_error("export: not a " + kind + " model");
    return k->export_c99(prefix);
  };
}

// Every built-in kind. A new kind adds one entry here (and its fitter in training/fitters.cpp).
std::map<std::string, ModelKind> built_in_kinds() {
  constexpr AutoCandidacy kDefault = AutoCandidacy::kDefault, kExtra = AutoCandidacy::kExtra;
  const std::vector<ModelKind> list = {
      {"linear", "linear regression on causal features (OLS / ridge / lasso)", &LinearModel::load, &export_c99_linear, kExtra},
      {"pi", "Prandtl–Ishlinskii hysteresis (play operators, analytic inverse)", &PiCreepModel::load, &export_c99_pi, kDefault},
      {"pi_creep_log", "PI hysteresis + logarithmic creep", &PiCreepModel::load, &export_c99_pi, kDefault},
      {"pi_creep_lti", "PI hysteresis + LTI creep (n spring–damper pairs)", &PiCreepModel::load, &export_c99_pi, kDefault},
      {"pi_creep_fractional", "PI hysteresis + fractional-order creep (multi-mode s^-alpha)", &PiCreepModel::load,
       &export_c99_pi, kDefault},
      {"pi_creep_prony", "PI hysteresis + creep spectrum (non-negative first-order modes on a log tau grid)",
       &PiCreepModel::load, &export_c99_pi, kDefault},
      {"pi_creep_play", "PI hysteresis + creep per play operator (non-negative low-passes of each play, Krejčí–Kuhnen)",
       &PiCreepPlayModel::load, &export_c99_pi_creep_play, kExtra},
      {"preisach", "discrete Preisach hysteresis (play outputs cut into non-negative ramp pieces: asymmetric loops)",
       &PiCreepModel::load, &export_c99_pi, kDefault},
      {"preisach_creep_prony", "discrete Preisach hysteresis + creep spectrum (as pi_creep_prony)", &PiCreepModel::load,
       &export_c99_pi, kDefault},
      {"dense", "dense network (depth × width, leaky ReLU) on the feature vector, trained with Adam/RMSprop/SGD",
       [](const YAML::Node& node) -> ModelPtr { return DenseModel::from_yaml(node); },
       export_of<DenseModel>("dense"), kExtra},
      {"lstm", "LSTM (layers × hidden, linear head) over the feature vector, truncated BPTT",
       [](const YAML::Node& node) -> ModelPtr { return LstmModel::from_yaml(node); }, nullptr, kExtra},
      {"kan", "Kolmogorov–Arnold network (B-spline + SiLU edges, grid updates), edges printable as formulas",
       [](const YAML::Node& node) -> ModelPtr { return KanModel::from_yaml(node); },
       export_of<KanModel>("kan"), kExtra},
      {"augmented",
       "a base model plus effect terms found by `piezo residual` (load only; fit with `piezo residual`)",
       [](const YAML::Node& node) { return AugmentedModel::from_yaml(node); }, &export_c99_augmented},
  };
  std::map<std::string, ModelKind> kinds;
  for (const ModelKind& k : list) kinds[k.name] = k;
  return kinds;
}

std::map<std::string, ModelKind>& kinds() {
  static std::map<std::string, ModelKind> k = built_in_kinds();
  return k;
}

}  // namespace

void register_model_kind(ModelKind kind) {
  const std::string name = kind.name;
  kinds()[name] = std::move(kind);
}

const ModelKind& model_kind(const std::string& name) {
  auto it = kinds().find(name);
  if (it == kinds().end()) {
    std::string known;
    for (const auto& [n, k] : kinds()) known += (known.empty() ? "" : ", ") + n;
    throw std::runtime_error("unknown model kind '" + name + "' (known: " + (known.empty() ? "none" : known) + ")");
  }
  return it->second;
}

std::vector<std::string> model_kind_names() {
  std::vector<std::string> names;
  for (const auto& [n, k] : kinds()) names.push_back(n);
  return names;
}

}  // namespace piezo::models
