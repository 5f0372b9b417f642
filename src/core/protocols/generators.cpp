// The protocol generators. Each one precomputes its whole voltage program once (deterministic by seed),
// so at(i) is random access and a recording resumes exactly where it stopped.
#include "generators.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/util/splitmix64.h"

namespace piezo::protocols {

namespace {

// Built-in defaults; config/protocols.yaml mirrors them (a unit test keeps the two equal).
const char* kDefaults = R"(
noise: {levels_v: [-80.0, -40.0, 0.0, 40.0, 80.0], settle_s: 180.0, record_s: 20.0}
random_walk:
  duration_s: 3600.0
  bound_v: 80.0
  start_v: 0.0
  trend_sigma_v_per_s: 0.6
  trend_correlation_s: 120.0
  slow_trend_factor: 0.3
  fast_trend_factor: 3.0
  slow_step_sigma_v: 0.03
  fast_step_sigma_v: 0.4
  mean_slow_s: 240.0
  mean_fast_s: 60.0
  pause_interval_s: 600.0
  pause_min_s: 20.0
  pause_max_s: 300.0
  end_ramp_s: 20.0
sweep:
  lower_v: -80.0
  upper_v: 80.0
  fractions: [0.25, 0.5, 0.75]
  fraction_step_v: 0.25
  cycles: 1
  full_range_step_sizes_v: [1.25, 0.5, 0.1, 0.05, 0.01]
  transition_step_v: 1.25
creep:
  scenarios: 15
  history_s: 1800.0
  hold_s: 1800.0
  target_range_v: 60.0
  pre_approach_s: 30.0
  pre_dwell_s: 120.0
  approach_min_s: 5.0
  approach_max_s: 60.0
  approach_min_v: 20.0
  approach_max_v: 140.0
  random_walk: {}
plan: {train_s: 57600.0, validation_s: 18000.0, test_s: 18000.0, random_walk: {}, creep: {}}
sawtooth: {teeth: 8, amplitude_start_v: 10.0, amplitude_end_v: 80.0, rate_v_per_s: 4.0, center_v: 0.0, hold_s: 0.0}
)";

constexpr double kTwoPi = 6.283185307179586;
constexpr std::size_t kMaxSamples = 50'000'000;  // ~52 days at 11 Hz: guards against absurd durations

using util::splitmix64;

// Small self-contained generator so programs are identical on every platform and library version.
class Rng {
 public:
  Rng(std::uint64_t seed, std::uint64_t stream) : state_(seed * 0x2545F4914F6CDD1DULL + stream * 0x9E3779B97F4A7C15ULL) {
    splitmix64(state_);
  }
  double uniform() { return (static_cast<double>(splitmix64(state_) >> 11) + 0.5) * (1.0 / 9007199254740992.0); }
  double uniform(double lo, double hi) { return lo + (hi - lo) * uniform(); }
  double normal() {
    const double r = std::sqrt(-2.0 * std::log(uniform()));
    return r * std::cos(kTwoPi * uniform());
  }

 private:
  std::uint64_t state_;
};

// Typed access to the merged parameters, errors naming "<protocol>.<key>".
class Params {
 public:
  Params(YAML::Node node, std::string where) : node_(std::move(node)), where_(std::move(where)) {}
  double num(const std::string& key, double lo = -1e300, double hi = 1e300) const {
    double v = 0.0;
    try {
      v = node_[key].as<double>();
    } catch (const YAML::Exception&) {
      fail(key, "expected a number");
    }
    if (!std::isfinite(v) || v < lo || v > hi) {
      std::ostringstream os;
      os << "must be in [" << lo << ", " << hi << "], got " << v;
      fail(key, os.str());
    }
    return v;
  }
  int integer(const std::string& key, int lo, int hi) const {
    int v = 0;
    try {
      v = node_[key].as<int>();
    } catch (const YAML::Exception&) {
      fail(key, "expected an integer");
    }
    if (v < lo || v > hi) fail(key, "must be in [" + std::to_string(lo) + ", " + std::to_string(hi) + "]");
    return v;
  }
  std::vector<double> list(const std::string& key, double lo, double hi) const {
    std::vector<double> out;
    const YAML::Node n = node_[key];
    if (!n.IsSequence() || n.size() == 0) fail(key, "expected a non-empty list of numbers");
    for (const auto& x : n) {
      double v = 0.0;
      try {
        v = x.as<double>();
      } catch (const YAML::Exception&) {
        fail(key, "expected a list of numbers");
      }
      if (!std::isfinite(v) || v < lo || v > hi) fail(key, "entries must be within [" + std::to_string(lo) + ", " +
                                                               std::to_string(hi) + "]");
      out.push_back(v);
    }
    return out;
  }
  YAML::Node node(const std::string& key) const { return node_[key]; }
  [[noreturn]] void fail(const std::string& key, const std::string& what) const {
    throw std::invalid_argument("protocol parameter " + where_ + "." + key + ": " + what);
  }
  const std::string& where() const { return where_; }

