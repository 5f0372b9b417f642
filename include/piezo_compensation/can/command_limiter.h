// The safety rules between a voltage command and the bus, for one axis: clamp to limits, slew limit,
// NaN/Inf rejection, command watchdog that HOLDS the last applied voltage (never drops to 0 V), and holds for
// halt or a second commander. Pure: time comes in as an argument (ROS time in the node, so sim time works).
#pragma once

#include <cstdint>
#include <optional>
#include <string>

namespace piezo::can {

struct LimiterConfig {
  double min_voltage_v = -80.0;
  double max_voltage_v = 80.0;
  double slew_rate_v_per_s = 200.0;   // largest rate of change of the applied voltage
  double command_timeout_s = 0.5;     // no command for this long → hold the applied voltage
  double max_step_dt_s = 0.1;         // longest interval one output step may cover (bounds a single jump)
};

// Throws std::invalid_argument naming the field.
void validate(const LimiterConfig& config);

enum class CommandOutcome {
  kAccepted,
  kClamped,        // accepted, outside the limits: clamped
  kRejectedNonFinite,
  kRejectedNoBaseline,  // the device has not reported its voltage yet: nothing to slew from
  kRejectedHeld,   // halted or more than one commander
};
const char* to_string(CommandOutcome outcome);

enum class HoldReason : std::uint8_t { kNone = 0, kHalted = 1, kMultipleCommanders = 2 };

class CommandLimiter {
 public:
  explicit CommandLimiter(const LimiterConfig& config);

  // The device's reported voltage. Until the driver has sent its own set point it is the baseline the slew
  // limit starts from (the voltage the piezo really has).
  void on_reported_voltage(double voltage_v);

  CommandOutcome command(double voltage_v, double now_s);

  // Advances the slew ramp and the watchdog. Returns the voltage to send now, or nothing when the applied
  // voltage does not change. Every value returned is within [min, max].
  std::optional<double> step(double now_s);

  void set_hold(HoldReason reason, bool on);  // halt / multiple commanders: stop where it is, refuse commands
  bool held() const { return holds_ != 0; }
  bool held_for(HoldReason reason) const { return holds_ & static_cast<std::uint8_t>(reason); }
  // After a reconnect the device may have moved on its own: re-baseline from its next report.
  void rebaseline();

  bool has_baseline() const { return has_applied_; }
  double applied_v() const { return applied_v_; }
  double target_v() const { return target_v_; }
  bool timed_out() const { return timed_out_; }
  std::uint64_t timeouts() const { return timeouts_; }
  const LimiterConfig& config() const { return config_; }

 private:
  LimiterConfig config_;
  bool has_applied_ = false;
  bool sent_once_ = false;   // driver has sent a set point since the last baseline
  double applied_v_ = 0.0;   // last voltage sent (or reported, before the first send)
  double target_v_ = 0.0;
  double last_step_s_ = 0.0;
  bool has_step_time_ = false;
  double last_command_s_ = 0.0;
  bool has_command_ = false;
  bool timed_out_ = false;
  std::uint64_t timeouts_ = 0;
  std::uint8_t holds_ = 0;
};

}  // namespace piezo::can
