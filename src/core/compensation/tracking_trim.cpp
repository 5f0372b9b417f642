#include "piezo_compensation/compensation/tracking_trim.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace piezo::compensation {

void TrackingTrimOptions::validate() const {
  auto need = [](bool ok, const char* what) {
    if (!ok) throw std::invalid_argument(what);
  };
  need(std::isfinite(period_s) && period_s > 0.0, "tracking_trim_period_s must be > 0 [s]");
  need(std::isfinite(max_nm) && max_nm >= 0.0, "tracking_trim_max_nm must be ≥ 0 [nm] (0 = 2 % of the ideal stroke)");
  need(std::isfinite(slew_nm_per_s) && slew_nm_per_s > 0.0, "tracking_trim_slew_nm_per_s must be > 0 [nm/s]");
  need(std::isfinite(deadband_sigma) && deadband_sigma >= 0.0, "tracking_trim_deadband_sigma must be ≥ 0 [fused 1σ]");
  need(std::isfinite(stale_after_s) && stale_after_s > 0.0, "encoder_stale_after_s must be > 0 [s]");
  need(std::isfinite(glitch_window_s) && glitch_window_s > 0.0 && glitch_window_s <= 3600.0,
       "tracking_trim_glitch_window_s must be in (0, 3600] [s]");
  need(glitch_count >= 1, "tracking_trim_glitch_count must be ≥ 1 [readings]");
}

const char* tracking_state_name(TrackingState s) {
  switch (s) {
    case TrackingState::kOff: return "off";
    case TrackingState::kModelOnly: return "model_only";
    case TrackingState::kIdle: return "idle";
    case TrackingState::kActive: return "active";
    case TrackingState::kHandedOver: return "handed_over";
    case TrackingState::kFallback: return "fallback";
  }
  return "?";
}

TrackingTrim::TrackingTrim(const TrackingTrimOptions& o, double dt_s) : o_(o), dt_s_(dt_s) {
  o_.validate();
  if (!(dt_s > 0.0) || !std::isfinite(dt_s)) throw std::invalid_argument("TrackingTrim: dt_s must be > 0");
  period_n_ = std::max<std::size_t>(1, static_cast<std::size_t>(std::lround(o_.period_s / dt_s)));
  ring_.assign(std::max<std::size_t>(1, static_cast<std::size_t>(std::lround(o_.glitch_window_s / dt_s))), 0);
  if (!o_.enabled) state_ = TrackingState::kOff;
}

void TrackingTrim::set_enabled(bool on) {
  o_.enabled = on;
  if (!on) trim_nm_ = aim_nm_ = 0.0, state_ = TrackingState::kOff;
}

void TrackingTrim::on_new_intent(double from_nm) {
  if (!o_.enabled) return;
  const double bound = o_.max_nm > 0.0 ? o_.max_nm : std::numeric_limits<double>::infinity();
  if (std::isfinite(from_nm)) trim_nm_ = std::clamp(trim_nm_ + from_nm, -bound, bound);
  if (state_ != TrackingState::kActive) aim_due_ = true;  // a move starts: aim at once; within a move, at the period
}

double TrackingTrim::hand_over() {
  const double v = trim_nm_;
  trim_nm_ = aim_nm_ = 0.0;
  if (o_.enabled) state_ = TrackingState::kHandedOver;
  return v;
}

void TrackingTrim::slew_towards(double target) {
  const double bound = o_.max_nm > 0.0 ? o_.max_nm : std::numeric_limits<double>::infinity();
  target = std::clamp(target, -bound, bound);
  const double step = o_.slew_nm_per_s * dt_s_;
  trim_nm_ = std::clamp(trim_nm_ + std::clamp(target - trim_nm_, -step, step), -bound, bound);
}

// Stuck: no reading taken for stale_after_s (the estimator refuses a level the model moved away from). Glitching:
// glitch_count or more readings refused within glitch_window_s.
bool TrackingTrim::encoder_bad(const TrackingInput& in) {
  const std::size_t fresh = have_refused_ && in.refused_readings >= last_refused_ ? in.refused_readings - last_refused_ : 0;
  last_refused_ = in.refused_readings;
  have_refused_ = true;
  refused_in_window_ -= ring_[ring_pos_];
  ring_[ring_pos_] = static_cast<unsigned char>(std::min<std::size_t>(fresh, 255));
  refused_in_window_ += ring_[ring_pos_];
  ring_pos_ = (ring_pos_ + 1) % ring_.size();
  if (static_cast<double>(in.since_reading_samples) * dt_s_ > o_.stale_after_s) {
    reason_ = "encoder stale: no reading taken for " + std::to_string(in.since_reading_samples) +
              " samples (stuck or lost); feedforward only";
    return true;
  }
  if (refused_in_window_ >= o_.glitch_count) {
    reason_ = "encoder glitching: " + std::to_string(refused_in_window_) + " readings refused by the estimator in the "
              "last " + std::to_string(static_cast<int>(std::lround(o_.glitch_window_s))) + " s; feedforward only";
    return true;
  }
  return false;
}

void TrackingTrim::step(const TrackingInput& in) {
  const bool bad = encoder_bad(in);  // counted every sample, so the window is current when the trim acts
  if (!o_.enabled) {
    state_ = TrackingState::kOff;
    reason_.clear();
    return;
  }
  if (!in.fusing) {
    state_ = TrackingState::kModelOnly;
    reason_ = "the estimator does not fuse readings on this axis";
    slew_towards(0.0);
    return;
  }
  if (in.holding) {
    state_ = TrackingState::kHandedOver;
    reason_.clear();
    return;
  }
  if (!in.has_intent) {
    state_ = TrackingState::kIdle;
    reason_ = "no intent";
    return;
  }
  if (bad || !in.model_ok || !std::isfinite(in.error_forecast_nm)) {
    if (state_ != TrackingState::kFallback) ++fallbacks_;
    state_ = TrackingState::kFallback;
    if (!bad) reason_ = !in.model_ok ? "the model falls back; feedforward only" : "no finite error estimate";
    aim_nm_ = 0.0;
    aim_due_ = true;  // a fresh aim once the encoder is good again
    slew_towards(0.0);
    return;
  }
  state_ = TrackingState::kActive;
  reason_.clear();
  if (aim_due_ || ++since_aim_ >= period_n_) {
    // the model's error beyond the dead band; the target the model is inverted for moves the other way
    const double band = std::isfinite(in.sigma_nm) ? o_.deadband_sigma * in.sigma_nm : 0.0;
    const double e = in.error_forecast_nm;
    aim_nm_ = -std::copysign(std::max(0.0, std::abs(e) - band), e);
    since_aim_ = 0;
    aim_due_ = false;
  }
  slew_towards(aim_nm_);
}

}  // namespace piezo::compensation
