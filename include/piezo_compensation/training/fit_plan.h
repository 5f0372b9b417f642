// A fit plan: what a fit runs on and what it fits — the training and validation data (and what the validation is
// scored on), the kind and its options — and the origin stamp every model fitted on it carries. `piezo fit` and
// `piezo residual` build one and run it; a fit plan knows nothing of files or the command line.
#pragma once

#include <yaml-cpp/yaml.h>

#include <cstddef>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/training/fit_request.h"

namespace piezo::training {

struct FitPlan {
  io::Dataset train, validation;  // validation empty: none
  // > 0: the validation part is `all` from this row on (one recording split by time): it is scored after the model
  // ran through the training part, so it starts with the real history, as live. 0: scored from its own start.
  std::size_t split_at = 0;
  io::Dataset all;                // the data the parts were cut from (what a split validation is scored on)
  std::string axis = "c";
  std::string kind;               // a kind of training/fitters.h, or "auto" (model selection)
  YAML::Node options{YAML::NodeType::Map};
  std::string source;             // the files the training data came from (the model's training_source)

  bool has_validation() const { return !validation.empty(); }
  const io::Dataset& score_data() const { return split_at ? all : validation; }
  // The request of the plan's data, axis and options (its data stay the plan's: the plan must outlive it).
  FitRequest request() const;
};

// Holds out the validation part of `all` (its training fraction `split`, in (0, 1]): data of several recordings
// keep whole ones (the last ones held out; never a recording cut in two, its zero and state would leak), one
// recording is cut by rows (at least 20 training rows). Throws std::invalid_argument naming the problem.
void split_by_fraction(FitPlan& plan, io::Dataset all, double split);

// The first `rows` rows of `all` train, the rest validate (scored after the training rows, split_at = rows).
void split_at_row(FitPlan& plan, io::Dataset all, std::size_t rows);

// A kind's options: the YAML mapping `file` ("" for none), then each KEY=VALUE of `sets` (a YAML value) over it.
// Throws std::invalid_argument naming the file or setting that cannot be read.
YAML::Node plan_options(const std::string& file, const std::vector<std::string>& sets);

// The origin stamp of a model fitted on `train`: the clock of its time column (the predictor feeds time_s only on
// that clock), its source (`source`, where the fit left it empty) and, when the data are simulated, that origin
// (a simulated stage's fit is refused on a real transport).
void stamp_origin(models::Model& model, const io::Dataset& train, const std::string& source);

}  // namespace piezo::training
