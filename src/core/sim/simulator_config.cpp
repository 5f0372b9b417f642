#include "piezo_compensation/sim/simulator_config.h"
#include "piezo_compensation/io/axes.h"

#include <yaml-cpp/yaml.h>

#include <cmath>
#include <functional>
#include <map>
#include <stdexcept>

namespace piezo::sim {

SimulatorConfig default_simulator_config() {
  SimulatorConfig c;
  for (int k = 0; k < io::kAxisCount; ++k) c.axes[k].name = io::kAxisNames[k];
  // a and b: longer stroke, coarse encoders (study §2.2: 250 nm on a/b, 20 nm on c).
  for (int k = 0; k < 2; ++k) {
    c.axes[k].stroke_nm = 6000.0;
    c.axes[k].encoder_quantisation_nm = 250.0;
    c.axes[k].asymmetry_nm = 24.0;
  }
  return c;
}

namespace {

[[noreturn]] void bad(const std::string& where, const std::string& what) {
  throw std::invalid_argument(where + ": " + what);
}

// Reads the scalar keys of one YAML map into fields; unknown keys are an error naming them.
class MapReader {
 public:
  MapReader(const YAML::Node& node, std::string where) : node_(node), where_(std::move(where)) {
    if (!node_.IsMap()) bad(where_, "expected a map of parameters");
  }
  MapReader& num(const std::string& key, double& out) {
    seen_[key] = true;
    if (auto v = node_[key]) {
      try {
        out = v.as<double>();
      } catch (const YAML::Exception&) {
        bad(where_ + "." + key, "expected a number");
      }
      if (!std::isfinite(out)) bad(where_ + "." + key, "must be finite");
    }
    return *this;
  }
  MapReader& integer(const std::string& key, int& out) {
    seen_[key] = true;
    if (auto v = node_[key]) {
      try {
        out = v.as<int>();
      } catch (const YAML::Exception&) {
        bad(where_ + "." + key, "expected an integer");
      }
    }
    return *this;
  }
  MapReader& flag(const std::string& key, bool& out) {
    seen_[key] = true;
    if (auto v = node_[key]) {
      try {
        out = v.as<bool>();
      } catch (const YAML::Exception&) {
        bad(where_ + "." + key, "expected true or false");
      }
    }
    return *this;
  }
  MapReader& list(const std::string& key, std::vector<double>& out) {
    seen_[key] = true;
    if (auto v = node_[key]) {
      if (!v.IsSequence()) bad(where_ + "." + key, "expected a list of numbers");
      out.clear();
      for (const auto& x : v) {
        double d = 0.0;
        try {
          d = x.as<double>();
        } catch (const YAML::Exception&) {
          bad(where_ + "." + key, "expected a list of numbers");
        }
        if (!std::isfinite(d)) bad(where_ + "." + key, "entries must be finite");
        out.push_back(d);
      }
    }
    return *this;
  }
  MapReader& text(const std::string& key, std::string& out) {
    seen_[key] = true;
    if (auto v = node_[key]) {
      if (!v.IsScalar()) bad(where_ + "." + key, "expected a string");
      out = v.as<std::string>();
    }
    return *this;
  }
  void finish() const {
    for (const auto& kv : node_) {
      const std::string key = kv.first.as<std::string>();
      if (!seen_.count(key)) bad(where_ + "." + key, "unknown key");
    }
  }