 private:
  YAML::Node node_;
  std::string where_;
};

// Voltage program storage (the 41 h default plan: ~45 MB).
struct Table {
  std::vector<double> v[3];
  std::vector<std::int32_t> segment;
  std::vector<std::uint8_t> phase;
  std::array<double, 3> last{};

  std::size_t size() const { return segment.size(); }
  void push(const std::array<double, 3>& volts, int seg, Phase ph) {
    if (size() >= kMaxSamples) throw std::invalid_argument("protocol longer than 50 million samples: reduce durations");
    for (int k = 0; k < 3; ++k) v[k].push_back(volts[k]);
    segment.push_back(seg);
    phase.push_back(static_cast<std::uint8_t>(ph));
    last = volts;
  }
  void push_same(double volts, int seg, Phase ph) { push({volts, volts, volts}, seg, ph); }
  // Linear ramp of all three axes from `last` to `to`, `step_v` per sample at most; ends exactly on `to`.
  void ramp_to(const std::array<double, 3>& to, double step_v, int seg, Phase ph) {
    double dist = 0.0;
    for (int k = 0; k < 3; ++k) dist = std::max(dist, std::fabs(to[k] - last[k]));
    const auto n = static_cast<std::size_t>(std::ceil(dist / step_v - 1e-9));
    const std::array<double, 3> from = last;
    for (std::size_t i = 1; i <= n; ++i) {
      std::array<double, 3> x{};
      for (int k = 0; k < 3; ++k) x[k] = from[k] + (to[k] - from[k]) * static_cast<double>(i) / static_cast<double>(n);
      push(x, seg, ph);
    }
  }
};

std::size_t samples(double seconds, double rate) { return static_cast<std::size_t>(std::llround(seconds * rate)); }

struct WalkParams {
  double bound_v, start_v, trend_sigma, trend_corr_s, slow_factor, fast_factor, slow_sigma, fast_sigma, mean_slow_s,
      mean_fast_s, pause_interval_s, pause_min_s, pause_max_s, end_ramp_s, duration_s;
};

WalkParams read_walk(const Params& p) {
  WalkParams w{};
  w.duration_s = p.num("duration_s", 0.0, 1e8);
  w.bound_v = p.num("bound_v", 0.0, 1e4);
  w.start_v = p.num("start_v", -w.bound_v, w.bound_v);
  w.trend_sigma = p.num("trend_sigma_v_per_s", 0.0, 1e4);
  w.trend_corr_s = p.num("trend_correlation_s", 1e-6, 1e8);
  w.slow_factor = p.num("slow_trend_factor", 0.0, 1e4);
  w.fast_factor = p.num("fast_trend_factor", 0.0, 1e4);
  w.slow_sigma = p.num("slow_step_sigma_v", 0.0, 1e4);
  w.fast_sigma = p.num("fast_step_sigma_v", 0.0, 1e4);
  w.mean_slow_s = p.num("mean_slow_s", 1e-6, 1e8);
  w.mean_fast_s = p.num("mean_fast_s", 1e-6, 1e8);
  w.pause_interval_s = p.num("pause_interval_s", 0.0, 1e8);
  w.pause_min_s = p.num("pause_min_s", 0.0, 1e8);
  w.pause_max_s = p.num("pause_max_s", w.pause_min_s, 1e8);
  w.end_ramp_s = p.num("end_ramp_s", 0.0, 1e8);
  return w;
}

// Three independent bounded walks with a persistent trend (OU velocity), slow/fast modes and shared pauses.
void append_walk(Table& t, const WalkParams& w, double rate, std::size_t n, std::uint64_t seed, std::uint64_t stream,
                 int seg, bool pauses, double end_ramp_s) {
  const double dt = 1.0 / rate;
  Rng axis_rng[3] = {Rng(seed, stream * 8 + 1), Rng(seed, stream * 8 + 2), Rng(seed, stream * 8 + 3)};
  Rng pause_rng(seed, stream * 8 + 4);
  const double a = std::exp(-dt / w.trend_corr_s);
  const double b = std::sqrt(1.0 - a * a);
  std::array<double, 3> v = t.last, d{};
  bool fast[3] = {false, false, false};
  for (int k = 0; k < 3; ++k) d[k] = w.trend_sigma * axis_rng[k].normal();
  const std::size_t n_ramp = std::min(n, samples(end_ramp_s, rate));
  const std::size_t n_walk = n - n_ramp;
  std::size_t pause_left = 0;
  for (std::size_t i = 0; i < n_walk; ++i) {
    if (pause_left == 0 && pauses && w.pause_interval_s > 0.0 && pause_rng.uniform() < dt / w.pause_interval_s)
      pause_left = std::max<std::size_t>(1, samples(pause_rng.uniform(w.pause_min_s, w.pause_max_s), rate));
    if (pause_left > 0) {
      --pause_left;
      t.push(v, seg, Phase::kHold);
      continue;
    }
    for (int k = 0; k < 3; ++k) {
      Rng& r = axis_rng[k];
      if (r.uniform() < dt / (fast[k] ? w.mean_fast_s : w.mean_slow_s)) fast[k] = !fast[k];
      d[k] = a * d[k] + b * w.trend_sigma * r.normal();
      v[k] += d[k] * (fast[k] ? w.fast_factor : w.slow_factor) * dt + (fast[k] ? w.fast_sigma : w.slow_sigma) * r.normal();
      // Reflect at the bounds and turn the trend around, so the walk reaches the extremes without sticking.
      if (v[k] > w.bound_v) {
        v[k] = 2.0 * w.bound_v - v[k];
        d[k] = -std::fabs(d[k]);
      } else if (v[k] < -w.bound_v) {
        v[k] = -2.0 * w.bound_v - v[k];
        d[k] = std::fabs(d[k]);
      }
      v[k] = std::clamp(v[k], -w.bound_v, w.bound_v);
    }
    t.push(v, seg, Phase::kExcite);
  }
  const std::array<double, 3> from = t.last;
  for (std::size_t i = 1; i <= n_ramp; ++i) {
    const double f = static_cast<double>(i) / static_cast<double>(n_ramp);
    t.push({from[0] * (1 - f), from[1] * (1 - f), from[2] * (1 - f)}, seg, Phase::kExcite);
  }
}

void append_creep(Table& t, const Params& p, const WalkParams& walk, double rate, std::uint64_t seed, int seg0) {
  const int scenarios = p.integer("scenarios", 1, 1000);
  const double history_s = p.num("history_s", 1.0 / rate, 1e7);
  const double hold_s = p.num("hold_s", 0.0, 1e7);
  const double target_v = p.num("target_range_v", 0.0, walk.bound_v);
  const double pre_s = p.num("pre_approach_s", 0.0, history_s);
  const double amin_s = p.num("approach_min_s", 1.0 / rate, history_s);
  const double amax_s = p.num("approach_max_s", amin_s, history_s);
  // The dwell gives way to short histories (tests, quick runs) instead of rejecting them.
  const double dwell_s = std::min(p.num("pre_dwell_s", 0.0, 1e7), std::max(0.0, history_s - pre_s - amax_s));
  const double amin_v = p.num("approach_min_v", 0.0, 2.0 * walk.bound_v);
  const double amax_v = p.num("approach_max_v", amin_v, 2.0 * walk.bound_v);
  if (pre_s + amax_s > history_s) p.fail("history_s", "must be at least pre_approach_s + approach_max_s");
  Rng rng(seed, 1000);
  for (int s = 0; s < scenarios; ++s) {
    const std::size_t n_hist = std::max<std::size_t>(1, samples(history_s, rate));
    const std::size_t n_app = std::max<std::size_t>(1, samples(rng.uniform(amin_s, amax_s), rate));
    const std::size_t n_pre = samples(pre_s, rate), n_dwell = samples(dwell_s, rate);
    const std::size_t n_walk = n_hist > n_app + n_pre + n_dwell ? n_hist - n_app - n_pre - n_dwell : 0;
    append_walk(t, walk, rate, n_walk, seed, 2000 + static_cast<std::uint64_t>(s), seg0 + s, false, 0.0);
    // The history ends with a quick approach to the hold voltage from alternating sides (and per axis), so the
    // 15 drifts differ in size and take both signs.
    std::array<double, 3> target{}, pre{};
    for (int k = 0; k < 3; ++k) {
      const double dir = ((s + k) % 2 == 0) ? 1.0 : -1.0;
      target[k] = rng.uniform(-target_v, target_v);
      pre[k] = std::clamp(target[k] - dir * rng.uniform(amin_v, amax_v), -walk.bound_v, walk.bound_v);
    }
    const auto ramp = [&](const std::array<double, 3>& to, std::size_t n) {
      const std::array<double, 3> from = t.last;
      for (std::size_t i = 1; i <= n; ++i) {
        const double f = static_cast<double>(i) / static_cast<double>(n);
        t.push({from[0] + (to[0] - from[0]) * f, from[1] + (to[1] - from[1]) * f, from[2] + (to[2] - from[2]) * f},
               seg0 + s, Phase::kExcite);
      }
    };
    ramp(pre, n_pre);
    for (std::size_t i = 0; i < n_dwell; ++i) t.push(pre, seg0 + s, Phase::kExcite);  // let the opposite creep fade
    ramp(target, n_app);
    const std::size_t n_hold = samples(hold_s, rate);
    for (std::size_t i = 0; i < n_hold; ++i) t.push(target, seg0 + s, Phase::kHold);
  }
}

class Generated : public Protocol {
 public:
  Generated(std::string name, YAML::Node params, double rate, std::uint64_t seed)
      : name_(std::move(name)), params_(std::move(params)), rate_(rate), seed_(seed) {}
  std::string name() const override { return name_; }
  std::size_t size() const override { return table.size(); }
  double sample_rate_hz() const override { return rate_; }
  ProtocolSample at(std::size_t i) const override {
    if (i >= table.size())
      throw std::out_of_range("protocol " + name_ + ": sample " + std::to_string(i) + " beyond the end (" +
                              std::to_string(table.size()) + " samples)");
    ProtocolSample s;
    for (int k = 0; k < 3; ++k) s.voltage_v[k] = table.v[k][i];
    s.segment = table.segment[i];
    s.phase = static_cast<Phase>(table.phase[i]);
    return s;
  }
  YAML::Node parameters() const override {
    YAML::Node n;
    n["protocol"] = name_;
    n["sample_rate_hz"] = rate_;
    n["seed"] = seed_;
    n["parameters"] = YAML::Clone(params_);
    return n;
  }
  Table table;

