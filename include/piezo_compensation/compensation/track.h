// The offline twin of the predictor's estimator (`piezo track`): the same AxisCompensator the node runs, fed a
// recording's rows (applied voltage, reading, model inputs) from a cold start at its first row, giving the
// fused position and its 1σ per row and a table per hold. Live and offline run the same code, so they agree.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

#include "piezo_compensation/compensation/drift_forecast_table.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"

namespace piezo::compensation {

struct TrackOptions {
  double min_hold_s = 300.0;    // a hold: the voltage unchanged for at least this long
  double settle_skip_s = 120.0; // hold scores start this long after the hold starts
  double end_window_s = 5.0;    // "end of hold": its last seconds
  double start_estimate_s = 0.0;  // > 0: the compensator's start-up state estimate over the first seconds
  ForecastTableOptions forecast;  // the forecast table (compensation/drift_forecast_table.h)
  double score_from_s = 300.0;  // every sample from this long after the first row is scored too (a cold start's
                                // first minutes are the estimator pinning the model's error)
};

struct TrackHold {
  double start_s = 0, end_s = 0, voltage_v = 0;
  std::size_t scored = 0;          // samples from settle_skip_s on
  // Against the truth when the data has one; else against the mean of the next end_window_s of readings (rows whose
  // next window lies in the hold), and within_2sigma counts the next reading within 2·√(σ² + r²), r the reading σ.
  double fused_mae_nm = NAN, model_mae_nm = NAN;
  double fused_end_nm = NAN, model_end_nm = NAN;  // worst |error| over the last end_window_s
  double within_2sigma = NAN;      // fraction of scored samples with |fused − truth| ≤ 2σ
  double mean_sigma_nm = NAN;      // mean reported 1σ over the scored samples
  // the readings' own average over the scored part against the fused one (no truth needed)
  double measured_mean_minus_fused_nm = NAN;
};

struct TrackResult {
  std::vector<double> time_s, applied_v, measured_nm, model_nm, fused_nm, fused_sigma_nm, true_nm;
  std::vector<TrackHold> holds;
  ForecastTable forecast;  // the position forecast per horizon, walk and holds (empty on a model-only axis)
  std::string estimator;   // the filter's noise model, or why the axis is model-only
  std::string start_estimate;  // the start-up state estimate's line (empty without start_estimate_s)
  bool fusing = false;
  bool has_truth = false;
  double reading_sigma_nm = NAN;  // the estimator's r (no truth: the next reading's spread about the truth)
  std::size_t recordings = 1;
  // over every hold's scored samples
  double fused_mae_nm = NAN, model_mae_nm = NAN, worst_fused_end_nm = NAN, worst_model_end_nm = NAN,
         within_2sigma = NAN;
  // over every sample from score_from_s on (moves included), against the truth
  double all_fused_mae_nm = NAN, all_model_mae_nm = NAN, all_within_2sigma = NAN;
  // when the estimator first knew the model's error to the reading's resolution (estimation::ErrorFilter::
  // zero_known), seconds after the first row; NaN: never
  double zero_known_s = NAN;
};

// Data of several recordings: each tracked on its own from a cold start (a fresh clone of the model), the rows and
// holds joined in order. Throws std::invalid_argument / io::DataError naming what is wrong (axis or input columns
// missing).
TrackResult track_recording(models::ModelPtr model, const io::Dataset& data, const std::string& axis,
                            const TrackOptions& o = {});

// Maximal runs of an unchanged voltage lasting ≥ min_s: [begin, end) row ranges.
std::vector<std::pair<std::size_t, std::size_t>> find_holds(const std::vector<double>& voltage_v, double rate_hz,
                                                            double min_s);

}  // namespace piezo::compensation
