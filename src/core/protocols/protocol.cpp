// Protocol base pieces: phase names, program(), defaults and the factory.
#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/protocols/protocol.h"

#include <algorithm>
#include <stdexcept>

#include "generators.h"

namespace piezo::protocols {

const char* phase_name(Phase p) {
  switch (p) {
    case Phase::kExcite: return "excite";
    case Phase::kHold: return "hold";
    case Phase::kSettle: return "settle";
    case Phase::kRecord: return "record";
    case Phase::kSweep: return "sweep";
  }
  return "unknown";
}

Phase phase_from_name(const std::string& name) {
  for (int k = 0; k <= static_cast<int>(Phase::kSweep); ++k)
    if (name == phase_name(static_cast<Phase>(k))) return static_cast<Phase>(k);
  throw std::invalid_argument("unknown protocol phase '" + name + "' (valid: excite, hold, settle, record, sweep)");
}

io::Dataset Protocol::program(std::size_t begin, std::size_t end) const {
  end = std::min(end, size());
  begin = std::min(begin, end);
  const std::size_t n = end - begin;
  const double rate = sample_rate_hz();
  io::Dataset d;
  d.source = "protocol " + name();
  d.time_s.resize(n);
  for (const char* ax : io::kAxisNames) d.add_axis(ax);
  for (auto& a : d.axes) {
    a.voltage_v.resize(n);
    a.position_nm.assign(n, 0.0);
  }
  d.segment.resize(n);
  d.phase.resize(n);
  for (std::size_t i = 0; i < n; ++i) {
    const ProtocolSample s = at(begin + i);
    d.time_s[i] = static_cast<double>(begin + i) / rate;
    for (int k = 0; k < 3; ++k) d.axes[k].voltage_v[i] = s.voltage_v[k];
    d.segment[i] = s.segment;
    d.phase[i] = static_cast<int>(s.phase);
  }
  return d;
}

std::vector<std::string> protocol_names() { return {"noise", "random_walk", "sweep", "creep", "plan", "sawtooth"}; }

std::unique_ptr<Protocol> make_protocol(const std::string& name, const YAML::Node& params, double sample_rate_hz,
                                        std::uint64_t seed) {
  if (!(sample_rate_hz > 0.0) || sample_rate_hz > 1e6)
    throw std::invalid_argument("protocol " + name + ": sample_rate_hz must be in (0, 1e6]");
  const YAML::Node defaults = default_protocol_parameters();
  if (!defaults[name]) {
    std::string valid;
    for (const auto& n : protocol_names()) valid += (valid.empty() ? "" : ", ") + n;
    throw std::invalid_argument("unknown protocol '" + name + "' (valid: " + valid + ")");
  }
  const YAML::Node merged = merge_parameters(defaults[name], params, name);
  return make_generated(name, merged, sample_rate_hz, seed);
}

}  // namespace piezo::protocols