 private:
  std::string name_;
  YAML::Node params_;
  double rate_;
  std::uint64_t seed_;
};

void build_noise(Generated& g, const Params& p, double rate) {
  const auto levels = p.list("levels_v", -1e4, 1e4);
  const std::size_t n_settle = samples(p.num("settle_s", 0.0, 1e7), rate);
  const std::size_t n_record = samples(p.num("record_s", 1.0 / rate, 1e7), rate);
  for (std::size_t j = 0; j < levels.size(); ++j) {
    for (std::size_t i = 0; i < n_settle; ++i) g.table.push_same(levels[j], static_cast<int>(j), Phase::kSettle);
    for (std::size_t i = 0; i < n_record; ++i) g.table.push_same(levels[j], static_cast<int>(j), Phase::kRecord);
  }
}

void build_sweep(Generated& g, const Params& p) {
  const double lo = p.num("lower_v", -1e4, 1e4);
  const double hi = p.num("upper_v", lo + 1e-6, 1e4);
  const auto fractions = p.list("fractions", 1e-3, 1.0);
  const double fstep = p.num("fraction_step_v", 1e-4, 1e4);
  const int cycles = p.integer("cycles", 1, 1000);
  const auto steps = p.list("full_range_step_sizes_v", 1e-4, 1e4);
  const double tstep = p.num("transition_step_v", 1e-4, 1e4);
  Table& t = g.table;
  t.last = {lo, lo, lo};
  int seg = 0;
  const double range = hi - lo;
  // Partial windows of width f·range, m starting points spread evenly over the range.
  for (double f : fractions) {
    const double w = f * range;
    const int m = f >= 1.0 ? 1 : std::max(2, static_cast<int>(std::lround(2.0 / f)) - 1);
    for (int j = 0; j < m; ++j, ++seg) {
      const double start = m == 1 ? lo : lo + (range - w) * j / (m - 1);
      t.ramp_to({start, start, start}, tstep, seg, Phase::kExcite);
      if (t.size() == 0) t.push_same(start, seg, Phase::kSweep);
      for (int c = 0; c < cycles; ++c) {
        t.ramp_to({start + w, start + w, start + w}, fstep, seg, Phase::kSweep);
        t.ramp_to({start, start, start}, fstep, seg, Phase::kSweep);
      }
    }
  }
  for (double s : steps) {
    t.ramp_to({lo, lo, lo}, tstep, seg, Phase::kExcite);
    if (t.size() == 0) t.push_same(lo, seg, Phase::kSweep);
    t.ramp_to({hi, hi, hi}, s, seg, Phase::kSweep);
    t.ramp_to({lo, lo, lo}, s, seg, Phase::kSweep);
    ++seg;
  }
}

void build_sawtooth(Generated& g, const Params& p, double rate) {
  const int teeth = p.integer("teeth", 1, 10000);
  const double a0 = p.num("amplitude_start_v", 0.0, 1e4);
  const double a1 = p.num("amplitude_end_v", 0.0, 1e4);
  const double step = p.num("rate_v_per_s", 1e-6, 1e6) / rate;
  const double center = p.num("center_v", -1e4, 1e4);
  const std::size_t n_hold = samples(p.num("hold_s", 0.0, 1e7), rate);
  Table& t = g.table;
  t.last = {center, center, center};
  t.push_same(center, 0, Phase::kSweep);
  for (int j = 0; j < teeth; ++j) {
    const double a = teeth == 1 ? a0 : a0 + (a1 - a0) * j / (teeth - 1);
    for (double target : {center + a, center - a, center}) t.ramp_to({target, target, target}, step, j, Phase::kSweep);
    for (std::size_t i = 0; i < n_hold; ++i) t.push_same(center, j, Phase::kHold);
  }
}

WalkParams walk_params(const YAML::Node& defaults, const YAML::Node& overrides, const std::string& where) {
  return read_walk(Params(merge_parameters(defaults, overrides, where), where));
}

}  // namespace

