// The forecast table of `piezo track`: the position forecast (compensation/drift_forecast.h, estimation/forecast.h)
// made at every row, scored per horizon in the walk before each hold and in the holds, against the mean of the
// readings over the 5 s after t + h (or of the truth, when the data has one), and the shortest horizon also against
// the next single reading (or truth row). ROS-free.
#pragma once

#include <cstddef>
#include <utility>
#include <vector>

#include "piezo_compensation/estimation/error_filter.h"

namespace piezo::compensation {

struct ForecastCell {
  std::size_t n = 0;
  double abs_sum_nm = 0.0, within_2sigma = 0.0, sigma_sum_nm = 0.0;
  double mae_nm() const { return n ? abs_sum_nm / static_cast<double>(n) : NAN; }
  double coverage() const { return n ? within_2sigma / static_cast<double>(n) : NAN; }
  double mean_sigma_nm() const { return n ? sigma_sum_nm / static_cast<double>(n) : NAN; }
  void add(const ForecastCell& o) { n += o.n, abs_sum_nm += o.abs_sum_nm, within_2sigma += o.within_2sigma, sigma_sum_nm += o.sigma_sum_nm; }
};

struct ForecastTableOptions {
  std::vector<double> horizons_s{0.1, 1.0, 10.0, 60.0, 300.0, 1200.0};
  double walk_s = 900.0;          // the walk: the last this long before each hold
  double hold_from_s = 120.0;     // the hold: from this long after its start, the window inside it
  double reference_window_s = 5.0;
};

struct ForecastTable {
  std::vector<double> horizons_s;
  std::vector<ForecastCell> walk, hold;  // per horizon
  ForecastCell walk_next, hold_next;     // the shortest horizon against the next single reading
  bool against_truth = false;
  void add(const ForecastTable& o);      // the same horizons (another recording's table)
};

// One recording's rows: the model's prediction, the readings, the truth (empty: none), the voltage, the filter's
// state after each row and the holds ([begin, end) rows, compensation/track.h find_holds). Within ±2σ counts
// |forecast − reference| ≤ 2·√(σ² + σ_ref²), σ_ref the reference's own noise (r²/n for the readings' mean, 0 for
// the truth).
ForecastTable score_forecasts(const estimation::NoiseModel& noise, double dt_s, const std::vector<double>& predicted_nm,
                              const std::vector<double>& measured_nm, const std::vector<double>& true_nm,
                              const std::vector<double>& voltage_v, const std::vector<estimation::FilterState>& states,
                              const std::vector<std::pair<std::size_t, std::size_t>>& holds,
                              const ForecastTableOptions& o = {});

}  // namespace piezo::compensation
