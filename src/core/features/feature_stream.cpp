#include "piezo_compensation/features/feature_stream.h"
#include "piezo_compensation/features/play_operator.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>
#include <stdexcept>

namespace piezo::features {

// Named (not anonymous): FeatureStream::Impl holds these types, and in a unity build an anonymous one warns.
namespace stream_detail {

enum class Type { kVoltageSq, kVoltage, kStep, kStepSum, kExpSum, kLowpass, kPlay, kStop, kPlayLowpass, kPlayHinge, kLag, kMean, kAux };

Type parse_type(const std::string& t, std::size_t index) {
  if (t == "voltage") return Type::kVoltage;
  if (t == "voltage_sq") return Type::kVoltageSq;
  if (t == "voltage_step") return Type::kStep;
  if (t == "step_sum") return Type::kStepSum;
  if (t == "exp_sum") return Type::kExpSum;
  if (t == "lowpass") return Type::kLowpass;
  if (t == "play") return Type::kPlay;
  if (t == "stop") return Type::kStop;
  if (t == "play_lowpass") return Type::kPlayLowpass;
  if (t == "play_hinge") return Type::kPlayHinge;
  if (t == "lagged_position") return Type::kLag;
  if (t == "position_mean") return Type::kMean;
  if (t == "aux") return Type::kAux;
  throw std::runtime_error("features[" + std::to_string(index) + "].type: unknown feature type '" + t +
                           "' (known: voltage, voltage_sq, voltage_step, step_sum, exp_sum, lowpass, play, stop, play_lowpass, "
                           "play_hinge, lagged_position, position_mean, aux)");
}

std::string fmt(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.4g", v);
  return buf;
}

// Fixed-capacity history; get(k) is the value committed k samples ago (k ≥ 1).
struct Ring {
  std::vector<double> buf;
  std::size_t head = 0;  // index of the most recent value
  void init(std::size_t cap, double v) {
    buf.assign(std::max<std::size_t>(cap, 1), v);
    head = 0;
  }
  void push(double v) {
    head = (head + 1 == buf.size()) ? 0 : head + 1;
    buf[head] = v;
  }
  double get(std::size_t k) const {  // 1 ≤ k ≤ capacity
    std::size_t i = head + buf.size() - (k - 1);
    if (i >= buf.size()) i -= buf.size();
    return buf[i];
  }
};

struct Compiled {
  Type type;
  std::size_t w = 0;       // samples (window or lag)
  double alpha = 0, alpha_w = 0;
  double a = 0;            // low-pass pole exp(-dt/τ); 0 = no low-pass
  double r = 0;            // threshold [V]
  double knot = 0;         // play_hinge knot [V]
  int aux_index = -1;
};

}  // namespace stream_detail
using namespace stream_detail;

std::string FeatureDef::name() const {
  if (type == "voltage") return "V";
  if (type == "voltage_step") return "dV";
  if (type == "voltage_sq") return "V^2";
  if (type == "step_sum") return "step_sum(V, " + fmt(window_s) + " s)";
  if (type == "exp_sum") return "exp_sum(V, " + fmt(window_s) + " s, a=" + fmt(decay) + ")";
  if (type == "lowpass") return "lowpass(V, " + fmt(time_constant_s) + " s)";
  if (type == "play") return "play(V, " + fmt(threshold_v) + " V)";
  if (type == "stop") return "stop(V, " + fmt(threshold_v) + " V)";
  if (type == "play_lowpass")
    return "lowpass(play(V, " + fmt(threshold_v) + " V), " + fmt(time_constant_s) + " s)";
  if (type == "play_hinge")
    return "max(play(V, " + fmt(threshold_v) + " V) " + (knot_v < 0 ? "+ " + fmt(-knot_v) : "- " + fmt(knot_v)) + " V, 0)";
  if (type == "lagged_position") return "D(t-" + fmt(lag_s) + " s)";
  if (type == "position_mean") return "mean(D, past " + fmt(window_s) + " s)";
  if (type == "aux") {
    std::string s = signal;
    if (lag_s > 0) s += "(t-" + fmt(lag_s) + " s)";
    if (time_constant_s > 0) s = "lowpass(" + s + ", " + fmt(time_constant_s) + " s)";
    return s;
  }
  return type;
}

YAML::Node FeatureSpec::to_yaml() const {
  YAML::Node n;
  YAML::Node list(YAML::NodeType::Sequence);
  for (const auto& f : features) {
    YAML::Node e;
    e["type"] = f.type;
    if (f.window_s != 0) e["window_s"] = f.window_s;
    if (f.decay != 0) e["decay"] = f.decay;
    if (f.time_constant_s != 0) e["time_constant_s"] = f.time_constant_s;
    if (f.threshold_v != 0) e["threshold_v"] = f.threshold_v;
    if (f.type == "play_hinge") e["knot_v"] = f.knot_v;
    if (f.lag_s != 0) e["lag_s"] = f.lag_s;
    if (!f.signal.empty()) e["signal"] = f.signal;
    list.push_back(e);
  }
  n["features"] = list;
  YAML::Node m(YAML::NodeType::Sequence), s(YAML::NodeType::Sequence);
  for (double v : mean) m.push_back(v);
  for (double v : scale) s.push_back(v);
  n["mean"] = m;
  n["scale"] = s;
  return n;
}

namespace {
double num_key(const YAML::Node& e, const char* key, std::size_t i) {
  const YAML::Node v = e[key];
  if (!v) return 0.0;
  try {
    double d = v.as<double>();
    if (!std::isfinite(d)) throw YAML::Exception(YAML::Mark(), "");
    return d;
  } catch (const YAML::Exception&) {
    throw std::runtime_error("features[" + std::to_string(i) + "]." + key + ": expected a finite number");
  }
}
std::vector<double> num_list(const YAML::Node& n, const char* key) {
  std::vector<double> out;
  const YAML::Node v = n[key];
  if (!v) return out;
  if (!v.IsSequence()) throw std::runtime_error(std::string(key) + ": expected a list of numbers");
  for (std::size_t i = 0; i < v.size(); ++i) {
    try {
      out.push_back(v[i].as<double>());
    } catch (const YAML::Exception&) {
      throw std::runtime_error(std::string(key) + "[" + std::to_string(i) + "]: expected a number");
    }
    if (!std::isfinite(out.back())) throw std::runtime_error(std::string(key) + "[" + std::to_string(i) + "]: not finite");
  }
  return out;
}
}  // namespace

FeatureSpec FeatureSpec::from_yaml(const YAML::Node& node) {
  if (!node || !node.IsMap()) throw std::runtime_error("feature spec: expected a mapping with key 'features'");
  const YAML::Node list = node["features"];
  if (!list) throw std::runtime_error("features: missing key");
  if (!list.IsSequence()) throw std::runtime_error("features: expected a list");
  FeatureSpec spec;
  for (std::size_t i = 0; i < list.size(); ++i) {
    const YAML::Node e = list[i];
    if (!e.IsMap()) throw std::runtime_error("features[" + std::to_string(i) + "]: expected a mapping");
    FeatureDef f;
    // The keys a feature entry may have: a misspelt one (e.g. `knot` for `knot_v`) is an error, not a default.
    static const char* const kKeys[] = {"type", "window_s", "decay", "time_constant_s", "threshold_v", "knot_v", "lag_s", "signal"};
    for (const auto& kv : e) {
      const std::string key = kv.first.as<std::string>();
      if (std::none_of(std::begin(kKeys), std::end(kKeys), [&](const char* k) { return key == k; })) {
        std::string valid;
        for (const char* k : kKeys) valid += (valid.empty() ? "" : ", ") + std::string(k);
        throw std::runtime_error("features[" + std::to_string(i) + "]." + key + ": unknown key (valid: " + valid + ")");
      }
    }
    if (!e["type"]) throw std::runtime_error("features[" + std::to_string(i) + "].type: missing key");
    f.type = e["type"].as<std::string>();
    parse_type(f.type, i);
    f.window_s = num_key(e, "window_s", i);
    f.decay = num_key(e, "decay", i);
    f.time_constant_s = num_key(e, "time_constant_s", i);
    f.threshold_v = num_key(e, "threshold_v", i);
    f.knot_v = num_key(e, "knot_v", i);
    if (f.type == "play_hinge" && !e["knot_v"])
      throw std::runtime_error("features[" + std::to_string(i) + "].knot_v: missing (a play_hinge needs its knot)");
    f.lag_s = num_key(e, "lag_s", i);
    if (e["signal"]) f.signal = e["signal"].as<std::string>();
    spec.features.push_back(f);
  }
  spec.mean = num_list(node, "mean");
  spec.scale = num_list(node, "scale");
  if (spec.mean.size() != spec.scale.size() || (!spec.mean.empty() && spec.mean.size() != spec.features.size()))
    throw std::runtime_error("mean/scale: expected " + std::to_string(spec.features.size()) +
                             " entries each (one per feature) or none, got " + std::to_string(spec.mean.size()) +
                             " and " + std::to_string(spec.scale.size()));
  for (std::size_t i = 0; i < spec.scale.size(); ++i)
    if (!(spec.scale[i] > 0)) throw std::runtime_error("scale[" + std::to_string(i) + "]: must be > 0");
  return spec;
}

bool FeatureDef::reads_position() const { return type == "lagged_position" || type == "position_mean"; }

bool FeatureSpec::uses_positions() const {
  return std::any_of(features.begin(), features.end(), [](const FeatureDef& f) { return f.reads_position(); });
}

std::vector<std::string> FeatureSpec::aux_signals() const {
  std::vector<std::string> out;
  for (const auto& f : features)
    if (f.type == "aux" && std::find(out.begin(), out.end(), f.signal) == out.end()) out.push_back(f.signal);
  return out;
}

struct FeatureStream::Impl {
  FeatureSpec spec;
  double rate_hz = 0;
  std::vector<Compiled> c;
  // Committed state (all "previous sample" values).
  Ring volts, pos;
  std::vector<double> state;   // per feature: exp sum, low-pass, play output, running position sum
  std::vector<double> state2;  // per feature: low-pass of the play output / of the aux signal
  std::vector<Ring> aux_hist;  // per feature (aux with lag)
  bool aux_primed = false;
  bool has_aux = false;


