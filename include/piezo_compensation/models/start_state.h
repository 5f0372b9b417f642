// The start-up state estimate: a model started on a recording whose history it has not seen. The first window_s
// seconds (applied voltage and measured position) choose the model's state at the recording's start among a few
// synthetic pre-histories — rest, or arriving at the first voltage from above or below after a turning point, then
// held there for several ages — and fix a constant offset (mean of measured − predicted over the window, least
// squares). Generic: it only uses Model::reset/predict/commit/clone, so it works for every kind.
//
// It is the one anchor: stream_model's anchor_s (`piezo eval/residual --anchor-s`) runs it, and the estimator
// (estimation::ErrorFilter) starts from its offset and σ in the compensator (the predictor's ~start_estimate_s,
// `piezo track --start-estimate-s`). It lives in models/ so that stream_model can run it; it knows no filter.
#pragma once

#include <cstddef>
#include <limits>
#include <string>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"

namespace piezo::models {

struct StartOptions {
  double window_s = 0.0;  // > 0: the first window_s seconds of the data are the window
  // false: offset only (the model is reset at rest at the first voltage and measured position: the plain anchor).
  bool search_history = true;
  // Turning points of the synthetic histories span this voltage range (a live node passes its voltage limits); NaN:
  // the data's voltage span over all its rows (the applied voltage is the known input, not a measurement) laid
  // on both sides of the first voltage, so histories from above and from below are both tried.
  double voltage_min_v = std::numeric_limits<double>::quiet_NaN();
  double voltage_max_v = std::numeric_limits<double>::quiet_NaN();
  // Samples of synthetic history per candidate (each sample one model step at the data's rate): caps the longest
  // hold, so the search stays fast at kHz rates (there the long ages drop out).
  std::size_t max_history_samples = 20000;
};

// One synthetic pre-history, at the data's rate: rest at reset_v, ramp to turn_v, ramp to the window's first
// voltage, hold there hold_rows samples (rest = reset at the first voltage and measured position, nothing else).
struct StartHistory {
  bool rest = true;
  double reset_v = 0, turn_v = 0, start_v = 0;
  std::size_t ramp_to_turn_rows = 0, ramp_to_start_rows = 0, hold_rows = 0;
  double dt_s = 0;
  std::string describe() const;  // "rest" or e.g. "from 42 V down, held 300 s"
};

struct StartEstimate {
  std::string candidate = "rest";     // the chosen pre-history, e.g. "from 42 V down, held 300 s"
  std::size_t candidates = 0;         // how many were tried
  double offset_nm = 0.0;             // measured − predicted over the window (mean)
  double offset_sigma_nm = 0.0;       // 1σ of that mean, from the residual scatter (its correlation counted)
  double rms_rest_nm = 0.0;           // window RMS residual of the offset-only anchor (rest candidate)
  double rms_nm = 0.0;                // window RMS residual of the chosen candidate (≤ rms_rest_nm)
  // A history replaces rest only when its window fit is better by more than chance: n_eff·ln(SSE_rest/SSE) >
  // 2·ln(n_eff) (a BIC-like penalty; n_eff counts the residuals' correlation), else rest is kept.
  std::size_t window_rows = 0;        // rows in the window (scoring starts at this row)
  StartHistory history;               // the chosen pre-history (prepare_start puts a model there)
  std::string describe() const;       // one line for logs and reports
};

// Throws std::invalid_argument for window_s ≤ 0 or not finite; io::DataError naming the source when the window
// covers the whole data set (nothing left after it) or holds a non-finite voltage or measured position; the
// stream's own errors (missing input columns). `model`'s own state is not changed.
StartEstimate estimate_start(const Model& model, const io::Dataset& data, const std::string& axis,
                             const StartOptions& o);

// Puts `model` in the state `history` ends in, just before the data's row 0 (reset, then the synthetic rows with
// the model's inputs held at row 0's values; free-run). The data gives the first voltage, measurement and inputs.
void prepare_start(Model& model, const io::Dataset& data, const std::string& axis, const StartHistory& history);

// Rows of the first window_s seconds (at least 1). Throws like estimate_start for a bad window.
std::size_t start_window_rows(const io::Dataset& data, const std::string& axis, double window_s);

// Mean of measured − predicted over rows [0, n), and its 1σ from the scatter about it (lag-1 correlation counted).
struct WindowFit {
  double offset_nm = 0, sigma_nm = 0, rms_nm = 0;  // σ NaN for n < 2
  double n_eff = 0;                                // independent residuals: n (1 − ρ1)/(1 + ρ1), in [1, n]
};
WindowFit window_offset(const double* measured_nm, const double* predicted_nm, std::size_t n);

}  // namespace piezo::models