YAML::Node default_protocol_parameters() { return YAML::Load(kDefaults); }

YAML::Node load_protocol_parameters(const std::string& yaml_path, const std::string& name) {
  YAML::Node root;
  try {
    root = YAML::LoadFile(yaml_path);
  } catch (const YAML::Exception& e) {
    throw std::invalid_argument(yaml_path + ": cannot read protocols file: " + e.what());
  }
  if (!root.IsNull() && !root.IsMap()) throw std::invalid_argument(yaml_path + ": expected a map of protocols");
  return root[name] ? YAML::Clone(root[name]) : YAML::Node();
}

YAML::Node merge_parameters(const YAML::Node& defaults, const YAML::Node& overrides, const std::string& where) {
  YAML::Node out = YAML::Clone(defaults);
  if (!overrides || overrides.IsNull()) return out;
  if (!overrides.IsMap()) throw std::invalid_argument("protocol parameters " + where + ": expected a map");
  for (const auto& kv : overrides) {
    const std::string key = kv.first.as<std::string>();
    const std::string w = where + "." + key;
    const YAML::Node def = defaults[key];
    if (!def) {
      std::string valid;
      for (const auto& d : defaults) valid += (valid.empty() ? "" : ", ") + d.first.as<std::string>();
      throw std::invalid_argument("protocol parameter " + w + ": unknown key (valid: " + valid + ")");
    }
    if (def.IsMap()) {
      // Nested override maps (plan.random_walk, creep.random_walk) are checked against the real defaults later.
      if (!kv.second.IsMap() && !kv.second.IsNull())
        throw std::invalid_argument("protocol parameter " + w + ": expected a map");
      out[key] = def.size() ? merge_parameters(def, kv.second, w) : YAML::Clone(kv.second);
    } else if (def.IsSequence()) {
      if (!kv.second.IsSequence()) throw std::invalid_argument("protocol parameter " + w + ": expected a list");
      out[key] = YAML::Clone(kv.second);
    } else {
      if (!kv.second.IsScalar()) throw std::invalid_argument("protocol parameter " + w + ": expected a number");
      out[key] = YAML::Clone(kv.second);
    }
  }
  return out;
}

