// The controller side of the protocol, for the simulated device (mm3e_sim): takes command frames, holds the
// set points, steps a plant (the simulator) once per encoder period and produces the report frames a real
// MM3E would send. ROS-free and clock-free: the caller decides when a period has passed.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <vector>

#include "piezo_compensation/can/codec.h"
#include "piezo_compensation/sim/manipulator_simulator.h"

namespace piezo::can {

struct DeviceConfig {
  ProtocolConfig protocol;
  double min_voltage_v = -80.0;  // the amplifier's own limits: set points beyond them are clamped
  double max_voltage_v = 80.0;
  std::array<double, kAxisCount> initial_voltage_v{0.0, 0.0, 0.0};
};

// Holds `voltages_v` for dt_s and returns one sample (sim::ManipulatorSimulator::step has this shape).
using Plant = std::function<sim::StepResult(const std::array<double, kAxisCount>& voltages_v, double dt_s)>;

class DeviceCore {
 public:
  DeviceCore(const DeviceConfig& config, Plant plant);

  // What a frame from the bus was for this device. A command is applied (unless the controller is halted); a
  // SYNC (synchronous mode) asks the caller to step() now; anything else is ignored (malformed ones counted).
  enum class Handled { kIgnored, kCommand, kSync };
  Handled handle(const can_frame& frame);

  struct Output {
    std::vector<can_frame> frames;  // per axis a voltage report and an encoder reading, plus a heartbeat when due
    sim::StepResult sample;
  };
  // One encoder period (1 / encoder_rate_hz of simulated time).
  Output step();

  void set_state(DeviceState state) { state_ = state; }
  // Fault injection. restart(): power-up as after a controller reset: every axis at its initial voltage, the
  // report counter from 0, state "boot" (commands ignored, a heartbeat every sample) for kBootSamples samples.
  void restart();
  // A stuck amplifier: the axis keeps its present output and ignores set points until released.
  void set_stuck(int axis, bool stuck) { stuck_.at(axis) = stuck; }
  static constexpr int kBootSamples = 2;
  DeviceState state() const { return state_; }
  void set_encoder_valid(int axis, bool valid) { encoder_valid_.at(axis) = valid; }

  const std::array<double, kAxisCount>& voltages_v() const { return voltages_v_; }
  std::uint64_t commands_received() const { return commands_; }
  std::uint64_t frames_rejected() const { return rejected_; }
  double period_s() const { return 1.0 / codec_.config().encoder_rate_hz; }
  const Codec& codec() const { return codec_; }

 private:
  DeviceConfig config_;
  Codec codec_;
  Plant plant_;
  std::array<double, kAxisCount> voltages_v_{};
  std::array<bool, kAxisCount> encoder_valid_{true, true, true};
  std::array<bool, kAxisCount> stuck_{false, false, false};
  int boot_samples_left_ = 0;
  std::uint32_t sequence_ = 0;
  std::uint16_t heartbeat_counter_ = 0;
  double time_s_ = 0.0, next_heartbeat_s_ = 0.0;
  DeviceState state_ = DeviceState::kOperational;
  std::uint64_t commands_ = 0, rejected_ = 0;
};

}  // namespace piezo::can
