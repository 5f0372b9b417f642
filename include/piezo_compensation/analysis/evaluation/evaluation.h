// Evaluation of a model over a data set through the Model interface, in both prediction modes:
//   one-step: the measured position of each sample is committed (lagged-position features see measurements);
//   free-run: the model's own prediction is committed (what a feedforward without a sensor has).
// Errors against the measurement and, for simulated data, against the true position. Creep holds come from the
// phase column (Phase::kHold) split at segment changes.
#pragma once

#include <string>
#include <vector>

#include "piezo_compensation/analysis/evaluation/metrics.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/start_state.h"

namespace piezo::analysis {

struct Hold {
  std::size_t begin = 0, end = 0;  // samples [begin, end)
  int segment = -1;
  double duration_s = 0;
};
// Runs of phase == Phase::kHold (a new run also starts where the segment changes). Without a phase column, as
// `piezo fit` finds them: the voltage of the first axis unchanged (within 1 µV) for at least kVoltageHoldMinS. A hold
// never spans two recordings.
constexpr double kVoltageHoldMinS = 60.0;
std::vector<Hold> find_holds(const io::Dataset& data, double min_duration_s = 0.0);

struct SeriesPrediction {
  std::vector<double> one_step, free_run;
  std::size_t first_scored = 0;                            // first row after the anchor window (0 without)
  std::vector<char> scored;  // rows after each recording's anchor window (all 1 without an anchor)
  double one_step_offset_nm = 0.0, free_run_offset_nm = 0.0;  // anchor offsets (0 without)
  models::StartEstimate start;  // the anchor's start estimate, free-run offset and σ (candidates = 0 without)
};
// Both modes through models::stream_model from a fresh clone reset at the first sample (rest at V_0, D_0).
// anchor_s > 0: the first anchor_s seconds choose the start state (anchor_history; the search runs once, in free
// run, and one-step starts from the same state) and fix each mode's offset (models/start_state.h).
// Throws on a non-finite one-step prediction; a diverging free-run is kept finite.
SeriesPrediction predict_series(const models::Model& model, const io::Dataset& data, const std::string& axis,
                                double anchor_s = 0.0, bool anchor_history = true);

struct ModeMetrics {
  ErrorStats vs_measured, vs_truth;  // vs_truth invalid when the data has no truth
};
struct SetMetrics {
  ModeMetrics one_step, free_run;
};

// Final position after a hold: means over its last `window_s` seconds.
struct FinalDeviation {
  int segment = -1;
  double hold_s = 0;
  double measured_nm = NAN, truth_nm = NAN, one_step_nm = NAN, free_run_nm = NAN;
};

// Errors inside holds, reported apart from the rest: MAE over hold samples, and each hold's end-of-hold error
// (prediction − reference, both averaged over the hold's last `window_s`).
struct HoldErrors {
  ErrorStats in_holds;              // over the hold samples where mask != 0
  std::vector<double> end_error_nm; // per hold (holds ending before the mask starts are skipped)
  double end_max_abs_nm = NAN, end_mean_abs_nm = NAN;
  bool valid() const { return !end_error_nm.empty(); }
};
HoldErrors hold_errors(const std::vector<double>& predicted, const std::vector<double>& reference, const io::Dataset& data,
                       const std::vector<char>& mask = {}, double window_s = 5.0);

// Each recording's first hold scored with the recording's zero taken from the data before it (the feedforward as
// an operator uses it after a zero: the tip's offset known, the model run free from the recording's start):
//   offset = mean(measured − free run) over the zero_window_s before the hold;
//   walk MAE over the walk_end_s before the hold (free run + offset against the readings);
//   creep = the position's change from the hold's first end_window_s to its last, predicted against measured
//   (means of the readings, so their noise averages to σ/√n).
struct ZeroedHold {
  std::string recording;
  double hold_s = 0, offset_nm = NAN, walk_mae_nm = NAN;
  double creep_measured_nm = NAN, creep_predicted_nm = NAN;
  double creep_error_nm() const { return creep_predicted_nm - creep_measured_nm; }
};

// The identification check's limit (analysis::Identification, model selection): a carry-over ratio above it means
// half the training recording did not predict its other half.
constexpr double kCarryOverAdvised = 2.0;

struct ModelEvaluation {
  std::string name, kind;
  std::size_t num_parameters = 0;
  bool uses_positions = false;
  // The model file's validation carry_over_ratio (`piezo fit`'s identification check; NaN when it has none): over
  // kCarryOverAdvised its training recording did not identify it, and errors on new data may come from that.
  double carry_over_ratio = NAN;
  SetMetrics hysteresis;  // test data outside holds (random walk / sweeps), after the warm-up
  SetMetrics creep;       // hold samples of the creep data
  std::vector<FinalDeviation> finals;
  HoldErrors holds_free_run, holds_free_run_truth;  // free-run in the creep data's holds, vs measured / vs truth
  std::vector<ZeroedHold> zeroed;  // EvalOptions::zero_window_s > 0: per recording of the test data
  SeriesPrediction test, creep_pred;
};

struct EvalOptions {
  std::string axis = "c";
  double warmup_s = 0.0;        // samples of the test data before this are not scored (history unknown to the model)
  double anchor_s = 0.0;        // > 0: the first anchor_s seconds fix the start state and offset; scored after them
  bool anchor_history = true;   // false: the anchor fixes the offset only (the model starts at rest)
  double final_window_s = 5.0;  // study: final position averaged over the last 5 s of each hold
  // Held out by time within one continuous recording (e.g. the plan: 2 = test, 3…17 = creep scenarios): the
  // model runs over the whole file, as it would live, and only these segments are scored. Empty = all.
  std::vector<int> test_segments, creep_segments;
  // > 0: each test recording's first hold scored from a zero taken over this long before it (ZeroedHold).
  double zero_window_s = 0.0;
  double walk_end_s = 900.0;
};

// The ZeroedHold of each recording of `data` from its free-run prediction (recordings without a hold, or with less
// than zero_window_s before it, are left out).
std::vector<ZeroedHold> zeroed_holds(const std::vector<double>& free_run, const io::Dataset& data, const std::string& axis,
                                     const EvalOptions& opt);

// `piezo eval`'s check of a loaded model file against the data it will run on: rate, axis, and every input
// through the one resolver of models/model_stream.h, as the streaming itself reads them. creep may be null.
// Throws models::ModelFileError naming `path`.
void check_model_for_eval(const models::Model& model, const std::string& path, const std::string& axis,
                          const io::Dataset& test, const io::Dataset* creep);

// creep may be null: then the holds of `test` are used for the creep metrics.
ModelEvaluation evaluate_model(const models::Model& model, const std::string& name, const io::Dataset& test,
                               const io::Dataset* creep, const EvalOptions& opt);

// Masks used above, exposed for reports and tests.
std::vector<char> hysteresis_mask(const io::Dataset& data, double warmup_s, const std::vector<int>& segments = {});
std::vector<char> hold_mask(const io::Dataset& data, const std::vector<int>& segments = {});
// "2", "3-17", "1,4,6-8" → segment numbers; throws std::invalid_argument naming the bad part.
std::vector<int> parse_segments(const std::string& list);

}  // namespace piezo::analysis
