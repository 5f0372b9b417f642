// Identifies a model's error-filter noise model (estimation/error_filter.h) from data: the model runs free over
// the data (the one streaming path), the reading σ and step come from the data's noise floor, and the variance
// rates are the maximum-likelihood ones on the rows from `first_row` on (the part the model was not fitted on).
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "piezo_compensation/estimation/error_filter.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"

namespace piezo::analysis {

// `model` is not changed (a clone runs). `first_row` > 0: the model runs through rows [0, first_row) first, as it
// would have (a split's training part), and only the rest is scored. Throws std::invalid_argument naming the
// problem (too few rows, a model that diverges).
estimation::NoiseModel identify_estimator(const models::Model& model, const io::Dataset& data,
                                          const std::string& axis, std::size_t first_row = 0);

// An axis' best-known position over `data`: its model run free (after `warmup` when given, as a model that kept
// running would), fused with its readings by the error filter of the model file's estimator block
// (models::ModelMeta::estimator); the model's prediction where the file has none or the block says model-only.
// Throws io::DataError when `data` lacks the axis, std::invalid_argument for a broken estimator block.
std::vector<double> fused_position(const models::Model& model, const io::Dataset& data, const std::string& axis,
                                   const io::Dataset* warmup = nullptr);

// A model of `axis`: `kind` (or auto: analysis::fit_auto) fitted on rows [0, n_fit) of `train` (the rest validates it); with `estimator`, its
// error filter identified on the rest (identify_estimator) and written to its estimator block, as fused_position
// reads it.
models::ModelPtr fit_axis_model(const io::Dataset& train, std::size_t n_fit, const std::string& axis,
                                const std::string& kind, std::uint64_t seed, bool estimator);

}  // namespace piezo::analysis