 private:
  YAML::Node node_;
  std::string where_;
  std::map<std::string, bool> seen_;
};

void read_axis(const YAML::Node& n, const std::string& where, AxisConfig& a) {
  MapReader r(n, where);
  r.num("voltage_min_v", a.voltage_min_v)
      .num("voltage_max_v", a.voltage_max_v)
      .num("stroke_nm", a.stroke_nm)
      .num("loop_width_fraction", a.loop_width_fraction)
      .text("hysteresis_model", a.hysteresis_model)
      .integer("play_operator_count", a.play_operator_count)
      .num("play_weight_decay_v", a.play_weight_decay_v)
      .num("asymmetry_nm", a.asymmetry_nm)
      .integer("creep_mode_count", a.creep_mode_count)
      .num("creep_tau_min_s", a.creep_tau_min_s)
      .num("creep_tau_max_s", a.creep_tau_max_s)
      .num("creep_alpha", a.creep_alpha)
      .num("creep_gain", a.creep_gain)
      .list("creep_spectrum_tau_s", a.creep_spectrum_tau_s)
      .list("creep_spectrum_weights", a.creep_spectrum_weights)
      .integer("preisach_grid_count", a.preisach_grid_count)
      .num("preisach_centre_offset", a.preisach_centre_offset)
      .num("preisach_centre_spread", a.preisach_centre_spread)
      .num("preisach_width_decay", a.preisach_width_decay)
      .flag("preisach_threshold_jitter", a.preisach_threshold_jitter)
      .num("encoder_quantisation_nm", a.encoder_quantisation_nm)
      .num("encoder_noise_sigma_nm", a.encoder_noise_sigma_nm)
      .finish();
}

void read_effects(const YAML::Node& n, const std::string& where, SimulatorConfig& c) {
  if (!n.IsMap()) bad(where, "expected a map of effects");
  for (const auto& kv : n) {
    const std::string name = kv.first.as<std::string>();
    const std::string w = where + "." + name;
    if (name == "thermal_drift") {
      auto& e = c.thermal_drift;
      MapReader(kv.second, w)
          .flag("enabled", e.enabled)
          .num("ambient_c", e.ambient_c)
          .num("amplitude_c", e.amplitude_c)
          .num("period_s", e.period_s)
          .num("noise_c", e.noise_c)
          .num("noise_correlation_s", e.noise_correlation_s)
          .num("lag_s", e.lag_s)
          .num("gain_nm_per_c", e.gain_nm_per_c)
          .finish();
    } else if (name == "cross_axis") {
      auto& e = c.cross_axis;
      MapReader(kv.second, w)
          .flag("enabled", e.enabled)
          .text("source_axis", e.source_axis)
          .text("target_axis", e.target_axis)
          .num("gain", e.gain)
          .finish();
    } else if (name == "encoder_periodic") {
      auto& e = c.encoder_periodic;
      MapReader(kv.second, w)
          .flag("enabled", e.enabled)
          .num("amplitude_nm", e.amplitude_nm)
          .num("period_nm", e.period_nm)
          .num("phase_rad", e.phase_rad)
          .finish();
    } else if (name == "rate_dependent") {
      auto& e = c.rate_dependent;
      MapReader(kv.second, w)
          .flag("enabled", e.enabled)
          .num("gain", e.gain)
          .num("reference_rate_v_per_s", e.reference_rate_v_per_s)
          .num("max_rate_ratio", e.max_rate_ratio)
          .num("filter_s", e.filter_s)
          .finish();
    } else if (name == "periodic_disturbance") {
      auto& e = c.periodic_disturbance;
      MapReader(kv.second, w)
          .flag("enabled", e.enabled)
          .num("amplitude_nm", e.amplitude_nm)
          .num("frequency_hz", e.frequency_hz)
          .num("phase_rad", e.phase_rad)
          .finish();
    } else {
      std::string valid;
      for (const auto& e : effect_names()) valid += (valid.empty() ? "" : ", ") + e;
      bad(w, "unknown effect (valid: " + valid + ")");
    }
  }
}

int config_axis_index(const std::string& name) { return io::axis_index_or_none(name); }

void require(bool ok, const std::string& param, const std::string& what) {
  if (!ok) throw std::invalid_argument("simulator parameter " + param + ": " + what);
}

}  // namespace

void validate(const SimulatorConfig& c) {
  require(c.sample_rate_hz > 0.0 && std::isfinite(c.sample_rate_hz), "sample_rate_hz", "must be > 0");
  for (const auto& a : c.axes) {
    const std::string p = "axes." + a.name + ".";
    require(config_axis_index(a.name) >= 0, "axes", "axis names must be a, b, c");
    require(a.voltage_max_v > a.voltage_min_v, p + "voltage_max_v", "must exceed voltage_min_v");
    require(a.stroke_nm > 0.0, p + "stroke_nm", "must be > 0");
    require(a.loop_width_fraction >= 0.0 && a.loop_width_fraction < 0.5, p + "loop_width_fraction",
            "must be in [0, 0.5)");
    require(a.play_operator_count >= 2 && a.play_operator_count <= 64, p + "play_operator_count", "must be in 2..64");
    require(a.play_weight_decay_v > 0.0, p + "play_weight_decay_v", "must be > 0");
    require(std::fabs(a.asymmetry_nm) < a.stroke_nm, p + "asymmetry_nm", "must be smaller than the stroke");
    require(a.creep_mode_count >= 1 && a.creep_mode_count <= 64, p + "creep_mode_count", "must be in 1..64");
    require(a.creep_tau_min_s > 0.0 && a.creep_tau_max_s >= a.creep_tau_min_s, p + "creep_tau_min_s",
            "need 0 < creep_tau_min_s <= creep_tau_max_s");
    require(a.creep_gain >= 0.0 && a.creep_gain < 1.0, p + "creep_gain", "must be in [0, 1)");
    require(std::isfinite(a.creep_alpha), p + "creep_alpha", "must be finite");
    require(a.hysteresis_model == "prandtl_ishlinskii" || a.hysteresis_model == "preisach", p + "hysteresis_model",
            "must be prandtl_ishlinskii or preisach, got '" + a.hysteresis_model + "'");
    require(a.preisach_grid_count >= 2 && a.preisach_grid_count <= 200, p + "preisach_grid_count",
            "must be in 2..200");
    require(std::fabs(a.preisach_centre_offset) <= 1.0, p + "preisach_centre_offset", "must be in [-1, 1]");
    require(a.preisach_centre_spread > 0.0, p + "preisach_centre_spread", "must be > 0");
    require(a.preisach_width_decay > 0.0, p + "preisach_width_decay", "must be > 0");
    require(a.creep_spectrum_tau_s.size() == a.creep_spectrum_weights.size(), p + "creep_spectrum_weights",
            "needs one weight per entry of creep_spectrum_tau_s");
    require(a.creep_spectrum_tau_s.size() <= 64, p + "creep_spectrum_tau_s", "at most 64 modes");
    double spectrum_sum = 0.0;
    for (std::size_t j = 0; j < a.creep_spectrum_tau_s.size(); ++j) {
      require(a.creep_spectrum_tau_s[j] > 0.0, p + "creep_spectrum_tau_s", "time constants must be > 0");
      spectrum_sum += std::fabs(a.creep_spectrum_weights[j]);
    }
    require(spectrum_sum < 1.0, p + "creep_spectrum_weights", "sum of |weights| must be < 1");
    require(a.encoder_quantisation_nm >= 0.0, p + "encoder_quantisation_nm", "must be >= 0");
    require(a.encoder_noise_sigma_nm >= 0.0, p + "encoder_noise_sigma_nm", "must be >= 0");
  }
  require(c.axes[0].name == "a" && c.axes[1].name == "b" && c.axes[2].name == "c", "axes", "must be a, b, c in order");
  const auto& t = c.thermal_drift;
  require(t.period_s > 0.0, "effects.thermal_drift.period_s", "must be > 0");
  require(t.noise_c >= 0.0, "effects.thermal_drift.noise_c", "must be >= 0");
  require(t.noise_correlation_s > 0.0, "effects.thermal_drift.noise_correlation_s", "must be > 0");
  require(t.lag_s > 0.0, "effects.thermal_drift.lag_s", "must be > 0");
  require(config_axis_index(c.cross_axis.source_axis) >= 0, "effects.cross_axis.source_axis", "must be a, b or c");
  require(config_axis_index(c.cross_axis.target_axis) >= 0, "effects.cross_axis.target_axis", "must be a, b or c");
  require(c.cross_axis.source_axis != c.cross_axis.target_axis, "effects.cross_axis.target_axis",
          "must differ from source_axis");
  require(c.encoder_periodic.period_nm > 0.0, "effects.encoder_periodic.period_nm", "must be > 0");
  require(c.rate_dependent.gain >= 0.0, "effects.rate_dependent.gain", "must be >= 0");
  require(c.rate_dependent.reference_rate_v_per_s > 0.0, "effects.rate_dependent.reference_rate_v_per_s",
          "must be > 0");
  require(c.rate_dependent.max_rate_ratio >= 0.0, "effects.rate_dependent.max_rate_ratio", "must be >= 0");
  require(c.rate_dependent.filter_s > 0.0, "effects.rate_dependent.filter_s", "must be > 0");
  require(c.periodic_disturbance.frequency_hz > 0.0, "effects.periodic_disturbance.frequency_hz", "must be > 0");
}

SimulatorConfig simulator_config_from_yaml(const YAML::Node& root, const std::string& where_prefix) {
  SimulatorConfig c = default_simulator_config();
  if (root.IsNull()) return c;
  if (!root.IsMap()) bad(where_prefix, "expected a map at the top level");
  for (const auto& kv : root) {
    const std::string key = kv.first.as<std::string>();
    const std::string where = where_prefix + ": " + key;
    if (key == "sample_rate_hz") {
      try {
        c.sample_rate_hz = kv.second.as<double>();
      } catch (const YAML::Exception&) {
        bad(where, "expected a number");
      }
    } else if (key == "axes") {
      if (!kv.second.IsMap()) bad(where, "expected a map a/b/c");
      for (const auto& ax : kv.second) {
        const std::string name = ax.first.as<std::string>();
        const int k = config_axis_index(name);
        if (k < 0) bad(where + "." + name, "unknown axis (valid: a, b, c)");
        read_axis(ax.second, where + "." + name, c.axes[k]);
      }
    } else if (key == "effects") {
      read_effects(kv.second, where, c);
    } else {
      bad(where, "unknown key (valid: sample_rate_hz, axes, effects)");
    }
  }
  try {
    validate(c);
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(where_prefix + ": " + e.what());
  }
  return c;
}

SimulatorConfig load_simulator_config(const std::string& yaml_path) {
  YAML::Node root;
  try {
    root = YAML::LoadFile(yaml_path);
  } catch (const YAML::Exception& e) {
    throw std::invalid_argument(yaml_path + ": cannot read simulator config: " + e.what());
  }
  return simulator_config_from_yaml(root, yaml_path);
}

const std::vector<std::string>& effect_names() {
  static const std::vector<std::string> names = {"thermal_drift", "cross_axis", "encoder_periodic", "rate_dependent",
                                                 "periodic_disturbance"};
  return names;
}

namespace {
bool* effect_flag(SimulatorConfig& c, const std::string& name) {
  if (name == "thermal_drift") return &c.thermal_drift.enabled;
  if (name == "cross_axis") return &c.cross_axis.enabled;
  if (name == "encoder_periodic") return &c.encoder_periodic.enabled;
  if (name == "rate_dependent") return &c.rate_dependent.enabled;
  if (name == "periodic_disturbance") return &c.periodic_disturbance.enabled;
  std::string valid;
  for (const auto& e : effect_names()) valid += (valid.empty() ? "" : ", ") + e;
  throw std::invalid_argument("unknown simulator effect '" + name + "' (valid: " + valid + ")");
}
}  // namespace

void enable_effect(SimulatorConfig& config, const std::string& name, bool enabled) {
  *effect_flag(config, name) = enabled;
}

bool effect_enabled(const SimulatorConfig& config, const std::string& name) {
  return *effect_flag(const_cast<SimulatorConfig&>(config), name);
}

std::vector<std::string> enabled_effects(const SimulatorConfig& config) {
  std::vector<std::string> out;
  for (const auto& e : effect_names())
    if (effect_enabled(config, e)) out.push_back(e);
  return out;
}

}  // namespace piezo::sim
