// The family table and each family's candidate generator (variants of lag, low-pass, signal, form).
#include "piezo_compensation/analysis/residual/residual_families.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/analysis/residual/residual_context.h"

namespace piezo::analysis {

const std::vector<FamilyTraits>& family_table() {
  // Report order. Fields: id, name, gain, additive counterpart, line in time, operating point, spectral,
  // compares signal, in readings.
  static const std::vector<FamilyTraits> table = {
      {Family::kTimeDrift, "time_drift", false, std::nullopt, true, false, false, false},
      {Family::kCrossAxis, "cross_axis", false, std::nullopt, false, false, false, true},
      {Family::kPositionPeriodic, "position_periodic", false, std::nullopt, false, true, true, true, true},
      {Family::kRateDependent, "rate_dependent", false, std::nullopt, false, true, false, true},
      {Family::kAuxSignal, "aux_signal", false, std::nullopt, false, false, false, true},
      {Family::kPeriodicDisturbance, "periodic_disturbance", false, std::nullopt, false, false, true, true},
      {Family::kMissingMemory, "missing_memory", false, std::nullopt, false, true, false, true},
      {Family::kVoltageNonlinearity, "voltage_nonlinearity", false, std::nullopt, false, true, false, true},
      {Family::kTimeGain, "time_gain", true, Family::kTimeDrift, true, false, false, false},
      {Family::kCrossAxisGain, "cross_axis_gain", true, Family::kCrossAxis, false, false, false, true},
      {Family::kAuxGain, "aux_gain", true, Family::kAuxSignal, false, false, false, true},
  };
  return table;
}

const FamilyTraits& traits(Family f) {
  for (const auto& t : family_table())
    if (t.id == f) return t;
  throw std::logic_error("family missing from the family table");
}

const FamilyTraits* find_family(const std::string& name) {
  for (const auto& t : family_table())
    if (name == t.name) return &t;
  return nullptr;
}

const FamilyTraits& traits_of(const std::string& name) {
  if (const FamilyTraits* t = find_family(name)) return *t;
  throw std::invalid_argument("unknown effect family '" + name + "'");
}

// The string interface of analysis/residual/residual.h, read from the table.
const std::vector<std::string>& residual_family_names() {
  static const std::vector<std::string> names = [] {
    std::vector<std::string> v;
    for (const auto& t : family_table()) v.emplace_back(t.name);
    return v;
  }();
  return names;
}
bool is_gain_family(const std::string& family) {
  const FamilyTraits* t = find_family(family);
  return t && t->gain;
}
std::string additive_counterpart(const std::string& gain_family) {
  const FamilyTraits* t = find_family(gain_family);
  return t && t->additive ? traits(*t->additive).name : "";
}
bool extrapolates_in_time(const std::string& family) {
  const FamilyTraits* t = find_family(family);
  return t && t->line_in_time;
}
bool is_reading_family(const std::string& family) {
  const FamilyTraits* t = find_family(family);
  return t && t->in_readings;
}
bool is_operating_point_family(const std::string& family) {
  const FamilyTraits* t = find_family(family);
  return t && t->operating_point;
}

namespace detail {
namespace {

using models::EffectTerm;

struct Adder {
  FamilyCandidates& fc;
  std::string family;
  void operator()(std::vector<EffectTerm> terms, std::map<std::string, double> p,
                  std::map<std::string, std::string> l = {}) const {
    fc.variants.push_back(Candidate{family, std::move(terms), std::move(p), std::move(l)});
  }
};

void time_drift(const Adder& add) {
  // A constant drift rate: the one time basis that extrapolates sanely past the training data.
  add({make_term(add.family, "linear", models::kSignalTime)}, {});
}

void cross_axis(const Context& c, const Adder& add) {
  if (c.other_axes.empty()) add.fc.note = "no other axis in the data";
  for (const auto& col : c.other_axes) {
    for (double lag : {0.0, 0.5, 1.0, 2.0, 5.0, 10.0})
      for (double tau : {0.0, 2.0, 10.0, 60.0})
        add({make_term(add.family, "linear", col, lag, tau)}, {{"lag_s", lag}, {"time_constant_s", tau}}, {{"signal", col}});
    // The other axis' hysteresis seen from its voltage (a 10-V play); its positions already carry it.
    if (!io::is_voltage_column(col)) continue;
    EffectTerm play = make_term(add.family, "play", col);
    play.threshold = 10.0;
    add({make_term(add.family, "linear", col), play}, {{"lag_s", 0.0}, {"play_threshold_v", 10.0}}, {{"signal", col}});
  }
}

void aux_signal(const Context& c, const Adder& add) {
  if (c.aux_names.empty()) add.fc.note = "no auxiliary column in the data";
  for (const auto& col : c.aux_names)
    for (double lag : {0.0, 10.0, 60.0})
      for (double tau : {0.0, 30.0, 300.0})
        add({make_term(add.family, "linear", col, lag, tau)}, {{"lag_s", lag}, {"time_constant_s", tau}}, {{"signal", col}});
}

// The base output scaled by 1 + f(signal) (f linear here; quadratic and gain-on-voltage are tried at validation).
// Signals as in the additive families, lags/low-passes chosen by the data.
void gain(Family family, const Context& c, const Adder& add) {
  std::vector<std::string> sigs;
  std::vector<double> lags{0.0}, taus{0.0};
  if (family == Family::kTimeGain) {
    sigs = {models::kSignalTime};
  } else if (family == Family::kCrossAxisGain) {
    sigs = c.other_axes;
    lags = {0.0, 1.0, 5.0};
    taus = {0.0, 10.0, 60.0};
    if (sigs.empty()) add.fc.note = "no other axis in the data";
  } else {
    sigs = c.aux_names;
    // Thermal paths are slow: delays up to minutes, low-passes up to ~20 min.
    lags = {0.0, 15.0, 45.0, 120.0};
    taus = {0.0, 30.0, 100.0, 300.0, 1000.0};
    if (sigs.empty()) add.fc.note = "no auxiliary column in the data";
  }
  for (const auto& sig : sigs) {
    const auto [mu, sd] = signal_stats(c, sig);
    if (!(sd > 0)) continue;
    for (double lag : lags)
      for (double tau : taus) {
        EffectTerm t = make_term(add.family, "gain", sig, lag, tau);
        t.scales = models::kSignalPosition;
        t.reference = c.x_at_zero_v;
        t.pre_center = mu;
        t.pre_scale = sd;
        add({t}, {{"lag_s", lag}, {"time_constant_s", tau}}, {{"signal", sig}, {"scales", "position"}});
      }
  }
  if (add.fc.variants.empty() && add.fc.note.empty()) add.fc.note = "signal constant";
}

void rate_dependent(const Adder& add) {
  for (double tau : {0.0, 1.0, 5.0, 20.0, 60.0})
    add({make_term(add.family, "rate", models::kSignalVoltage, 0.0, tau)}, {{"time_constant_s", tau}});
}

void missing_memory(const Adder& add) {
  for (double tau : {10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0})
    add({make_term(add.family, "linear", models::kSignalVoltage, 0.0, tau)}, {{"time_constant_s", tau}});
  for (double r : {5.0, 20.0})
    for (double tau : {30.0, 300.0, 1000.0}) {
      EffectTerm t = make_term(add.family, "play", models::kSignalVoltage, 0.0, tau);
      t.threshold = r;
      add({t}, {{"time_constant_s", tau}, {"play_threshold_v", r}});
    }
}

void voltage_nonlinearity(const Context& c, const std::vector<double>& position, const Adder& add) {
  auto powers = [&](const std::string& sig, const std::vector<double>& v) {
    EffectTerm t = make_term(add.family, "powers", sig);
    t.pre_center = mean_of(v, 0, v.size());
    t.pre_scale = std::max(1e-9, span_of(v) / 2.0);
    return t;
  };
  add({powers(models::kSignalVoltage, c.voltage)}, {}, {{"signal", models::kSignalVoltage}});
  add({powers(models::kSignalPosition, position)}, {}, {{"signal", models::kSignalPosition}});
}

// One sinusoid at the strongest periodogram peak, in time or in position.
void periodic(bool in_time, const Context& c, const std::vector<double>& residual, const std::vector<double>& position,
              std::size_t stride, const Adder& add) {
  FamilyCandidates& fc = add.fc;
  fc.spectral = true;
  const double duration = static_cast<double>(c.x_base.size()) / c.fs;
  std::vector<double> u, r;
  if (in_time) {
    u = c.data->time_s;
    r = residual;
  } else {
    for (std::size_t i = 0; i < residual.size(); i += stride) {
      u.push_back(position[i]);
      r.push_back(residual[i]);
    }
  }
  const double range = span_of(u);
  // Time: at least 8 full periods inside TRAIN (fewer cannot be told from slow structure such as creep the
  // model misses), up to 0.98·Nyquist. Position: at least 4 full periods across the visited range (a smooth
  // shape over the stroke is voltage_nonlinearity's or a gain's; a random walk traverses each period many
  // times), down to 30 nm.
  const double f_min = in_time ? 8.0 / duration : 4.0 / std::max(range, 1e-9);
  const double f_max = in_time ? 0.49 * c.fs : 1.0 / 30.0;
  if (f_max <= f_min) {
    fc.note = in_time ? "data too short" : "position range too small";
    return;
  }
  fc.peak = find_periodic_peak(u, r, f_min, f_max, 4.0);
  if (fc.peak.frequency <= 0) {
    fc.note = fc.peak.skipped.empty() ? "no spectrum" : fc.peak.skipped;
    return;
  }
  const double period = 1.0 / fc.peak.frequency;
  EffectTerm t = make_term(add.family, "sincos", in_time ? models::kSignalTime : models::kSignalPosition);
  t.period = period;
  if (in_time)
    add({t}, {{"period_s", period}, {"frequency_hz", fc.peak.frequency}, {"power_ratio", fc.peak.power_ratio}});
  else
    add({t}, {{"period_nm", period}, {"power_ratio", fc.peak.power_ratio}});
  std::ostringstream os;
  os << "peak " << fc.peak.power_ratio << (in_time ? "× the red-noise background, " : "× the prewhitened noise level, ")
     << fc.peak.searched << " frequencies searched";
  fc.note = os.str();
}

}  // namespace

FamilyCandidates candidates(Family family, const Context& c, const std::vector<double>& residual,
                            const std::vector<double>& position, std::size_t stride) {
  FamilyCandidates fc;
  const Adder add{fc, traits(family).name};
  switch (family) {
    case Family::kTimeDrift: time_drift(add); break;
    case Family::kCrossAxis: cross_axis(c, add); break;
    case Family::kAuxSignal: aux_signal(c, add); break;
    case Family::kTimeGain:
    case Family::kCrossAxisGain:
    case Family::kAuxGain: gain(family, c, add); break;
    case Family::kRateDependent: rate_dependent(add); break;
    case Family::kMissingMemory: missing_memory(add); break;
    case Family::kVoltageNonlinearity: voltage_nonlinearity(c, position, add); break;
    case Family::kPeriodicDisturbance: periodic(true, c, residual, position, stride, add); break;
    case Family::kPositionPeriodic: periodic(false, c, residual, position, stride, add); break;
  }
  return fc;
}

}  // namespace detail
}  // namespace piezo::analysis
