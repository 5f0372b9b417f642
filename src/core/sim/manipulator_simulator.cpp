#include "piezo_compensation/sim/manipulator_simulator.h"

#include <algorithm>
#include <cmath>
#include <optional>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/sim/piezo_axis.h"
#include "piezo_compensation/sim/simulator_config.h"
#include "piezo_compensation/util/splitmix64.h"

namespace piezo::sim {

namespace {

constexpr double kTwoPi = 6.283185307179586;

using util::splitmix64;

int axis_index(const std::string& name) { return io::axis_index_or_none(name); }

}  // namespace

// The simulator's parts, in a named namespace: ManipulatorSimulator::Impl holds them, and a class of external
// linkage may not have fields of an anonymous namespace's types.
namespace manipulator_detail {

// xoshiro256+ with Box–Muller normals: fast, and the same sequence on every platform.
class Rng {
 public:
  explicit Rng(std::uint64_t seed) {
    for (auto& s : s_) s = splitmix64(seed);
  }
  double uniform() {  // (0, 1)
    const std::uint64_t r = s_[0] + s_[3];
    const std::uint64_t t = s_[1] << 17;
    s_[2] ^= s_[0];
    s_[3] ^= s_[1];
    s_[1] ^= s_[2];
    s_[0] ^= s_[3];
    s_[2] ^= t;
    s_[3] = (s_[3] << 45) | (s_[3] >> 19);
    return (static_cast<double>(r >> 11) + 0.5) * (1.0 / 9007199254740992.0);
  }
  double normal() {
    if (has_spare_) {
      has_spare_ = false;
      return spare_;
    }
    const double r = std::sqrt(-2.0 * std::log(uniform()));
    const double a = kTwoPi * uniform();
    spare_ = r * std::sin(a);
    has_spare_ = true;
    return r * std::cos(a);
  }

 private:
  std::uint64_t s_[4];
  double spare_ = 0.0;
  bool has_spare_ = false;
};

// The configured hysteresis model of one axis.
class Hysteresis {
 public:
  explicit Hysteresis(const AxisConfig& c) {
    if (c.hysteresis_model == "preisach")
      preisach_.emplace(c);
    else
      pi_.emplace(c);
  }
  double update(double v, double scale) { return pi_ ? pi_->update(v, scale) : preisach_->update(v, scale); }

 private:
  std::optional<PrandtlIshlinskii> pi_;
  std::optional<Preisach> preisach_;
};

struct Axis {
  AxisConfig cfg;
  Hysteresis hysteresis;
  CreepModes creep;
  Rng rng;
  double v_prev = 0.0;
  double rate_ratio = 0.0;  // low-passed |dV/dt| / reference (rate_dependent effect)
  double v_mid = 0.0, v_half = 1.0;
  Axis(const AxisConfig& c, std::uint64_t seed)
      : cfg(c), hysteresis(c), creep(c), rng(seed),
        v_mid(0.5 * (c.voltage_max_v + c.voltage_min_v)), v_half(0.5 * (c.voltage_max_v - c.voltage_min_v)) {
    v_prev = v_mid;
  }
};

}  // namespace manipulator_detail
using manipulator_detail::Axis;
using manipulator_detail::Hysteresis;
using manipulator_detail::Rng;

struct ManipulatorSimulator::Impl {
  SimulatorConfig cfg;
  std::vector<Axis> axes;
  Rng thermal_rng;
  double time_s = 0.0;
  // thermal state
  double thermal_phase_rad = 0.0, thermal_noise_c = 0.0, thermal_lagged_c = 0.0;
  int cross_source = 0, cross_target = 2;

  Impl(const SimulatorConfig& c, std::uint64_t seed) : cfg(c), thermal_rng(seed ^ 0x7468657266ULL) {
    validate(cfg);
    for (int k = 0; k < 3; ++k) axes.emplace_back(cfg.axes[k], seed * 3 + static_cast<std::uint64_t>(k) + 1);
    // Seed-dependent phase so different runs see different parts of the temperature cycle.
    thermal_phase_rad = kTwoPi * thermal_rng.uniform();
    thermal_lagged_c = cfg.thermal_drift.ambient_c + cfg.thermal_drift.amplitude_c * std::sin(thermal_phase_rad);
    cross_source = axis_index(cfg.cross_axis.source_axis);
    cross_target = axis_index(cfg.cross_axis.target_axis);
  }

