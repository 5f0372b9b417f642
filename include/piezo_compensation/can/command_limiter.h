// The safety rules between a voltage command and the bus, for one axis: clamp to limits, slew limit, a hard
// cap per frame, NaN/Inf rejection, command watchdog that HOLDS the last applied voltage (never drops to 0 V),
// holds for halt, a second commander or a device that does not follow. Pure: time comes in as an argument (ROS
// time in the node, so sim time works).
//
// What the device really has is the reference: the applied voltage is the last value whose frame was written
// (step() only proposes, sent() accepts), and every fresh voltage report is checked against the values written
// within report_lag_s. A report that matches none of them pauses the ramp; report_mismatch_count in a row trip
// a device fault that holds the axis until clear_fault(), and the reports become the baseline again. The ramp
// never runs more than max_unconfirmed_v ahead of the last report that matched (or the baseline). After a
// refused frame nothing is proposed until the device reports again.
#pragma once

#include <cstdint>
#include <deque>
#include <optional>
#include <string>
#include <utility>

namespace piezo::can {

// Compile-time ceilings of the configurable limits (docs/driver.md): no parameter file can go beyond them.
constexpr double kVoltageCeilingV = 150.0;         // |min_voltage_v|, |max_voltage_v|
constexpr double kSlewRateCeilingVPerS = 2000.0;   // slew_rate_v_per_s
constexpr double kFrameStepCeilingV = 20.0;        // max_frame_step_v
constexpr double kStepDtCeilingS = 1.0;            // max_step_dt_s

struct LimiterConfig {
  double min_voltage_v = -80.0;
  double max_voltage_v = 80.0;
  double slew_rate_v_per_s = 200.0;   // largest rate of change of the applied voltage
  double command_timeout_s = 0.5;     // no command for this long → hold the applied voltage
  double max_step_dt_s = 0.1;         // longest interval one output step may cover (bounds a single jump)
  double max_frame_step_v = 5.0;      // [V] hard cap on the change one frame may carry, whatever the clock did
  // [V] how far the set point may run ahead of the device's last report that matched. Bounds what a device
  // that silently ignores set points for a while (and then takes the next) can see: 2 × this + tolerance.
  double max_unconfirmed_v = 10.0;
  double max_stamp_ahead_s = 0.5;     // [s] a command stamped further ahead of now is refused
  double report_tolerance_v = 0.5;    // [V] a report this far from every recently written value does not match
  double report_lag_s = 0.5;          // [s] written values a report may still show (transport + sample delay,
                                      // a loaded host: a shorter window made reports late by 0.1 s trip the axis)
  int report_mismatch_count = 3;      // reports in a row that do not match → device fault, axis held
  // Synchronous mode on the simulated device (refused on SocketCAN): time is samples, one frame per sample, no
  // stall can happen; max_frame_step_v and max_unconfirmed_v may then exceed their ceilings (the node sets them
  // to the slew rate × one sample period).
  bool lockstep = false;
};

// Throws std::invalid_argument naming the field.
void validate(const LimiterConfig& config);

enum class CommandOutcome {
  kAccepted,
  kClamped,        // accepted, outside the limits: clamped
  kRejectedNonFinite,
  kRejectedNoBaseline,  // the device has not reported its voltage yet: nothing to slew from
  kRejectedHeld,   // halted, more than one commander, or a device fault
  kRejectedFutureStamp,  // stamped more than max_stamp_ahead_s after now (another clock)
};
const char* to_string(CommandOutcome outcome);

enum class HoldReason : std::uint8_t { kNone = 0, kHalted = 1, kMultipleCommanders = 2, kDeviceFault = 4 };

class CommandLimiter {
 public:
  explicit CommandLimiter(const LimiterConfig& config);

  // A fresh voltage report (newer than every report before it) at caller time now_s. Before the first frame,
  // and while held, it is the baseline; afterwards it is checked against what was written.
  void on_reported_voltage(double voltage_v, double now_s);

  // command_time_s: when the commander issued it (NaN = now_s); taken as min(command_time_s, now_s).
  CommandOutcome command(double voltage_v, double now_s, double command_time_s = kNoStamp);

  // Advances the slew ramp and the watchdog. Returns the voltage to send now, or nothing when the applied
  // voltage does not change. The value is a proposal: it becomes the applied voltage only through sent().
  std::optional<double> step(double now_s);
  // The frame carrying voltage_v (as encoded) was written at now_s.
  void sent(double voltage_v, double now_s);
  // The transport refused a frame (queue full, or ECONNREFUSED: nobody listening, so a frame written just before
  // it may be lost too). No proposal until the next fresh report, which is checked like any other: at most one
  // lost frame per refusal, and a report that matches nothing written pauses and then trips as below.
  void refused();
  // Whether a frame with this value may go on the bus: within [min, max], or a ramp-in step from a baseline
  // outside them towards the inside; never more than max_frame_step_v from the applied voltage.
  bool sendable(double voltage_v) const;

  void set_hold(HoldReason reason, bool on);  // halt / multiple commanders: stop where it is, refuse commands
  // The device does not follow (restart, not operational, reports away from the commanded value): hold the
  // axis, take the next reports as the baseline, keep `why` for diagnostics until clear_fault().
  void trip(const std::string& why);
  void set_name(const std::string& name) { name_ = name; }  // "axis a": prefix of the fault text
  void clear_fault();
  bool held() const { return holds_ != 0; }
  bool held_for(HoldReason reason) const { return holds_ & static_cast<std::uint8_t>(reason); }
  const std::string& fault() const { return fault_; }
  // After a reconnect the device may have moved on its own: re-baseline from its next report.
  void rebaseline();

  bool has_baseline() const { return has_applied_; }
  double applied_v() const { return applied_v_; }
  double target_v() const { return target_v_; }
  bool timed_out() const { return timed_out_; }
  bool paused() const { return mismatches_ > 0 || awaiting_report_; }
  bool awaiting_report() const { return awaiting_report_; }
  std::uint64_t timeouts() const { return timeouts_; }
  std::uint64_t report_mismatches() const { return mismatch_total_; }
  const LimiterConfig& config() const { return config_; }

  static constexpr double kNoStamp = __builtin_nan("");

 private:
  bool matches_written(double voltage_v) const;
  void prune(double now_s);
  void take_baseline(double voltage_v, double now_s);

  LimiterConfig config_;
  bool has_applied_ = false;
  bool sent_once_ = false;   // a frame was written since the last baseline
  bool awaiting_report_ = false;  // a frame was refused: the next report is the baseline
  double applied_v_ = 0.0;   // last voltage written (or reported, before the first frame)
  double confirmed_v_ = 0.0; // last report that matched (or the baseline)
  double target_v_ = 0.0;
  double last_step_s_ = 0.0;
  bool has_step_time_ = false;
  double last_command_s_ = 0.0;
  bool has_command_ = false;
  bool timed_out_ = false;
  std::uint64_t timeouts_ = 0;
  std::uint8_t holds_ = 0;
  std::string fault_;
  std::string name_ = "axis";
  int mismatches_ = 0;
  std::uint64_t mismatch_total_ = 0;
  std::deque<std::pair<double, double>> written_;  // (time, value) the device may still show
};

}  // namespace piezo::can
