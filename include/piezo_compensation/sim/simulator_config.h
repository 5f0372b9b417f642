// Parameters of the simulated MM3E manipulator. Every name carries its unit; defaults mirror
// config/simulator.yaml. Equations and parameter choices: docs/simulator.md.
#pragma once

#include <yaml-cpp/yaml.h>

#include <array>
#include <string>
#include <vector>

namespace piezo::sim {

// One piezo axis: hysteresis (Prandtl–Ishlinskii or Preisach), multi-mode creep, encoder.
struct AxisConfig {
  std::string name;                       // "a", "b" or "c"
  double voltage_min_v = -80.0;           // applied voltages are clamped to [min, max]
  double voltage_max_v = 80.0;
  double stroke_nm = 2000.0;              // creep-free (fast) full-range displacement of the hysteresis part
  double loop_width_fraction = 0.10;      // creep-free full-range loop width (at mid voltage) / stroke
  std::string hysteresis_model = "prandtl_ishlinskii";  // or "preisach" (asymmetric relay hysterons)
  int play_operator_count = 12;           // play operators with thresholds r_i = i·(range/2)/n, i = 0..n-1
  double play_weight_decay_v = 40.0;      // play weights w_i ∝ exp(−r_i / decay) for i ≥ 1
  double asymmetry_nm = 8.0;              // static asymmetry: + asymmetry·u², u = normalised voltage
  int creep_mode_count = 12;              // first-order relaxation modes, τ log-spaced
  double creep_tau_min_s = 0.5;
  double creep_tau_max_s = 20000.0;
  double creep_alpha = -0.1;              // mode weights g_j ∝ τ_j^(−α)
  double creep_gain = 0.35;               // Σ g_j: creep displacement at full relaxation / hysteretic displacement
  // Explicit creep spectrum: when creep_spectrum_tau_s is non-empty, the modes are exactly these time constants
  // with these weights (dimensionless, same meaning as g_j) and the log-spaced parameters above are unused.
  std::vector<double> creep_spectrum_tau_s;
  std::vector<double> creep_spectrum_weights;
  // Preisach hysteresis (hysteresis_model: preisach): relays with up/down switching voltages α ≥ β on a
  // grid of preisach_grid_count points over the range; weight density over the relays' centre c = (α+β)/2 and
  // half-width w = (α−β)/2 (both as fractions of the half range R):
  //   μ ∝ exp(−(c − centre_offset)² / (2·centre_spread²)) · exp(−w / width_decay).
  // A centre offset makes the loop asymmetric (a Prandtl–Ishlinskii model's density is uniform in c).
  int preisach_grid_count = 40;
  double preisach_centre_offset = 0.25;
  double preisach_centre_spread = 0.45;
  double preisach_width_decay = 0.25;
  // true: each relay's switching voltages lie at a fixed pseudo-random place inside its grid cell (its weight
  // unchanged), as in a material with a continuous distribution of hysterons. On the plain grid a whole row of
  // relays switches at one voltage: a slowly moving command (a hold trim) then sees one-sample steps of
  // stroke·loop_width/grid (7 nm on a 2-µm axis with 100 points) that no continuous model can follow.
  bool preisach_threshold_jitter = false;
  double encoder_quantisation_nm = 20.0;  // encoder LSB
  double encoder_noise_sigma_nm = 19.97;  // raw Gaussian σ before quantisation (measured σ² ≈ raw² + q²/12)
};

// thermal_drift: y += gain·(T_lag − ambient); T = ambient + amplitude·sin(2πt/period + φ) + OU noise.
struct ThermalDriftConfig {
  bool enabled = false;
  double ambient_c = 22.0;
  double amplitude_c = 0.8;
  double period_s = 5400.0;
  double noise_c = 0.02;              // σ of the Ornstein–Uhlenbeck part of the temperature
  double noise_correlation_s = 300.0;
  double lag_s = 300.0;               // first-order lag between air temperature and the mechanics
  double gain_nm_per_c = 60.0;
};

// cross_axis: y_target += gain·(hysteretic + creep displacement of the source axis).
struct CrossAxisConfig {
  bool enabled = false;
  std::string source_axis = "a";
  std::string target_axis = "c";
  double gain = 0.02;                 // [nm/nm]
};

// encoder_periodic: measured += amplitude·sin(2π·y_true/period + φ) (encoder interpolation error).
struct EncoderPeriodicConfig {
  bool enabled = false;
  double amplitude_nm = 30.0;
  double period_nm = 400.0;
  double phase_rad = 0.0;
};

// rate_dependent: the non-linear play operators (i ≥ 1) are weighted by 1 + gain·ρ, ρ = first-order low-pass
// (filter_s) of min(|dV/dt| / reference, max_rate_ratio): loop width grows with the sweep rate.
struct RateDependentConfig {
  bool enabled = false;
  double gain = 0.4;
  double reference_rate_v_per_s = 10.0;
  double max_rate_ratio = 2.0;
  double filter_s = 1.0;
};

// periodic_disturbance: y += amplitude·sin(2π·frequency·t + phase) (mechanical vibration).
struct PeriodicDisturbanceConfig {
  bool enabled = false;
  double amplitude_nm = 25.0;
  double frequency_hz = 0.05;
  double phase_rad = 0.0;
};

struct SimulatorConfig {
  double sample_rate_hz = 11.0;       // encoder rate (also the rate the batch tools default to)
  std::array<AxisConfig, 3> axes{};   // a, b, c
  ThermalDriftConfig thermal_drift;
  CrossAxisConfig cross_axis;
  EncoderPeriodicConfig encoder_periodic;
  RateDependentConfig rate_dependent;
  PeriodicDisturbanceConfig periodic_disturbance;
};

SimulatorConfig default_simulator_config();
// Reads a YAML file shaped like config/simulator.yaml; keys not given keep their defaults.
// Throws std::invalid_argument naming the file and the bad key (unknown key, wrong type, out of range).
SimulatorConfig load_simulator_config(const std::string& yaml_path);
// The same from a parsed node (e.g. the `simulator:` part of a stage file); errors start with `where`.
SimulatorConfig simulator_config_from_yaml(const YAML::Node& root, const std::string& where);
// Checks ranges; throws std::invalid_argument naming the parameter.
void validate(const SimulatorConfig& config);

// Effect names: thermal_drift, cross_axis, encoder_periodic, rate_dependent, periodic_disturbance.
const std::vector<std::string>& effect_names();
// Throws std::invalid_argument listing the valid names for an unknown one.
void enable_effect(SimulatorConfig& config, const std::string& name, bool enabled = true);
bool effect_enabled(const SimulatorConfig& config, const std::string& name);
std::vector<std::string> enabled_effects(const SimulatorConfig& config);

}  // namespace piezo::sim
