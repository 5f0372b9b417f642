// The estimator's forecast of the model's error h ahead (docs/estimation.md, "Forecast"): the filter's state carried
// forward (the slow error held, the fast error settling; the slow error's rate only in the variance) with the process
// noise of the model's motion over the horizon, its σ scaled per horizon by a calibration on held-out training data
// (NoiseModel::forecast_*). compensation/drift_forecast.h turns it into the position forecast; ROS-free.
#pragma once

#include <cstddef>
#include <utility>
#include <vector>

#include "piezo_compensation/estimation/error_filter.h"

namespace piezo::estimation {

// The model's motion over a horizon, as the process noise sees it: path_nm = Σ|Δp| over the steps, fast_path_nm the
// same with each step's share decayed to the horizon's end by the fast error's settling (Σ|Δp_k|·φ^(2(n−k))).
struct ForecastPath {
  std::size_t steps = 0;
  double path_nm = 0.0, fast_path_nm = 0.0;
};

struct ErrorForecast {
  double mean_nm = 0.0;   // the model's error expected at the horizon
  double var_nm2 = 0.0;   // its variance as the noise model propagates it (before the calibration's scale)
  double sigma_nm = 0.0;  // the calibrated 1σ: forecast_sigma_scale(h)·√var_nm2
};

// The error of a filter in state `s` `path.steps` samples ahead. `hold`: the voltage is held over the horizon (the
// calibration's hold scales, else its move scales). A model-only noise model (fuse: false) gives a zero mean and
// model_sigma_nm.
ErrorForecast forecast_error(const NoiseModel& m, double dt_s, const FilterState& s, const ForecastPath& path, bool hold);

// The calibrated scale of the propagated σ at a horizon: interpolated in log h between the calibrated horizons,
// held beyond the ends; 1 without a calibration.
double forecast_sigma_scale(const NoiseModel& m, double horizon_s, bool hold);

// Running sums of the model's motion that give ForecastPath for any row and horizon in O(1) (offline: the
// calibration, `piezo track`). `predicted_nm`: the model's prediction per row.
class PathSums {
 public:
  PathSums(const std::vector<double>& predicted_nm, double phi);
  ForecastPath between(std::size_t row, std::size_t steps) const;  // rows (row, row + steps]

 private:
  std::vector<double> cum_, decayed_;
  double phi2_;
};

// Offline: the forecast made at a row of a run for the mean of the readings over the window after t + h (the
// model's mean over that window's readings plus the error expected at t + h), and that mean. The states are the
// filter's after each row (filter_states, or the compensator's own).
struct WindowForecast {
  bool ok = false;               // the window lies in the run and holds at least half its readings
  bool held = false;             // the voltage is unchanged from the row to the window's end
  double forecast_nm = 0.0, reference_nm = 0.0;
  double var_nm2 = 0.0;          // propagated, before the calibration's scale
  double sigma_nm = 0.0;         // calibrated 1σ of the forecast
  double reference_var_nm2 = 0.0;  // the reference's own: r²/n
};

class RunForecaster {
 public:
  RunForecaster(const NoiseModel& m, double dt_s, const std::vector<double>& predicted_nm,
                const std::vector<double>& measured_nm, const std::vector<double>& voltage_v,
                std::vector<FilterState> states, double window_s);
  WindowForecast at(std::size_t row, double horizon_s) const;
  // The next single reading against the forecast for it (one sample ahead): ok false when it is lost.
  WindowForecast next_reading(std::size_t row) const;
  std::size_t size() const { return p_.size(); }

 private:
  const NoiseModel& m_;
  double dt_;
  const std::vector<double>& p_;
  const std::vector<double>& y_;
  std::vector<FilterState> states_;
  PathSums sums_;
  std::vector<double> ys_, yn_, ps_, vc_;
  std::size_t w_;
};

// The filter's state after each row of a run from a cold start.
std::vector<FilterState> filter_states(const NoiseModel& m, double dt_s, const std::vector<double>& predicted_nm,
                                       const std::vector<double>& measured_nm);

struct ForecastCalibrationOptions {
  std::vector<double> horizons_s{0.1, 1.0, 10.0, 60.0, 300.0, 1200.0};
  double reference_window_s = 5.0;  // the forecast is checked against the mean of the readings over this long
  double coverage = 0.95;           // the share of references the calibrated ±2σ should hold
  std::size_t min_samples = 200;    // fewer checked rows at a horizon: its scale is left at 1
  // The holds of the run ([begin, end) rows, each at least 300 s of an unchanged voltage). Given, the scales are
  // calibrated on the rows the forecast table scores (compensation/drift_forecast_table.h): those in the last
  // walk_s before each hold and those from hold_from_s into it, each window in its regime (one entirely in a hold
  // or one that contains motion); empty: on every row.
  std::vector<std::pair<std::size_t, std::size_t>> holds;
  double walk_s = 900.0, hold_from_s = 120.0;
};

// Calibrates m.forecast_* on a run of the model over data it was not fitted on (the identification's run): the
// filter runs over it, and at every row and horizon the forecast is compared with the mean of the readings over
// the reference window after t + h (the window's model mean standing in for the position there); per horizon and
// for holds and moves apart, the scale is the one whose ±2·√(scale²·var + r²/n) holds `coverage` of them, r the
// reading σ, n the readings in the window. Rows from recording starts are not special: give one recording's run.
void calibrate_forecast(NoiseModel& m, double dt_s, const std::vector<double>& predicted_nm,
                        const std::vector<double>& measured_nm, const std::vector<double>& voltage_v,
                        const ForecastCalibrationOptions& o = {});

}  // namespace piezo::estimation
