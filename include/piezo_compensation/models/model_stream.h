// The one path that runs a model over a data set, and the one resolver that maps a model's inputs to the data.
// Fit validation, `piezo eval`, `piezo residual`, the drift forecast and the predictor use these (or are tested
// equal to them sample by sample). Lives in models/ so that training, compensation and analysis can all use it.
#pragma once

#include <cstddef>
#include <functional>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/start_state.h"

namespace piezo::models {

enum class PredictionMode { kFreeRun, kOneStep };
PredictionMode parse_prediction_mode(const std::string& s);  // "free-run"/"free_run" or "one-step"/"one_step"
const char* prediction_mode_name(PredictionMode m);          // "free-run" or "one-step"

// What one name in Model::aux_inputs() reads. The live predictor maps the same kinds to topics.
struct InputSource {
  enum class Kind {
    kTime,          // "time_s": the data's time column (live: the clock the model file names)
    kAux,           // an auxiliary column, e.g. "temperature_c"
    kAxisVoltage,   // "<axis>_voltage_v": an axis' applied voltage at this sample
    kAxisPosition,  // "<axis>_position_nm" of ANOTHER axis: its measured position at the previous sample (the
                    // latest reading known before this sample's; row 0 reads row 0)
    kAxisFused,     // "<axis>_fused_position_nm" of ANOTHER axis: its best-known position (its model fused with its
                    // encoder) at the previous sample, like kAxisPosition. Offline a derived column of that name
                    // (analysis::add_fused_positions); live the predictor's estimate for that axis.
  };
  Kind kind = Kind::kAux;
  std::string name;  // as in aux_inputs()
  std::string axis;  // for the axis kinds
};

// Classifies `name` for a model of `own_axis`. Throws io::DataError for what can never be an input: any
// "<axis>_true_position_nm" (ground truth) and the own axis' "<axis>_position_nm" (the target itself).
// `axis_names` are the axes that exist (a name "<x>_voltage_v" with x not among them is an aux column).
InputSource classify_input(const std::string& name, const std::string& own_axis,
                           const std::vector<std::string>& axis_names);

// Resolves a model's input names against a data set once, then gives each row's values in aux_inputs() order.
class InputResolver {
 public:
  // Throws io::DataError naming the data source and the first missing or forbidden column.
  InputResolver(const io::Dataset& data, const std::vector<std::string>& names, const std::string& own_axis);
  std::size_t size() const { return cols_.size(); }
  const std::vector<InputSource>& sources() const { return sources_; }
  // Values at row i (nullptr when the model reads no inputs). Valid until the next call.
  const double* at(std::size_t i);
  void fill(std::size_t i, double* out) const;

 private:
  std::vector<InputSource> sources_;
  std::vector<const std::vector<double>*> cols_;
  std::vector<char> lagged_;
  std::vector<double> row_;
};

// The step each row advances a model over (Model::set_step_s): the row's own step for a model that runs at any
// rate on data without a sample clock (the first row, and a step beyond io::kMaxStepS, take the data's period),
// the data's period on a sample clock, and nothing for a model that runs at its training rate only. stream_model
// and the compensator's offline twin (compensation/track.h) step models through it. Keeps a reference to
// data.time_s.
class RowSteps {
 public:
  RowSteps(const Model& model, const io::Dataset& data);
  double step_s(std::size_t i) const;             // row i's step; NaN: the model keeps its own
  void apply(Model& model, std::size_t i) const;  // the model's step for row i, before its predict

 private:
  const std::vector<double>& t_;
  double period_s_ = 0;
  bool per_row_ = false;
};

struct StreamOptions {
  PredictionMode mode = PredictionMode::kFreeRun;
  // Initial state: reset (rest at the first voltage and measured position) at the first row streamed.
  // false = continue from the model's current state (it must have been reset or streamed before).
  bool reset = true;
  // Streamed first (reset at its row 0 when `reset`), then `data` continues without a reset, as a model that
  // kept running would. Only `data`'s predictions are returned.
  const io::Dataset* warmup = nullptr;
  // > 0: the first anchor_s seconds of `data` are the start window (models/start_state.h). From a reset without
  // warm-up they choose the model's start state (anchor_history); always they fix a constant offset (mean of
  // measured − predicted there), added to every returned prediction; scoring starts after them
  // (StreamResult::first_scored).
  double anchor_s = 0.0;
  bool anchor_history = true;  // false: offset only (the model starts at rest, as before the start estimate)
  // Free-run only: a diverging prediction is kept finite (±1e12 nm) instead of throwing, so metrics stay
  // defined (evaluation reports a diverging model; the residual loop refuses one).
  bool keep_diverging = false;
  // Called after each row of `data` is committed (not the warm-up's), with the row and the model in its state.
  std::function<void(std::size_t row, const Model& model)> after_row;
};

struct StreamResult {
  std::vector<double> prediction;  // per row of `data` [nm], offset included
  double anchor_offset_nm = 0.0;   // 0 without an anchor
  std::size_t first_scored = 0;    // first row after the anchor window (0 without one); the first recording's
  // Data of several recordings (io::RecordingMark): each streamed on its own from its own reset (and start estimate
  // and offset with an anchor); per recording, its rows' anchor window [begin, first scored) and its estimate.
  std::vector<std::pair<std::size_t, std::size_t>> windows;
  std::vector<StartEstimate> starts;
  bool anchored = false;
  // The anchor's start estimate. Its offset is this stream's (the one-step stream of a model that reads the position:
  // the window mean under the estimate's row weights, and their weighted RMS; its σ the estimate's).
  StartEstimate start;
};

// Per row: predict with the row's voltage and inputs, then commit the measured position (one-step) or the
// model's own prediction (free-run). Data of several recordings: each is streamed on its own, from a reset (the
// first one continues the model's state when !reset), with its own anchor; a warm-up is refused. Throws std::runtime_error naming the row on a non-finite prediction (see
// keep_diverging), io::DataError on missing columns.
StreamResult stream_model(Model& model, const io::Dataset& data, const std::string& axis, const StreamOptions& o = {});

// The model's free-run prediction over `data`: a clone run from each recording's rest, a diverging run kept (not
// thrown). How the fits, model selection and the output map score a model without a start estimate.
std::vector<double> free_run_prediction(const Model& model, const io::Dataset& data, const std::string& axis);

// Each recording's zero as the data show it against a prediction: per recording of `data`, the mean of measured −
// predicted over its rows from `from` on (0 for a recording with no such row). A fit profiles it out of its training
// positions, the residual loop out of TRAIN's residual, model selection out of its scores.
std::vector<double> recording_offsets(const io::Dataset& data, const std::string& axis, const std::vector<double>& predicted_nm,
                                      std::size_t from = 0);

// Mask of the rows scored after an anchor: 0 in each recording's anchor window (sized data.size()).
std::vector<char> scored_mask(const StreamResult& r, std::size_t n);

}  // namespace piezo::models
