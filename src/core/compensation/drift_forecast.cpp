#include "piezo_compensation/compensation/drift_forecast.h"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "piezo_compensation/estimation/forecast.h"

namespace piezo::compensation {

namespace {

// The position forecast: the model's run ahead plus the error the filter expects `steps` samples from its state
// (step 0 of the run is the next sample, one step after the filter's last).
void add_error_forecast(DriftForecast& f, const std::vector<std::size_t>& steps,
                        const std::vector<estimation::ForecastPath>& paths, const EstimatorState& e, double dt_s) {
  const estimation::FilterState& s = e.state;
  f.fused_now_nm = s.last_predicted_nm + (e.noise.fuse ? s.slow_nm + s.fast_nm : 0.0);
  f.forecast_nm.resize(steps.size());
  f.forecast_drift_nm.resize(steps.size());
  f.forecast_sigma_nm.resize(steps.size());
  for (std::size_t i = 0; i < steps.size(); ++i) {
    const estimation::ErrorForecast ef = estimation::forecast_error(e.noise, dt_s, s, paths[i], true);
    f.forecast_nm[i] = f.position_nm[i] + ef.mean_nm;
    f.forecast_drift_nm[i] = f.forecast_nm[i] - f.fused_now_nm;
    f.forecast_sigma_nm[i] = ef.sigma_nm;
  }
}

}  // namespace

DriftForecast forecast_drift(const models::Model& model, double hold_voltage_v, const std::vector<double>& horizons_s,
                             double sample_rate_hz, const double* aux, const EstimatorState* estimator) {
  DriftForecast f;
  f.horizons_s = horizons_s;
  f.drift_nm.assign(horizons_s.size(), std::nan(""));
  f.position_nm.assign(horizons_s.size(), std::nan(""));
  if (!(sample_rate_hz > 0.0) || !std::isfinite(sample_rate_hz)) {
    f.error = "drift forecast: sample rate must be positive";
    return f;
  }
  if (!std::isfinite(hold_voltage_v)) {
    f.error = "drift forecast: hold voltage is not finite";
    return f;
  }
  std::vector<std::size_t> steps(horizons_s.size());
  std::size_t max_steps = 0;
  for (std::size_t i = 0; i < horizons_s.size(); ++i) {
    if (!(horizons_s[i] >= 0.0) || !std::isfinite(horizons_s[i])) {
      std::ostringstream s;
      s << "drift forecast: horizon " << horizons_s[i] << " s is not a finite non-negative time";
      f.error = s.str();
      return f;
    }
    steps[i] = static_cast<std::size_t>(std::llround(horizons_s[i] * sample_rate_hz));
    max_steps = std::max(max_steps, steps[i]);
  }

  std::unique_ptr<models::Model> m = model.clone();
  // Inputs are held like the voltage, except time, which runs on (a time-drift or time-gain term must see it).
  const std::vector<std::string> names = model.aux_inputs();
  std::vector<double> held(aux ? names.size() : 0);
  if (aux) std::copy(aux, aux + names.size(), held.begin());
  std::vector<std::size_t> clocks;
  for (std::size_t k = 0; k < held.size(); ++k)
    if (names[k] == "time_s") clocks.push_back(k);
  const models::ModelInput in{hold_voltage_v, held.empty() ? nullptr : held.data()};
  auto tick = [&] {
    for (std::size_t k : clocks) held[k] += 1.0 / sample_rate_hz;
  };
  // Step 0 is the next sample: the voltage change itself; the drift is what follows it.
  // the model's motion from the filter's last prediction on, for the process noise over each horizon
  std::vector<estimation::ForecastPath> paths(steps.size());
  estimation::ForecastPath path;
  const double phi2 = estimator ? std::exp(-2.0 / (sample_rate_hz * std::max(estimator->noise.fast_tau_s, 1e-9))) : 0.0;
  double last = estimator ? estimator->state.last_predicted_nm : 0.0;
  auto advance = [&](double p) {
    const double d = std::isfinite(p) ? std::abs(p - last) : 0.0;
    last = p;
    path.steps += 1;
    path.path_nm += d;
    path.fast_path_nm = phi2 * path.fast_path_nm + d;
  };
  double p = m->predict(in);
  m->commit(in, p);
  advance(p);
  if (!std::isfinite(p)) {
    f.error = "drift forecast: model prediction is not finite";
    return f;
  }
  f.start_position_nm = p;
  tick();
  std::vector<std::size_t> order(steps.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::sort(order.begin(), order.end(), [&](std::size_t x, std::size_t y) { return steps[x] < steps[y]; });
  std::size_t next = 0, n = 0;
  while (next < order.size() && steps[order[next]] == 0) paths[order[next]] = path, f.position_nm[order[next++]] = p;
  while (next < order.size()) {
    p = m->predict(in);
    m->commit(in, p);
    advance(p);
    tick();
    ++n;
    if (!std::isfinite(p)) {
      std::ostringstream s;
      s << "drift forecast: model prediction is not finite after " << n / sample_rate_hz << " s";
      f.error = s.str();
      f.steps = n;
      return f;
    }
    while (next < order.size() && steps[order[next]] == n) paths[order[next]] = path, f.position_nm[order[next++]] = p;
  }
  f.steps = n;
  for (std::size_t i = 0; i < steps.size(); ++i) f.drift_nm[i] = f.position_nm[i] - f.start_position_nm;
  if (estimator) add_error_forecast(f, steps, paths, *estimator, 1.0 / sample_rate_hz);
  f.ok = true;
  return f;
}

}  // namespace piezo::compensation