std::unique_ptr<Protocol> make_generated(const std::string& name, const YAML::Node& params, double rate,
                                         std::uint64_t seed) {
  auto g = std::make_unique<Generated>(name, params, rate, seed);
  const Params p(params, name);
  const YAML::Node defaults = default_protocol_parameters();
  if (name == "noise") {
    build_noise(*g, p, rate);
  } else if (name == "random_walk") {
    const WalkParams w = read_walk(p);
    g->table.last = {w.start_v, w.start_v, w.start_v};
    append_walk(g->table, w, rate, samples(w.duration_s, rate), seed, 0, 0, true, w.end_ramp_s);
  } else if (name == "sweep") {
    build_sweep(*g, p);
  } else if (name == "creep") {
    const WalkParams w = walk_params(defaults["random_walk"], p.node("random_walk"), name + ".random_walk");
    g->table.last = {w.start_v, w.start_v, w.start_v};
    append_creep(g->table, p, w, rate, seed, 0);
  } else if (name == "plan") {
    const YAML::Node walk_over = p.node("random_walk");
    const WalkParams w = walk_params(defaults["random_walk"], walk_over, name + ".random_walk");
    const char* series[3] = {"train_s", "validation_s", "test_s"};
    g->table.last = {w.start_v, w.start_v, w.start_v};
    for (int s = 0; s < 3; ++s)
      append_walk(g->table, w, rate, samples(p.num(series[s], 0.0, 1e8), rate), seed, 1 + static_cast<std::uint64_t>(s),
                  s, true, w.end_ramp_s);
    const std::string cw = name + ".creep";
    const YAML::Node creep = merge_parameters(defaults["creep"], p.node("creep"), cw);
    const YAML::Node plan_walk = merge_parameters(defaults["random_walk"], walk_over, name + ".random_walk");
    const WalkParams cwalk = walk_params(plan_walk, creep["random_walk"], cw + ".random_walk");
    append_creep(g->table, Params(creep, cw), cwalk, rate, seed + 7, 3);
  } else if (name == "sawtooth") {
    build_sawtooth(*g, p, rate);
  } else {
    throw std::invalid_argument("unknown protocol '" + name + "'");
  }
  if (g->size() == 0) throw std::invalid_argument("protocol " + name + ": the parameters give an empty program");
  return g;
}

}  // namespace piezo::protocols
