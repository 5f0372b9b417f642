// The start-up state estimate: a model started on a recording whose history it has not seen. The first window_s
// seconds (applied voltage and measured position) choose the model's state at the recording's start among a few
// synthetic pre-histories — rest, or arriving at the first voltage from above or below after a turning point or
// after a decaying staircase of them, or the window's own motion played backwards, then held there for several
// ages — and a constant offset. Each candidate's window is fitted by an offset weighted
// against the candidates' spread (rows where the unknown history still moves the prediction count little), and
// among the candidates that fit about as well as the best, the one that needs the least offset is chosen: an
// offset that a plausible state explains is left to the state, which the voltage sweeps into agreement later.
// Then the chosen state's linear parts (Model::linear_state_count: the creep modes) are fitted on the window with
// the offset, by a small ridge least-squares: each state's prior is where training-like operation keeps it at the
// first voltage (ModelMeta::state_prior; a model file without one: how far the candidates put it), the offset's
// the reading noise (docs/models.md, "Start-up state estimate").
// Generic: it only uses the Model interface, so it works for every kind (kinds without linear states: no fit).
//
// It is the one anchor: stream_model's anchor_s (`piezo eval/residual --anchor-s`) runs it, and the estimator
// (estimation::ErrorFilter) starts from its offset and σ in the compensator (the predictor's ~start_estimate_s,
// `piezo track --start-estimate-s`). It lives in models/ so that stream_model can run it; it knows no filter.
#pragma once

#include <cstddef>
#include <limits>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"

