// Drift forecast: how far the tip will still move if the voltage is held, by running a copy of the model ahead
// in free run (its own predictions become its remembered positions; no sensor in the loop).
#pragma once

#include <string>
#include <vector>

#include "piezo_compensation/estimation/error_filter.h"
#include "piezo_compensation/models/model.h"

namespace piezo::compensation {

struct DriftForecast {
  bool ok = false;
  std::vector<double> horizons_s;    // as requested
  std::vector<double> drift_nm;      // position at (next sample + horizon) minus position at the next sample
  std::vector<double> position_nm;   // absolute predicted position at each horizon
  double start_position_nm = 0.0;    // predicted position at the next sample with the held voltage
  // With the estimator's state (forecast_drift's `estimator`): the forecast of the position at each horizon, the
  // model's run ahead plus the error the filter expects there (estimation/forecast.h), its drift from the fused
  // position now and its calibrated 1σ about the true position (the readings' 5-s mean there); else empty.
  std::vector<double> forecast_nm, forecast_drift_nm, forecast_sigma_nm;
  double fused_now_nm = 0.0;         // the fused position the forecast drift is counted from
  std::size_t steps = 0;             // model steps run
  std::string error;                 // one line when !ok (non-finite prediction, bad horizon)
};

// The estimator's state and noise model, for the forecast with its σ.
struct EstimatorState {
  estimation::NoiseModel noise;
  estimation::FilterState state;
};

// Does not change `model`: the state is cloned. Horizons are rounded to whole samples at `sample_rate_hz`.
// `aux` (values of Model::aux_inputs() at the next sample, or null) is held constant over the forecast like the
// voltage, except "time_s", which advances one sample period per step. Equal to models::stream_model over a
// data set that holds voltage and inputs (tested in test_eval_stream).
DriftForecast forecast_drift(const models::Model& model, double hold_voltage_v, const std::vector<double>& horizons_s,
                             double sample_rate_hz, const double* aux = nullptr,
                             const EstimatorState* estimator = nullptr);

}  // namespace piezo::compensation
