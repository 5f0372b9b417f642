// The simulated MM3E manipulator: three piezo axes with hysteresis, creep, encoders and optional extra effects.
// ROS-free; deterministic for a given seed. Parameters and equations: docs/simulator.md, config/simulator.yaml.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"

namespace piezo::sim {

struct SimulatorConfig;  // defined in sim/simulator_config.h

// One encoder sample of one axis.
struct AxisReading {
  double voltage_v = 0.0;             // voltage applied over the step [V]
  double true_position_nm = 0.0;      // noise-free position [nm] (evaluation only)
  double measured_position_nm = 0.0;  // encoder reading: quantised, noisy, with any encoder effects [nm]
};

struct StepResult {
  double time_s = 0.0;                 // simulated time at the end of the step
  std::array<AxisReading, 3> axes{};   // a, b, c
  double temperature_c = 0.0;          // simulated temperature channel (meaningful when thermal drift is on)
};

class ManipulatorSimulator {
 public:
  // Throws std::invalid_argument naming the bad parameter.
  ManipulatorSimulator(const SimulatorConfig& config, std::uint64_t seed);
  ~ManipulatorSimulator();
  ManipulatorSimulator(ManipulatorSimulator&&) noexcept;
  ManipulatorSimulator& operator=(ManipulatorSimulator&&) noexcept;

  // Step-at-a-time API (the simulated CAN device): hold `voltages_v` (a, b, c; clamped to each axis' limits)
  // for dt_s seconds, then take one encoder sample. Any dt_s > 0 is accepted.
  StepResult step(const std::array<double, 3>& voltages_v, double dt_s);

  // Batch API: runs the voltage columns of `program` (any axes present; missing axes are held at 0 V) at the
  // program's own sample times and returns a data set with measured and true positions filled in, plus the
  // auxiliary column `temperature_c` when thermal drift is on. The simulator continues from its current state.
  io::Dataset run(const io::Dataset& program);

  double time_s() const;
  const SimulatorConfig& config() const;
  // Switches the thermal drift effect (its configured parameters) on or off from now on. Switched on, the
  // mechanics start at the ambient temperature and follow the air through the lag, so the position does not jump;
  // switched off, the thermal offset goes at once.
  void set_thermal_drift(bool on);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace piezo::sim