namespace piezo::models {

struct StartOptions {
  double window_s = 0.0;  // > 0: the first window_s seconds of the data are the window
  // false: offset only (the model is reset at rest at the first voltage and measured position: the plain anchor).
  bool search_history = true;
  // Turning points of the synthetic histories span this voltage range (a live node passes its voltage limits); NaN:
  // the model's training voltage range (ModelMeta::train_voltage_min_v/max_v), or, when the model file has none,
  // the data's voltage span over all its rows (the applied voltage is the known input, not a measurement) laid
  // on both sides of the first voltage, so histories from above and from below are both tried.
  double voltage_min_v = std::numeric_limits<double>::quiet_NaN();
  double voltage_max_v = std::numeric_limits<double>::quiet_NaN();
  // Samples of synthetic history per candidate (each sample one model step at the data's rate): caps the longest
  // hold, so the search stays fast at kHz rates (there the long ages drop out).
  std::size_t max_history_samples = 20000;
  // Also try the window's own motion played backwards as pre-histories (StartHistory::replay_v).
  bool replay_window = true;
  // Also try decaying staircases of turning points (StartHistory::shrink): the nested memory of several swings.
  bool staircases = true;
  // Also rest the single-turn ramps at the range's middle (where operation keeps a slow state: near its gain × the
  // mean voltage), besides the range's ends and the first voltage.
  bool rest_at_middle = true;
  // Fit the chosen candidate's linear states (Model::linear_state_count: creep modes) on the window as well.
  bool fit_linear_states = true;
};

// One synthetic pre-history, at the data's rate: rest at reset_v, ramp to turn_v, ramp to the window's first
// voltage, hold there hold_rows samples (rest = reset at the first voltage and measured position, nothing else).
struct StartHistory {
  bool rest = true;
  double reset_v = 0, turn_v = 0, start_v = 0;
  std::size_t ramp_to_turn_rows = 0, ramp_to_start_rows = 0, hold_rows = 0;
  double dt_s = 0;
  // Non-empty: after the ramp to turn_v, these voltages one per row (they end at start_v), instead of the ramp to
  // start_v: the window's own motion played backwards as a pre-history of the same statistics.
  std::vector<double> replay_v;
  // > 0: replay_v is a decaying staircase instead: from turn_v, swings around start_v, each this fraction of the last
  // (a nested memory of several turning points, which one turning point cannot leave).
  double shrink = 0.0;
  // Then each linear state k moved by linear_shift_nm[k] (Model::shift_linear_state; empty: none).
  std::vector<double> linear_shift_nm;
  std::string describe() const;  // "rest" or e.g. "from 42 V down, held 300 s"
};

struct StartEstimate {
  std::string candidate = "rest";     // the chosen pre-history, e.g. "from 42 V down, held 300 s"
  std::size_t candidates = 0;         // how many were tried
  // Measured − predicted over the window, each row weighted by 1/(σ² + (spread/2)²): σ the reading noise (the
  // scatter of the residual's steps), spread the range of every non-diverging candidate's prediction at that row.
  // With linear states fitted: the offset of that fit. Offset only (search_history false): the plain mean.
  double offset_nm = 0.0;
  // 1σ of the offset: half the weighted spread (what the unknown history may still shift) and the noise's share
  // (its correlation counted); with linear states fitted: the posterior σ of the fitted correction (offset and
  // states) at the window's last row; offset only: the scatter's share alone.
  double offset_sigma_nm = 0.0;
  double rms_rest_nm = 0.0;           // weighted window RMS residual of the rest candidate (its own offset)
  double rms_best_nm = 0.0;           // the smallest weighted window RMS of any candidate
  double rms_nm = 0.0;                // that of the chosen candidate
  // The chosen candidate: among those with n_eff·ln(SSE/SSE_best) ≤ 8·ln(n_eff) (SSE weighted; n_eff counts the
  // weights and the residuals' correlation; rest's), the one with the smallest |offset|, rest first on a tie.
  double spread_end_nm = 0.0;         // the candidates' spread at the window's last row (0 for offset only)
  std::size_t window_rows = 0;        // rows in the window (scoring starts at this row)
  // The row weights of the window fit, 1/(σ² + (spread/2)²) per window row (empty for offset only: equal weights).
  // A stream of the same start in another mode (one-step, with the measured position fed back) takes its offset
  // as the mean of measured − predicted under these weights (stream_model, models/model_stream.h).
  std::vector<double> window_weight;
  // The linear-state fit (StartOptions::fit_linear_states): states fitted (0: the kind has none, or every candidate
  // puts them at one place) and the largest |shift| [nm] of one state's share of the prediction.
  std::size_t linear_states = 0;
  double linear_shift_max_nm = 0.0;
  // How much of the voltage range the window swept: (max − min of its voltage) / the candidates' range (the training
  // range, or the limits given). The memory of a swing wider than the window's is not in the window: below
  // kWindowSweepAdvised the report says so (a longer window that sweeps the range starts better; docs/models.md).
  double window_swept_v = 0.0, range_v = 0.0;
  double swept_fraction() const { return range_v > 0 ? window_swept_v / range_v : 0.0; }
  StartHistory history;               // the chosen pre-history (prepare_start puts a model there)
  std::string describe() const;       // one line for logs and reports
};

// Below this fraction of the voltage range swept in the window, StartEstimate::describe() advises a longer window.
inline constexpr double kWindowSweepAdvised = 0.5;

// Throws std::invalid_argument for window_s ≤ 0 or not finite; io::DataError naming the source when the window
// covers the whole data set (nothing left after it) or holds a non-finite voltage or measured position; the
// stream's own errors (missing input columns). `model`'s own state is not changed.
StartEstimate estimate_start(const Model& model, const io::Dataset& data, const std::string& axis,
                             const StartOptions& o);

// Puts `model` in the state `history` ends in (its linear shifts included), just before the data's row 0 (reset, then the synthetic rows with
// the model's inputs held at row 0's values; free-run). The data gives the first voltage, measurement and inputs.
void prepare_start(Model& model, const io::Dataset& data, const std::string& axis, const StartHistory& history);

// Where the model's free run over its training data keeps each linear state (ModelMeta::state_prior): per state a
// least-squares line in the applied voltage and the RMS scatter about it, over a pass of the data after a warm-up
// pass (so that no state is still settling from the reset). The σ adds half the gap between two warm-ups started at
// rest at either end of the data's voltage range: a state that one training length does not settle (a mode much
// slower than the recording) keeps a wide prior. Empty when the model has no linear states or its run does not stay
// finite (e.g. a NaN voltage). The fitters store it in every model file (training::fit_model).
std::vector<LinearStatePrior> learn_state_prior(const Model& model, const io::Dataset& train, const std::string& axis);

// Rows of the first window_s seconds (at least 1). Throws like estimate_start for a bad window.
std::size_t start_window_rows(const io::Dataset& data, const std::string& axis, double window_s);

// Mean of measured − predicted over rows [0, n), and its 1σ from the scatter about it (lag-1 correlation counted).
struct WindowFit {
  double offset_nm = 0, sigma_nm = 0, rms_nm = 0;  // σ NaN for n < 2
  double n_eff = 0;                                // independent residuals: n (1 − ρ1)/(1 + ρ1), in [1, n]
};
WindowFit window_offset(const double* measured_nm, const double* predicted_nm, std::size_t n);

}  // namespace piezo::models
