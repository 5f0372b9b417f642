// Hold trim (docs/predictor.md): once an axis has had no new intent for a settle time, a slow correction is
// added to the target the model is inverted for, so that the fused estimate (model + encoder,
// estimation/error_filter.h) goes to the intended position. Integral action on (intended − fused), bounded,
// slew-limited; paused while the axis moves, on a stale encoder and while the model falls back; a new intent
// cancels it at once. ROS-free; the AxisCompensator drives it once per sample.
#pragma once

#include <cstddef>
#include <string>

namespace piezo::compensation {

struct HoldTrimOptions {
  bool enabled = true;
  double settle_s = 5.0;            // no new intent for this long before the trim acts
  double time_constant_s = 20.0;    // integral time constant: far below the encoder rate, above the filter's settling
  double max_nm = 0.0;              // bound on |trim| (0 = 2 % of the ideal stroke, set by the compensator)
  double slew_nm_per_s = 1.0;       // largest change of the trim per second
  double stale_after_s = 1.0;       // no valid reading for this long: paused (the trim holds its value)
  // Dead band in fused 1σ: the trim integrates only the part of |intended − fused| beyond this many σ, so an
  // estimate that cannot tell the error from zero does not move the tip (0 = none).
  double deadband_sigma = 1.0;
  void validate() const;            // throws std::invalid_argument naming the field
};

enum class TrimState { kOff, kModelOnly, kMoving, kSettling, kActive, kStale, kFallback };
const char* trim_state_name(TrimState s);  // "off", "model_only", "moving", "settling", "active", "stale", "fallback"

class HoldTrim {
 public:
  HoldTrim(const HoldTrimOptions& o, double dt_s);
  void set_enabled(bool on);
  bool enabled() const { return o_.enabled; }
  void set_max_nm(double max_nm) { o_.max_nm = max_nm; }
  // A new intent (a different target): the trim is cancelled at once and the settle time starts again.
  void on_new_intent();
  // The tracking trim's correction taken over as the axis settles (added to the trim, within its bound), so the
  // sum of the two does not jump.
  void take_over(double trim_nm);
  // One sample. `fusing`: the estimate is informed by readings; `fused_sigma_nm`: its 1σ; `since_reading_samples`:
  // samples since the last valid one; `model_ok`: the prediction and the command are from the model (no fallback).
  void step(double intended_nm, double fused_nm, double fused_sigma_nm, bool fusing, std::size_t since_reading_samples,
            bool model_ok, bool has_intent);
  double trim_nm() const { return trim_nm_; }
  TrimState state() const { return state_; }
  double settled_s() const { return settled_samples_ * dt_s_; }
  const HoldTrimOptions& options() const { return o_; }

 private:
  HoldTrimOptions o_;
  double dt_s_;
  double trim_nm_ = 0.0;
  std::size_t settled_samples_ = 0;
  TrimState state_ = TrimState::kMoving;
};

}  // namespace piezo::compensation