  double raw(std::size_t i, const ModelInput& in) const {
    const Compiled& f = c[i];
    const double v = in.voltage_v;
    switch (f.type) {
      case Type::kVoltage: return v;
      case Type::kVoltageSq: return v * v;
      case Type::kStep: return v - volts.get(1);
      case Type::kStepSum: return v - volts.get(f.w);
      case Type::kExpSum: return f.alpha * state[i] + v - f.alpha_w * volts.get(f.w);
      case Type::kLowpass: return f.a * state[i] + (1 - f.a) * v;
      case Type::kPlay: return play(v, f.r, state[i]);
      case Type::kStop: return v - play(v, f.r, state[i]);
      case Type::kPlayLowpass: return f.a * state2[i] + (1 - f.a) * play(v, f.r, state[i]);
      case Type::kPlayHinge: return std::max(play(v, f.r, state[i]) - f.knot, 0.0);
      case Type::kLag: return pos.get(f.w);
      case Type::kMean: return state[i] / static_cast<double>(f.w);
      case Type::kAux: {
        if (!in.aux) throw std::runtime_error("feature '" + spec.features[i].name() + "': no aux input given");
        const double now = in.aux[f.aux_index];
        const double x = f.w == 0 ? now : (aux_primed ? aux_hist[i].get(f.w) : now);
        if (f.a == 0) return x;
        return aux_primed ? f.a * state2[i] + (1 - f.a) * x : x;
      }
    }
    return 0;
  }
};

FeatureStream::FeatureStream(const FeatureSpec& spec, double sample_rate_hz) : impl_(std::make_unique<Impl>()) {
  if (!(sample_rate_hz > 0) || !std::isfinite(sample_rate_hz))
    throw std::runtime_error("feature stream: sample rate must be > 0 Hz");
  if (!spec.mean.empty() && spec.mean.size() != spec.features.size())
    throw std::runtime_error("feature spec: mean/scale size does not match the number of features");
  Impl& m = *impl_;
  m.spec = spec;
  m.rate_hz = sample_rate_hz;
  const double dt = 1.0 / sample_rate_hz;
  const auto aux_names = spec.aux_signals();
  std::size_t vcap = 1, pcap = 1;
  for (std::size_t i = 0; i < spec.features.size(); ++i) {
    const FeatureDef& d = spec.features[i];
    Compiled f{parse_type(d.type, i)};
    const std::string where = "features[" + std::to_string(i) + "] (" + d.type + ")";
    auto samples = [&](double s, const char* key, std::size_t min) {
      const double n = std::round(s * sample_rate_hz);
      if (!(n >= static_cast<double>(min)) || n > 1e8)
        throw std::runtime_error(where + "." + key + " = " + fmt(s) + " s is " + fmt(n) + " samples at " +
                                 fmt(sample_rate_hz) + " Hz; need at least " + std::to_string(min));
      return static_cast<std::size_t>(n);
    };
    auto pole = [&](double tau) {
      if (!(tau > 0)) throw std::runtime_error(where + ".time_constant_s: must be > 0");
      return std::exp(-dt / tau);
    };
    switch (f.type) {
      case Type::kStepSum:
        f.w = samples(d.window_s, "window_s", 1);
        vcap = std::max(vcap, f.w);
        break;
      case Type::kExpSum:
        f.w = samples(d.window_s, "window_s", 1);
        if (!(d.decay > 0 && d.decay < 1)) throw std::runtime_error(where + ".decay: must be in (0, 1)");
        f.alpha = d.decay;
        f.alpha_w = std::pow(d.decay, static_cast<double>(f.w));
        vcap = std::max(vcap, f.w);
        break;
      case Type::kLowpass: f.a = pole(d.time_constant_s); break;
      case Type::kPlay:
      case Type::kStop:
        if (!(d.threshold_v >= 0)) throw std::runtime_error(where + ".threshold_v: must be >= 0");
        f.r = d.threshold_v;
        break;
      case Type::kPlayHinge:
        if (!(d.threshold_v >= 0)) throw std::runtime_error(where + ".threshold_v: must be >= 0");
        if (!std::isfinite(d.knot_v)) throw std::runtime_error(where + ".knot_v: must be a finite voltage");
        f.r = d.threshold_v;
        f.knot = d.knot_v;
        break;
      case Type::kPlayLowpass:
        if (!(d.threshold_v >= 0)) throw std::runtime_error(where + ".threshold_v: must be >= 0");
        f.r = d.threshold_v;
        f.a = pole(d.time_constant_s);
        break;
      case Type::kLag:
        f.w = samples(d.lag_s, "lag_s", 1);  // causal: the position being predicted is never a feature
        pcap = std::max(pcap, f.w);
        break;
      case Type::kMean:
        f.w = samples(d.window_s, "window_s", 1);
        pcap = std::max(pcap, f.w);
        break;
      case Type::kAux:
        if (d.signal.empty()) throw std::runtime_error(where + ".signal: missing");
        f.aux_index = static_cast<int>(std::find(aux_names.begin(), aux_names.end(), d.signal) - aux_names.begin());
        f.w = d.lag_s > 0 ? samples(d.lag_s, "lag_s", 1) : 0;
        if (d.time_constant_s > 0) f.a = pole(d.time_constant_s);
        break;
      default: break;
    }
    m.has_aux |= f.type == Type::kAux;
    m.c.push_back(f);
  }
  // One extra slot so that V_{t-w} and D_{t-w} are still held when the window is full.
  m.volts.init(vcap + 1, 0.0);
  m.pos.init(pcap + 1, 0.0);
  m.state.assign(m.c.size(), 0.0);
  m.state2.assign(m.c.size(), 0.0);
  m.aux_hist.resize(m.c.size());
  for (std::size_t i = 0; i < m.c.size(); ++i)
    if (m.c[i].type == Type::kAux && m.c[i].w > 0) m.aux_hist[i].init(m.c[i].w + 1, 0.0);
  reset(0.0, 0.0);
}

FeatureStream::~FeatureStream() = default;
FeatureStream::FeatureStream(const FeatureStream& o) : impl_(std::make_unique<Impl>(*o.impl_)) {}
FeatureStream& FeatureStream::operator=(const FeatureStream& o) {
  if (this != &o) impl_ = std::make_unique<Impl>(*o.impl_);
  return *this;
}

void FeatureStream::reset(double voltage_v, double position_nm) {
  Impl& m = *impl_;
  m.volts.init(m.volts.buf.size(), voltage_v);
  m.pos.init(m.pos.buf.size(), position_nm);
  m.aux_primed = false;
  for (std::size_t i = 0; i < m.c.size(); ++i) {
    const Compiled& f = m.c[i];
    double s = 0, s2 = 0;
    switch (f.type) {
      case Type::kExpSum: s = voltage_v * (1 - f.alpha_w) / (1 - f.alpha); break;  // at rest forever at V
      case Type::kLowpass: s = voltage_v; break;
      case Type::kPlay:
      case Type::kStop:
      case Type::kPlayHinge: s = voltage_v; break;
      case Type::kPlayLowpass: s = voltage_v; s2 = voltage_v; break;
      case Type::kMean: s = position_nm * static_cast<double>(f.w); break;
      default: break;
    }
    m.state[i] = s;
    m.state2[i] = s2;
  }
}

void FeatureStream::compute(const ModelInput& in, double* out) const {
  const Impl& m = *impl_;
  const std::size_t n = m.c.size();
  if (m.spec.mean.empty()) {
    for (std::size_t i = 0; i < n; ++i) out[i] = m.raw(i, in);
  } else {
    for (std::size_t i = 0; i < n; ++i) out[i] = (m.raw(i, in) - m.spec.mean[i]) / m.spec.scale[i];
  }
}

void FeatureStream::commit(const ModelInput& in, double position_nm) {
  Impl& m = *impl_;
  const double v = in.voltage_v;
  for (std::size_t i = 0; i < m.c.size(); ++i) {
    const Compiled& f = m.c[i];
    switch (f.type) {
      case Type::kExpSum: m.state[i] = f.alpha * m.state[i] + v - f.alpha_w * m.volts.get(f.w); break;
      case Type::kLowpass: m.state[i] = f.a * m.state[i] + (1 - f.a) * v; break;
      case Type::kPlay:
      case Type::kStop:
      case Type::kPlayHinge: m.state[i] = play(v, f.r, m.state[i]); break;
      case Type::kPlayLowpass:
        m.state[i] = play(v, f.r, m.state[i]);
        m.state2[i] = f.a * m.state2[i] + (1 - f.a) * m.state[i];
        break;
      case Type::kMean: m.state[i] += position_nm - m.pos.get(f.w); break;
      case Type::kAux: {
        if (!in.aux) throw std::runtime_error("feature '" + m.spec.features[i].name() + "': no aux input given");
        const double now = in.aux[f.aux_index];
        if (!m.aux_primed && f.w > 0) m.aux_hist[i].init(m.aux_hist[i].buf.size(), now);
        const double x = f.w == 0 ? now : m.aux_hist[i].get(f.w);
        m.state2[i] = (m.aux_primed && f.a > 0) ? f.a * m.state2[i] + (1 - f.a) * x : x;
        if (f.w > 0) m.aux_hist[i].push(now);
        break;
      }
      default: break;
    }
  }
  if (m.has_aux) m.aux_primed = true;
  m.volts.push(v);
  m.pos.push(position_nm);
}

std::size_t FeatureStream::size() const { return impl_->c.size(); }
const FeatureSpec& FeatureStream::spec() const { return impl_->spec; }

}  // namespace piezo::features
