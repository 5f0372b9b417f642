#include "piezo_compensation/can/device_core.h"

#include <algorithm>
#include <stdexcept>

namespace piezo::can {

DeviceCore::DeviceCore(const DeviceConfig& config, Plant plant)
    : config_(config), codec_(config.protocol), plant_(std::move(plant)) {
  if (!plant_) throw std::invalid_argument("device: no plant given");
  if (!(config_.min_voltage_v < config_.max_voltage_v)) throw std::invalid_argument("device: min_voltage_v must be below max_voltage_v");
  for (int i = 0; i < kAxisCount; ++i)
    voltages_v_[i] = std::clamp(config_.initial_voltage_v[i], config_.min_voltage_v, config_.max_voltage_v);
}

DeviceCore::Handled DeviceCore::handle(const can_frame& frame) {
  const DecodeResult r = codec_.decode(frame);
  if (!r.ok()) {
    if (r.error != DecodeError::kUnknownId) ++rejected_;
    return Handled::kIgnored;
  }
  if (std::holds_alternative<SyncFrame>(r.message_value)) return Handled::kSync;
  const auto* c = std::get_if<CommandFrame>(&r.message_value);
  if (!c) return Handled::kIgnored;
  ++commands_;
  // a halted or faulted controller keeps its output
  if (state_ != DeviceState::kOperational || stuck_[c->axis]) return Handled::kCommand;
  voltages_v_[c->axis] = std::clamp(c->voltage_v, config_.min_voltage_v, config_.max_voltage_v);
  return Handled::kCommand;
}

DeviceCore::Output DeviceCore::step() {
  Output out;
  const double dt = period_s();
  out.sample = plant_(voltages_v_, dt);
  time_s_ += dt;
  for (int i = 0; i < kAxisCount; ++i) {
    VoltageReport v;
    v.axis = i;
    v.voltage_v = voltages_v_[i];
    v.sequence = sequence_;
    out.frames.push_back(codec_.encode(v));
    EncoderReport e;
    e.axis = i;
    e.position_m = out.sample.axes[i].measured_position_nm * 1e-9;
    e.sequence = sequence_;
    e.valid = encoder_valid_[i];
    try {
      out.frames.push_back(codec_.encode(e));
    } catch (const std::invalid_argument&) {  // a non-finite or huge reading: report it flagged invalid
      e.position_m = 0.0;
      e.valid = false;
      out.frames.push_back(codec_.encode(e));
    }
  }
  ++sequence_;
  if (state_ == DeviceState::kBoot || time_s_ + 1e-12 >= next_heartbeat_s_) {
    Heartbeat h;
    h.state = state_;
    h.counter = heartbeat_counter_++;
    out.frames.push_back(codec_.encode(h));
    next_heartbeat_s_ = time_s_ + codec_.config().heartbeat_period_s;
  }
  if (boot_samples_left_ > 0 && --boot_samples_left_ == 0 && state_ == DeviceState::kBoot)
    state_ = DeviceState::kOperational;
  return out;
}

void DeviceCore::restart() {
  for (int i = 0; i < kAxisCount; ++i)
    voltages_v_[i] = std::clamp(config_.initial_voltage_v[i], config_.min_voltage_v, config_.max_voltage_v);
  stuck_.fill(false);
  sequence_ = 0;
  heartbeat_counter_ = 0;
  state_ = DeviceState::kBoot;
  boot_samples_left_ = kBootSamples;
}

}  // namespace piezo::can
