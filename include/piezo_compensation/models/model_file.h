// The self-describing model file (YAML):
//   format_version: 1
//   kind: linear                     # a registered kind (models/registry.h)
//   axis: c
//   sample_rate_hz: 11
//   created_utc: 2026-11-21T06:00:00Z
//   training: {fingerprint: "fnv1a64:…:N", source: plan.csv}
//   validation: {one_step_mae_nm: 17.1, ...}
//   model: {...}                     # Model::to_yaml(): feature spec with normalisation, weights, ...
// The `model:` node handed to ModelKind::load carries `sample_rate_hz`, `axis` and `kind` copied from the top level
// (kinds need the rate to build their FeatureStream). Errors name the file and the key.
#pragma once

#include <stdexcept>
#include <string>
#include <vector>

#include <yaml-cpp/yaml.h>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/yaml_fields.h"  // the kinds' loaders read their fields with these

namespace piezo::models {

constexpr int kModelFormatVersion = 1;

class ModelFileError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

YAML::Node model_to_file_yaml(const Model& model);
// `where` names the source in errors ("model.yaml").
ModelPtr model_from_file_yaml(const YAML::Node& root, const std::string& where);

void save_model(const std::string& path, const Model& model);
ModelPtr load_model(const std::string& path);

// Throws ModelFileError naming `where` when the data's rate or axes do not fit the model, or an input the model
// reads is not in the data as models::InputResolver (the one resolver every tool streams with) finds it.
// `axis`: the axis it runs on (default: the model's own).
// Throws ModelFileError naming `where` and both axes when `model` was fitted for another axis than `axis` (the
// file's `axis:`): each axis has its own hysteresis and creep, so a model is run only on the axis it was fitted for.
void check_model_axis(const Model& model, const std::string& axis, const std::string& where);

// The TrainingSpan of each recording of `data` for `axis` (what training::fit_model stores).
std::vector<TrainingSpan> training_spans(const io::Dataset& data, const std::string& axis);
// "" when no recording of `data` holds the rows of one of the model's training spans (its own times in the span's
// range, the same count and hash); else one line naming the overlap, e.g. "test.csv: rows 1-28699 (t = 0-2609 s)
// are rows model.yaml was trained on (test.csv)".
std::string training_overlap(const ModelMeta& meta, const io::Dataset& data, const std::string& axis,
                             const std::string& model_path);

void check_model_matches_data(const Model& model, const io::Dataset& data, const std::string& where,
                              const std::string& axis = "");

}  // namespace piezo::models
