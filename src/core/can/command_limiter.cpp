#include "piezo_compensation/can/command_limiter.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace piezo::can {

void validate(const LimiterConfig& c) {
  auto finite = [](double v) { return std::isfinite(v); };
  if (!finite(c.min_voltage_v) || !finite(c.max_voltage_v) || c.min_voltage_v >= c.max_voltage_v)
    throw std::invalid_argument("min_voltage_v must be finite and below max_voltage_v");
  if (c.min_voltage_v < -1000.0 || c.max_voltage_v > 1000.0)
    throw std::invalid_argument("min_voltage_v/max_voltage_v must be within ±1000 V");
  if (!finite(c.slew_rate_v_per_s) || c.slew_rate_v_per_s <= 0)
    throw std::invalid_argument("slew_rate_v_per_s must be a finite value > 0");
  if (!finite(c.command_timeout_s) || c.command_timeout_s <= 0)
    throw std::invalid_argument("command_timeout_s must be a finite value > 0");
  if (!finite(c.max_step_dt_s) || c.max_step_dt_s <= 0)
    throw std::invalid_argument("max_step_dt_s must be a finite value > 0");
}

const char* to_string(CommandOutcome outcome) {
  switch (outcome) {
    case CommandOutcome::kAccepted: return "accepted";
    case CommandOutcome::kClamped: return "clamped";
    case CommandOutcome::kRejectedNonFinite: return "rejected: not finite";
    case CommandOutcome::kRejectedNoBaseline: return "rejected: no voltage report from the device yet";
    case CommandOutcome::kRejectedHeld: return "rejected: axis is held";
  }
  return "unknown";
}

CommandLimiter::CommandLimiter(const LimiterConfig& config) : config_(config) { validate(config_); }

void CommandLimiter::on_reported_voltage(double voltage_v) {
  if (sent_once_ || !std::isfinite(voltage_v)) return;
  if (!has_applied_) target_v_ = voltage_v;
  has_applied_ = true;
  applied_v_ = voltage_v;
  if (held() || !has_command_) target_v_ = voltage_v;
}

CommandOutcome CommandLimiter::command(double voltage_v, double now_s) {
  if (!std::isfinite(voltage_v)) return CommandOutcome::kRejectedNonFinite;
  if (held()) return CommandOutcome::kRejectedHeld;
  if (!has_applied_) return CommandOutcome::kRejectedNoBaseline;
  const double clamped = std::clamp(voltage_v, config_.min_voltage_v, config_.max_voltage_v);
  target_v_ = clamped;
  last_command_s_ = now_s;
  has_command_ = true;
  timed_out_ = false;
  return clamped == voltage_v ? CommandOutcome::kAccepted : CommandOutcome::kClamped;
}

std::optional<double> CommandLimiter::step(double now_s) {
  double dt = has_step_time_ ? now_s - last_step_s_ : 0.0;
  if (!(dt > 0)) dt = 0;  // time went backwards (sim time reset) or did not move
  dt = std::min(dt, config_.max_step_dt_s);
  last_step_s_ = now_s;
  has_step_time_ = true;
  if (has_command_ && !timed_out_ && now_s - last_command_s_ > config_.command_timeout_s) {
    timed_out_ = true;
    ++timeouts_;
    target_v_ = applied_v_;  // hold where it is: never fall back to 0 V
  }
  if (!has_applied_ || target_v_ == applied_v_) return std::nullopt;
  const double max_delta = config_.slew_rate_v_per_s * dt;
  const double delta = std::clamp(target_v_ - applied_v_, -max_delta, max_delta);
  const double next = std::clamp(applied_v_ + delta, config_.min_voltage_v, config_.max_voltage_v);
  if (next == applied_v_) return std::nullopt;
  applied_v_ = next;
  sent_once_ = true;
  return next;
}

void CommandLimiter::set_hold(HoldReason reason, bool on) {
  const auto bit = static_cast<std::uint8_t>(reason);
  if (on) {
    holds_ |= bit;
    target_v_ = applied_v_;
  } else {
    holds_ &= static_cast<std::uint8_t>(~bit);
  }
}

void CommandLimiter::rebaseline() {
  has_applied_ = false;
  sent_once_ = false;
  has_command_ = false;
  timed_out_ = false;
}

}  // namespace piezo::can
