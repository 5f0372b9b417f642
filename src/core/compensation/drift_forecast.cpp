#include "piezo_compensation/compensation/drift_forecast.h"

#include <algorithm>
#include <cmath>
#include <sstream>

namespace piezo::compensation {

DriftForecast forecast_drift(const models::Model& model, double hold_voltage_v, const std::vector<double>& horizons_s,
                             double sample_rate_hz, const double* aux) {
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
  double p = m->predict(in);
  m->commit(in, p);
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
  while (next < order.size() && steps[order[next]] == 0) f.position_nm[order[next++]] = p;
  while (next < order.size()) {
    p = m->predict(in);
    m->commit(in, p);
    tick();
    ++n;
    if (!std::isfinite(p)) {
      std::ostringstream s;
      s << "drift forecast: model prediction is not finite after " << n / sample_rate_hz << " s";
      f.error = s.str();
      f.steps = n;
      return f;
    }
    while (next < order.size() && steps[order[next]] == n) f.position_nm[order[next++]] = p;
  }
  f.steps = n;
  for (std::size_t i = 0; i < steps.size(); ++i) f.drift_nm[i] = f.position_nm[i] - f.start_position_nm;
  f.ok = true;
  return f;
}

}  // namespace piezo::compensation
