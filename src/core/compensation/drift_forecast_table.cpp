#include "piezo_compensation/compensation/drift_forecast_table.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "piezo_compensation/estimation/forecast.h"

namespace piezo::compensation {

void ForecastTable::add(const ForecastTable& o) {
  if (horizons_s.empty()) {
    *this = o;
    return;
  }
  if (o.horizons_s != horizons_s) throw std::invalid_argument("ForecastTable::add: different horizons");
  for (std::size_t k = 0; k < horizons_s.size(); ++k) walk[k].add(o.walk[k]), hold[k].add(o.hold[k]);
  walk_next.add(o.walk_next);
  hold_next.add(o.hold_next);
}

namespace {

void count(ForecastCell& c, const estimation::WindowForecast& f, bool truth) {
  const double ref_var = truth ? 0.0 : f.reference_var_nm2;
  const double e = std::abs(f.forecast_nm - f.reference_nm);
  c.n += 1;
  c.abs_sum_nm += e;
  c.sigma_sum_nm += f.sigma_nm;
  c.within_2sigma += e <= 2.0 * std::sqrt(f.sigma_nm * f.sigma_nm + ref_var) ? 1.0 : 0.0;
}

}  // namespace

ForecastTable score_forecasts(const estimation::NoiseModel& noise, double dt_s, const std::vector<double>& p,
                              const std::vector<double>& y, const std::vector<double>& truth,
                              const std::vector<double>& v, const std::vector<estimation::FilterState>& states,
                              const std::vector<std::pair<std::size_t, std::size_t>>& holds,
                              const ForecastTableOptions& o) {
  ForecastTable t;
  t.horizons_s = o.horizons_s;
  t.walk.resize(o.horizons_s.size());
  t.hold.resize(o.horizons_s.size());
  t.against_truth = !truth.empty();
  const std::vector<double>& ref = t.against_truth ? truth : y;
  const estimation::RunForecaster run(noise, dt_s, p, ref, v, states, o.reference_window_s);
  const std::size_t walk_n = static_cast<std::size_t>(std::lround(o.walk_s / dt_s));
  const std::size_t skip_n = static_cast<std::size_t>(std::lround(o.hold_from_s / dt_s));
  for (const auto& [b, e] : holds) {
    for (std::size_t i = b > walk_n ? b - walk_n : 0; i < b; ++i) {
      for (std::size_t k = 0; k < o.horizons_s.size(); ++k) {
        const estimation::WindowForecast f = run.at(i, o.horizons_s[k]);
        if (f.ok) count(t.walk[k], f, t.against_truth);
      }
      const estimation::WindowForecast f = run.next_reading(i);
      if (f.ok && !o.horizons_s.empty()) count(t.walk_next, f, t.against_truth);
    }
    for (std::size_t i = b + skip_n; i < e; ++i) {
      for (std::size_t k = 0; k < o.horizons_s.size(); ++k) {
        const estimation::WindowForecast f = run.at(i, o.horizons_s[k]);
        if (f.ok && f.held) count(t.hold[k], f, t.against_truth);
      }
      const estimation::WindowForecast f = run.next_reading(i);
      if (f.ok && f.held) count(t.hold_next, f, t.against_truth);
    }
  }
  return t;
}

}  // namespace piezo::compensation
