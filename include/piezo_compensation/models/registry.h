// The model kinds, one explicit list (registry.cpp): loader and optional C export per kind, so that the model
// file, `piezo eval`, `piezo export`, the residual tool and the predictor node handle every kind the same way.
// No static registrars: the list is the same in static and shared builds. Fitters live one layer up, in
// training/fitters.h, keyed by the same names.
#pragma once

#include <yaml-cpp/yaml.h>

#include <functional>
#include <string>
#include <vector>

#include "piezo_compensation/models/model.h"

namespace piezo::models {

// Whether `piezo fit --model auto` tries a kind: kDefault, always (an invertible physical kind that reads only the
// axis's own voltage); kExtra, only when named with --auto-extra (neural kinds, linear on lasso features: they may
// read other columns, and a base that reads one hides the effect the residual loop must find; pi_creep_play, whose
// choice on the simulated stages does not carry over to a separate recording: docs/validation/pi_creep_play.md); kNever.
enum class AutoCandidacy { kNever, kDefault, kExtra };

struct ModelKind {
  std::string name;          // "linear", "dense", ...
  std::string description;   // one line for --help
  std::function<ModelPtr(const YAML::Node& model_node)> load;   // from the file's `model:` node; throws on bad keys
  std::function<std::string(const Model&, const std::string& prefix)> export_c99;  // may be empty
  AutoCandidacy auto_candidacy = AutoCandidacy::kNever;
};

// Adds (or replaces) a kind at run time, by an explicit call (a test's own model, a program's extra kind); call it
// before other threads look kinds up.
void register_model_kind(ModelKind kind);
const ModelKind& model_kind(const std::string& name);  // throws std::runtime_error listing the known kinds
std::vector<std::string> model_kind_names();            // sorted

}  // namespace piezo::models
