// Tracking trim (docs/predictor.md, "Tracking trim"): while the axis moves, the feedforward's target is corrected
// by the model's error that the fused estimate knows (estimation/error_filter.h), forecast half a period ahead
// (estimation/forecast.h: the slow error held, the fast error settling). Its aim is the model's
// error, never a position, so it cannot pull the tip towards an old intent (an operator's stream of intents during
// a walk is followed by the feedforward, the trim only removes the model's error); the first intent of a move takes
// the aim at once, then once per period. It acts only on the part of the error beyond deadband_sigma fused σ (on a/b, with
// 250 nm steps, only as far as the crossings have pinned the error), bounded, slew-limited. The compensator inverts
// the model for intended + trim inside the voltage limits. When the axis settles, its value is handed to the hold
// trim (compensation/hold_trim.h) and a new move takes the hold trim's value back, so the sum never jumps. A stuck
// or glitching encoder (the estimator refusing its readings) makes it fall back to the feedforward: the trim slews
// to 0 and its state says why. ROS-free; the AxisCompensator drives it once per sample.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

namespace piezo::compensation {

struct TrackingTrimOptions {
  bool enabled = false;
  double period_s = 1.0;          // the aim is taken from the fused estimate once per period
  double max_nm = 0.0;            // bound on |trim| (0 = 2 % of the ideal stroke, set by the compensator)
  double slew_nm_per_s = 20.0;    // largest change of the trim per second
  double deadband_sigma = 1.0;    // the part of the error within this many fused σ is left alone
  double stale_after_s = 1.0;     // no reading taken for this long: fall back (a stuck encoder)
  double glitch_window_s = 10.0;  // readings refused (outside the gate) in this long …
  std::size_t glitch_count = 3;   // … this many or more: fall back (a glitching encoder)
  void validate() const;          // throws std::invalid_argument naming the parameter
};

enum class TrackingState { kOff, kModelOnly, kIdle, kActive, kHandedOver, kFallback };
// "off", "model_only", "idle" (no intent), "active", "handed_over" (the hold trim has it), "fallback"
const char* tracking_state_name(TrackingState s);

// What the trim is told each sample about the estimator.
struct TrackingInput {
  bool fusing = false;            // the estimate is informed by readings
  double error_forecast_nm = 0;   // the model's error expected half a period ahead (fused − model, forecast)
  double sigma_nm = 0;            // its 1σ
  std::size_t since_reading_samples = 0;
  std::size_t refused_readings = 0;  // the estimator's running count (rejected + stale)
  bool model_ok = true;           // prediction and command from the model (no fallback)
  bool has_intent = false;
  bool holding = false;           // the hold trim has taken over (it is settling or acting)
};

class TrackingTrim {
 public:
  TrackingTrim(const TrackingTrimOptions& o, double dt_s);
  void set_enabled(bool on);
  bool enabled() const { return o_.enabled; }
  void set_max_nm(double max_nm) { o_.max_nm = max_nm; }
  // A new intent: from a hold or idle, the aim is taken at the next sample. `from_nm`: the hold trim's correction,
  // handed back and added to the trim's own, so the target does not jump.
  void on_new_intent(double from_nm);
  void step(const TrackingInput& in);
  // The hold trim takes over: the trim's value is returned and the trim is 0 until the next intent.
  double hand_over();
  double trim_nm() const { return trim_nm_; }
  double aim_nm() const { return aim_nm_; }
  TrackingState state() const { return state_; }
  const std::string& reason() const { return reason_; }  // why it falls back, or is idle/model-only
  std::size_t fallbacks() const { return fallbacks_; }
  const TrackingTrimOptions& options() const { return o_; }

 private:
  void slew_towards(double target);
  bool encoder_bad(const TrackingInput& in);
  TrackingTrimOptions o_;
  double dt_s_;
  double trim_nm_ = 0.0, aim_nm_ = 0.0;
  std::size_t since_aim_ = 0, period_n_ = 1;
  bool aim_due_ = true;
  // the refused readings of the last glitch_window_s, one slot per sample
  std::vector<unsigned char> ring_;
  std::size_t ring_pos_ = 0, refused_in_window_ = 0, last_refused_ = 0;
  bool have_refused_ = false;
  TrackingState state_ = TrackingState::kIdle;
  std::string reason_;
  std::size_t fallbacks_ = 0;
};

}  // namespace piezo::compensation
