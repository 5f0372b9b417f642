// Reload onto the running base (predictor ~reload_model, docs/predictor.md "Reload"). `piezo residual` run on a
// ~snapshot with the running model as base writes an augmented model on that same base. Warmed over the buffered
// window from rest, its base starts with the wrong creep and play states (the stage had a history before the
// window) and carries that error for tens of minutes; the running base has seen the true history. The fresh model
// takes the running base's state, and its offset is re-estimated on the window against the running base's
// recorded predictions (the terms' offset was fitted against a cold-started base).
#pragma once

#include <cstddef>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/augmented_model.h"

namespace piezo::compensation {

struct BaseHandover {
  bool done = false;
  double offset_change_nm = 0.0;  // added to the fresh model's offset
  std::size_t samples = 0;        // window rows the offset was estimated on
  std::string why;                // why not, when !done
};

// fresh: already streamed (free-run, from rest) over `data`, which gave `warm_prediction` per row and, as its base
// part, `warm_base` (AugmentedModel::set_base_trace during that stream: the base started at rest on the window).
// running: the model running now. running_base: its base's prediction per row of `data` (NaN where none was
// recorded). The offset is estimated on the rows after the first tenth of the window (the terms' low-passes settle
// there).
BaseHandover hand_over_base(models::AugmentedModel& fresh, const models::Model& running, const io::Dataset& data,
                            const std::string& axis, const std::vector<double>& warm_prediction,
                            const std::vector<double>& warm_base, const std::vector<double>& running_base);

}  // namespace piezo::compensation
