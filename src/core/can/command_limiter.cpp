#include "piezo_compensation/can/command_limiter.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>

namespace piezo::can {

void validate(const LimiterConfig& c) {
  auto finite = [](double v) { return std::isfinite(v); };
  auto in = [](double v, double lo, double hi) { return std::isfinite(v) && v > lo && v <= hi; };
  if (!finite(c.min_voltage_v) || !finite(c.max_voltage_v) || c.min_voltage_v >= c.max_voltage_v)
    throw std::invalid_argument("min_voltage_v must be finite and below max_voltage_v");
  if (c.min_voltage_v < -kVoltageCeilingV || c.max_voltage_v > kVoltageCeilingV)
    throw std::invalid_argument("min_voltage_v/max_voltage_v must be within ±" +
                                std::to_string(static_cast<int>(kVoltageCeilingV)) + " V (compile-time ceiling)");
  if (!in(c.slew_rate_v_per_s, 0.0, kSlewRateCeilingVPerS))
    throw std::invalid_argument("slew_rate_v_per_s must be in (0, " +
                                std::to_string(static_cast<int>(kSlewRateCeilingVPerS)) + "] V/s");
  if (!finite(c.command_timeout_s) || c.command_timeout_s <= 0)
    throw std::invalid_argument("command_timeout_s must be a finite value > 0");
  if (!in(c.max_step_dt_s, 0.0, kStepDtCeilingS)) throw std::invalid_argument("max_step_dt_s must be in (0, 1] s");
  const double step_ceiling = c.lockstep ? 2 * kVoltageCeilingV : kFrameStepCeilingV;
  if (!in(c.max_frame_step_v, 0.0, step_ceiling))
    throw std::invalid_argument("max_frame_step_v must be in (0, " +
                                std::to_string(static_cast<int>(kFrameStepCeilingV)) + "] V");
  if (!in(c.max_unconfirmed_v, 0.0, 2 * step_ceiling) || c.max_unconfirmed_v < c.max_frame_step_v)
    throw std::invalid_argument("max_unconfirmed_v must be in [max_frame_step_v, " +
                                std::to_string(static_cast<int>(2 * kFrameStepCeilingV)) + "] V");
  if (!in(c.max_stamp_ahead_s, 0.0, 60.0)) throw std::invalid_argument("max_stamp_ahead_s must be in (0, 60] s");
  if (!in(c.report_tolerance_v, 0.0, 10.0)) throw std::invalid_argument("report_tolerance_v must be in (0, 10] V");
  if (!in(c.report_lag_s, 0.0, 10.0)) throw std::invalid_argument("report_lag_s must be in (0, 10] s");
  if (c.report_mismatch_count < 1 || c.report_mismatch_count > 100)
    throw std::invalid_argument("report_mismatch_count must be 1..100");
}

const char* to_string(CommandOutcome outcome) {
  switch (outcome) {
    case CommandOutcome::kAccepted: return "accepted";
    case CommandOutcome::kClamped: return "clamped";
    case CommandOutcome::kRejectedNonFinite: return "rejected: not finite";
    case CommandOutcome::kRejectedNoBaseline: return "rejected: no voltage report from the device yet";
    case CommandOutcome::kRejectedHeld: return "rejected: axis is held";
    case CommandOutcome::kRejectedFutureStamp: return "rejected: stamped in the future (clocks disagree?)";
  }
  return "unknown";
}

CommandLimiter::CommandLimiter(const LimiterConfig& config) : config_(config) { validate(config_); }

void CommandLimiter::take_baseline(double voltage_v, double now_s) {
  if (!has_applied_ || held() || !has_command_ || timed_out_) target_v_ = voltage_v;
  has_applied_ = true;
  applied_v_ = voltage_v;
  confirmed_v_ = voltage_v;
  mismatches_ = 0;
  written_.clear();
  written_.emplace_back(now_s, voltage_v);
}

void CommandLimiter::prune(double now_s) {
  // The oldest entry stays while it is the last one written before the window: the device may still show it.
  while (written_.size() >= 2 && written_[1].first < now_s - config_.report_lag_s) written_.pop_front();
}

bool CommandLimiter::matches_written(double voltage_v) const {
  for (const auto& w : written_)
    if (std::abs(w.second - voltage_v) <= config_.report_tolerance_v) return true;
  return false;
}

void CommandLimiter::on_reported_voltage(double voltage_v, double now_s) {
  if (!std::isfinite(voltage_v)) return;
  awaiting_report_ = false;
  if (!sent_once_ || held()) {
    take_baseline(voltage_v, now_s);
    return;
  }
  prune(now_s);
  if (matches_written(voltage_v)) {
    mismatches_ = 0;
    confirmed_v_ = voltage_v;
    return;
  }
  ++mismatch_total_;
  if (++mismatches_ >= config_.report_mismatch_count) {
    char buf[160];
    std::snprintf(buf, sizeof buf, "device reports %.3f V, driver commanded %.3f V (%d reports in a row)", voltage_v,
                  applied_v_, mismatches_);
    trip(buf);
    take_baseline(voltage_v, now_s);
  }
}

CommandOutcome CommandLimiter::command(double voltage_v, double now_s, double command_time_s) {
  if (!std::isfinite(voltage_v)) return CommandOutcome::kRejectedNonFinite;
  if (held()) return CommandOutcome::kRejectedHeld;
  if (!has_applied_) return CommandOutcome::kRejectedNoBaseline;
  double stamp = now_s;
  if (std::isfinite(command_time_s)) {
    if (command_time_s > now_s + config_.max_stamp_ahead_s) return CommandOutcome::kRejectedFutureStamp;
    stamp = std::min(command_time_s, now_s);
  }
  const double clamped = std::clamp(voltage_v, config_.min_voltage_v, config_.max_voltage_v);
  target_v_ = clamped;
  last_command_s_ = stamp;
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
  if (!has_applied_ || held() || paused() || target_v_ == applied_v_) return std::nullopt;  // paused: awaiting a report too
  const double max_delta = std::min(config_.slew_rate_v_per_s * dt, config_.max_frame_step_v);
  // The target is always inside the limits, so from a baseline outside them this ramps in.
  double next = applied_v_ + std::clamp(target_v_ - applied_v_, -max_delta, max_delta);
  // Not further ahead of what the device confirmed; this only shortens the step, never reverses it.
  if (next > applied_v_) next = std::min(next, confirmed_v_ + config_.max_unconfirmed_v);
  else next = std::max(next, confirmed_v_ - config_.max_unconfirmed_v);
  if ((target_v_ > applied_v_) != (next > applied_v_) || next == applied_v_ || !sendable(next)) return std::nullopt;
  return next;
}

bool CommandLimiter::sendable(double v) const {
  if (!std::isfinite(v) || !has_applied_) return false;
  if (std::abs(v - applied_v_) > config_.max_frame_step_v * (1 + 1e-9)) return false;
  if (v >= config_.min_voltage_v && v <= config_.max_voltage_v) return true;
  // ramp-in: strictly between an applied voltage outside the limits and the limits
  if (v > config_.max_voltage_v) return v < applied_v_;
  return v > applied_v_;
}

void CommandLimiter::sent(double voltage_v, double now_s) {
  if (!std::isfinite(voltage_v)) return;
  applied_v_ = voltage_v;
  sent_once_ = true;
  written_.emplace_back(now_s, voltage_v);
  prune(now_s);
}

void CommandLimiter::refused() {
  if (has_applied_) awaiting_report_ = true;
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

void CommandLimiter::trip(const std::string& why) {
  if (!held_for(HoldReason::kDeviceFault)) fault_ = name_ + ": " + why + "; holding until ~recover";
  set_hold(HoldReason::kDeviceFault, true);
  has_command_ = false;
  timed_out_ = false;
}

void CommandLimiter::clear_fault() {
  set_hold(HoldReason::kDeviceFault, false);
  fault_.clear();
  mismatches_ = 0;
}

void CommandLimiter::rebaseline() {
  has_applied_ = false;
  sent_once_ = false;
  awaiting_report_ = false;
  has_command_ = false;
  timed_out_ = false;
  mismatches_ = 0;
  written_.clear();
}

}  // namespace piezo::can
