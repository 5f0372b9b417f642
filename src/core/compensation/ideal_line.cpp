#include "piezo_compensation/compensation/ideal_line.h"
#include "piezo_compensation/compensation/live_inputs.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace piezo::compensation {
namespace {

// From rest at 0 V / 0 nm: ramp to `target_v`, hold, return the final free-run position.
double settled_position(const models::Model& proto, double target_v, const IdealLineOptions& o) {
  std::unique_ptr<models::Model> m = proto.clone();
  m->reset(0.0, 0.0);
  const std::size_t ramp = std::max<std::size_t>(1, static_cast<std::size_t>(std::llround(o.ramp_s * o.sample_rate_hz)));
  const std::size_t hold = static_cast<std::size_t>(std::llround(o.hold_s * o.sample_rate_hz));
  // inputs at their neutral values (the terms on them contribute nothing): the ideal line is the stage's own
  std::vector<double> aux;
  for (const auto& name : m->aux_inputs()) aux.push_back(neutral_input(*m, name));
  const double* aux_ptr = aux.empty() ? nullptr : aux.data();
  double p = 0.0;
  for (std::size_t i = 1; i <= ramp + hold; ++i) {
    const double v = i <= ramp ? target_v * static_cast<double>(i) / static_cast<double>(ramp) : target_v;
    const models::ModelInput in{v, aux_ptr};
    p = m->predict(in);
    if (!std::isfinite(p)) {
      std::ostringstream s;
      s << "ideal line: model prediction is not finite on the way to " << target_v << " V";
      throw std::runtime_error(s.str());
    }
    m->commit(in, p);
  }
  return p;
}

}  // namespace

IdealLine ideal_line_from_model(const models::Model& model, const IdealLineOptions& o) {
  if (!(o.voltage_max_v > o.voltage_min_v)) throw std::runtime_error("ideal line: voltage limits are empty");
  if (!(o.sample_rate_hz > 0.0)) throw std::runtime_error("ideal line: sample rate must be positive");
  const double p_lo = settled_position(model, o.voltage_min_v, o);
  const double p_hi = settled_position(model, o.voltage_max_v, o);
  IdealLine line;
  line.gain_nm_per_v = (p_hi - p_lo) / (o.voltage_max_v - o.voltage_min_v);
  if (!(std::abs(line.gain_nm_per_v) > 1e-9)) {
    std::ostringstream s;
    s << "ideal line: the model does not move between " << o.voltage_min_v << " V and " << o.voltage_max_v << " V";
    throw std::runtime_error(s.str());
  }
  line.offset_nm = p_lo - line.gain_nm_per_v * o.voltage_min_v;
  return line;
}

}  // namespace piezo::compensation