  StepResult step(const std::array<double, 3>& voltages_v, double dt_s) {
    if (!(dt_s > 0.0) || !std::isfinite(dt_s)) {
      std::ostringstream os;
      os << "simulator step: dt_s must be finite and > 0, got " << dt_s;
      throw std::invalid_argument(os.str());
    }
    for (int k = 0; k < 3; ++k)
      if (!std::isfinite(voltages_v[k]))
        throw std::invalid_argument(std::string("simulator step: voltage of axis ") + axes[k].cfg.name +
                                    " is not finite");
    time_s += dt_s;
    StepResult out;
    out.time_s = time_s;

    double thermal_offset_nm = 0.0;
    out.temperature_c = cfg.thermal_drift.ambient_c;
    if (cfg.thermal_drift.enabled) {
      const auto& t = cfg.thermal_drift;
      const double a = std::exp(-dt_s / t.noise_correlation_s);
      thermal_noise_c = thermal_noise_c * a + t.noise_c * std::sqrt(1.0 - a * a) * thermal_rng.normal();
      const double temp = t.ambient_c + t.amplitude_c * std::sin(kTwoPi * time_s / t.period_s + thermal_phase_rad) +
                          thermal_noise_c;
      thermal_lagged_c += (temp - thermal_lagged_c) * (1.0 - std::exp(-dt_s / t.lag_s));
      thermal_offset_nm = t.gain_nm_per_c * (thermal_lagged_c - t.ambient_c);
      out.temperature_c = temp;
    }
    const double disturbance_nm =
        cfg.periodic_disturbance.enabled
            ? cfg.periodic_disturbance.amplitude_nm *
                  std::sin(kTwoPi * cfg.periodic_disturbance.frequency_hz * time_s + cfg.periodic_disturbance.phase_rad)
            : 0.0;

    std::array<double, 3> base{};  // hysteresis + asymmetry + creep of each axis
    for (int k = 0; k < 3; ++k) {
      Axis& ax = axes[k];
      const double v = std::clamp(voltages_v[k], ax.cfg.voltage_min_v, ax.cfg.voltage_max_v);
      double scale = 1.0;
      if (cfg.rate_dependent.enabled) {
        const auto& r = cfg.rate_dependent;
        const double ratio = std::min(std::fabs(v - ax.v_prev) / dt_s / r.reference_rate_v_per_s, r.max_rate_ratio);
        ax.rate_ratio += (ratio - ax.rate_ratio) * (1.0 - std::exp(-dt_s / r.filter_s));
        scale = 1.0 + r.gain * ax.rate_ratio;
      }
      ax.v_prev = v;
      const double h = ax.hysteresis.update(v, scale);
      const double creep = ax.creep.update(h, dt_s);
      const double u = (v - ax.v_mid) / ax.v_half;
      base[k] = h + creep + ax.cfg.asymmetry_nm * u * u;
      out.axes[k].voltage_v = v;
    }
    for (int k = 0; k < 3; ++k) {
      Axis& ax = axes[k];
      double y = base[k] + thermal_offset_nm + disturbance_nm;
      if (cfg.cross_axis.enabled && k == cross_target) y += cfg.cross_axis.gain * base[cross_source];
      double reading = y + ax.cfg.encoder_noise_sigma_nm * ax.rng.normal();
      if (cfg.encoder_periodic.enabled)
        reading += cfg.encoder_periodic.amplitude_nm *
                   std::sin(kTwoPi * y / cfg.encoder_periodic.period_nm + cfg.encoder_periodic.phase_rad);
      const double q = ax.cfg.encoder_quantisation_nm;
      if (q > 0.0) reading = q * std::nearbyint(reading / q);
      out.axes[k].true_position_nm = y;
      out.axes[k].measured_position_nm = reading;
    }
    return out;
  }
};

ManipulatorSimulator::ManipulatorSimulator(const SimulatorConfig& config, std::uint64_t seed)
    : impl_(std::make_unique<Impl>(config, seed)) {}
ManipulatorSimulator::~ManipulatorSimulator() = default;
ManipulatorSimulator::ManipulatorSimulator(ManipulatorSimulator&&) noexcept = default;
ManipulatorSimulator& ManipulatorSimulator::operator=(ManipulatorSimulator&&) noexcept = default;

StepResult ManipulatorSimulator::step(const std::array<double, 3>& voltages_v, double dt_s) {
  return impl_->step(voltages_v, dt_s);
}

double ManipulatorSimulator::time_s() const { return impl_->time_s; }
void ManipulatorSimulator::set_thermal_drift(bool on) {
  if (on && !impl_->cfg.thermal_drift.enabled) impl_->thermal_lagged_c = impl_->cfg.thermal_drift.ambient_c;
  impl_->cfg.thermal_drift.enabled = on;
}

const SimulatorConfig& ManipulatorSimulator::config() const { return impl_->cfg; }

io::Dataset ManipulatorSimulator::run(const io::Dataset& program) {
  const std::string src = program.source.empty() ? std::string("simulator program") : program.source;
  const std::size_t n = program.size();
  if (program.axes.empty())
    throw io::DataError(src + ": no <axis>_voltage_v column (a, b or c) to drive the simulator with");
  for (const auto& a : program.axes) {
    if (axis_index(a.name) < 0) throw io::DataError(src + ": unknown axis '" + a.name + "' (valid: a, b, c)");
    if (a.voltage_v.size() != n)
      throw io::DataError(src + ": column " + io::voltage_column(a.name) + " has " +
                          std::to_string(a.voltage_v.size()) + " rows, time_s has " + std::to_string(n));
  }
  io::Dataset out;
  out.source = program.source;
  out.origin = io::kOriginSimulated;
  out.time_s = program.time_s;
  out.segment = program.segment;
  out.phase = program.phase;
  std::vector<int> idx;
  for (const auto& a : program.axes) {
    auto& s = out.add_axis(a.name);
    s.voltage_v.resize(n);
    s.position_nm.resize(n);
    s.true_position_nm.resize(n);
  }
  for (const auto& a : out.axes) idx.push_back(axis_index(a.name));
  std::vector<const std::vector<double>*> vcol(3, nullptr);
  for (const auto& a : program.axes) vcol[axis_index(a.name)] = &a.voltage_v;
  const bool thermal = impl_->cfg.thermal_drift.enabled;
  std::vector<double> temperature;
  if (thermal) temperature.resize(n);

  double nominal_dt = 1.0 / impl_->cfg.sample_rate_hz;
  if (n >= 2) nominal_dt = (program.time_s.back() - program.time_s.front()) / static_cast<double>(n - 1);
  std::array<double, 3> v{};
  for (std::size_t i = 0; i < n; ++i) {
    const double t = program.time_s[i];
    double dt = i == 0 ? t - impl_->time_s : t - program.time_s[i - 1];
    // First row: continue the simulator's clock if the program carries on from it, else one nominal period.
    if (i == 0 && !(dt >= 0.5 * nominal_dt && dt <= 1.5 * nominal_dt)) dt = nominal_dt;
    if (!std::isfinite(t) || !(dt > 0.0)) {
      std::ostringstream os;
      os << src << ": row " << i + 2 << ", column time_s: time does not increase (" << t << " s)";
      throw io::DataError(os.str());
    }
    for (int k = 0; k < 3; ++k) {
      v[k] = vcol[k] ? (*vcol[k])[i] : 0.0;
      if (!std::isfinite(v[k])) {
        std::ostringstream os;
        os << src << ": row " << i + 2 << ", column " << io::voltage_column(impl_->axes[k].cfg.name)
           << ": not a finite voltage";
        throw io::DataError(os.str());
      }
    }
    const StepResult r = impl_->step(v, dt);
    for (std::size_t j = 0; j < idx.size(); ++j) {
      auto& s = out.axes[j];
      const auto& a = r.axes[idx[j]];
      s.voltage_v[i] = a.voltage_v;
      s.position_nm[i] = a.measured_position_nm;
      s.true_position_nm[i] = a.true_position_nm;
    }
    if (thermal) temperature[i] = r.temperature_c;
  }
  out.aux = program.aux;
  if (thermal) {
    out.aux.erase(std::remove_if(out.aux.begin(), out.aux.end(),
                                 [](const io::AuxSignal& s) { return s.name == "temperature_c"; }),
                  out.aux.end());
    out.aux.push_back({"temperature_c", std::move(temperature)});
  }
  return out;
}

}  // namespace piezo::sim
