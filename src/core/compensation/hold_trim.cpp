#include "piezo_compensation/compensation/hold_trim.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace piezo::compensation {

void HoldTrimOptions::validate() const {
  auto need = [](bool ok, const char* what) {
    if (!ok) throw std::invalid_argument(what);
  };
  need(std::isfinite(settle_s) && settle_s >= 0.0, "hold_trim_settle_s must be ≥ 0 [s]");
  need(std::isfinite(time_constant_s) && time_constant_s > 0.0, "hold_trim_time_constant_s must be > 0 [s]");
  need(std::isfinite(max_nm) && max_nm >= 0.0, "hold_trim_max_nm must be ≥ 0 [nm] (0 = 2 % of the ideal stroke)");
  need(std::isfinite(slew_nm_per_s) && slew_nm_per_s > 0.0, "hold_trim_slew_nm_per_s must be > 0 [nm/s]");
  need(std::isfinite(stale_after_s) && stale_after_s > 0.0, "encoder_stale_after_s must be > 0 [s]");
  need(std::isfinite(deadband_sigma) && deadband_sigma >= 0.0, "hold_trim_deadband_sigma must be ≥ 0 [fused 1σ]");
}

const char* trim_state_name(TrimState s) {
  switch (s) {
    case TrimState::kOff: return "off";
    case TrimState::kModelOnly: return "model_only";
    case TrimState::kMoving: return "moving";
    case TrimState::kSettling: return "settling";
    case TrimState::kActive: return "active";
    case TrimState::kStale: return "stale";
    case TrimState::kFallback: return "fallback";
  }
  return "?";
}

HoldTrim::HoldTrim(const HoldTrimOptions& o, double dt_s) : o_(o), dt_s_(dt_s) {
  o_.validate();
  if (!(dt_s > 0.0)) throw std::invalid_argument("HoldTrim: dt_s must be > 0");
}

void HoldTrim::set_enabled(bool on) {
  o_.enabled = on;
  if (!on) trim_nm_ = 0.0;
}

void HoldTrim::on_new_intent() {
  trim_nm_ = 0.0;
  settled_samples_ = 0;
  state_ = TrimState::kMoving;
}

void HoldTrim::take_over(double trim_nm) {
  if (!o_.enabled || !std::isfinite(trim_nm)) return;
  const double bound = o_.max_nm > 0.0 ? o_.max_nm : std::numeric_limits<double>::infinity();
  trim_nm_ = std::clamp(trim_nm_ + trim_nm, -bound, bound);
}

void HoldTrim::step(double intended_nm, double fused_nm, double fused_sigma_nm, bool fusing,
                    std::size_t since_reading_samples, bool model_ok, bool has_intent) {
  ++settled_samples_;
  if (!o_.enabled) {
    state_ = TrimState::kOff;
    return;
  }
  if (!fusing) {
    state_ = TrimState::kModelOnly;
    trim_nm_ = 0.0;
    return;
  }
  if (!has_intent || settled_samples_ * dt_s_ < o_.settle_s) {
    state_ = settled_samples_ <= 1 ? TrimState::kMoving : TrimState::kSettling;
    return;
  }
  if (!model_ok) {
    state_ = TrimState::kFallback;
    return;
  }
  if (since_reading_samples * dt_s_ > o_.stale_after_s) {
    state_ = TrimState::kStale;  // the estimate only predicts now: hold the trim, do not integrate
    return;
  }
  state_ = TrimState::kActive;
  if (!std::isfinite(fused_nm)) return;
  const double e = intended_nm - fused_nm;
  const double band = std::isfinite(fused_sigma_nm) ? o_.deadband_sigma * fused_sigma_nm : 0.0;
  const double beyond = std::copysign(std::max(0.0, std::abs(e) - band), e);
  const double rate = std::clamp(beyond / o_.time_constant_s, -o_.slew_nm_per_s, o_.slew_nm_per_s);
  const double bound = o_.max_nm > 0.0 ? o_.max_nm : std::numeric_limits<double>::infinity();
  trim_nm_ = std::clamp(trim_nm_ + rate * dt_s_, -bound, bound);
}

}  // namespace piezo::compensation
