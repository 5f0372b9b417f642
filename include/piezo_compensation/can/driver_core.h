// The ROS-free heart of the mm3e_driver node: owns the transport, decodes what the controller sends, runs the
// three command limiters and writes set points. A receive thread handles the bus (reconnect with back-off,
// bus-off, silence); commands and ticks come from the caller's threads. All public methods are thread-safe.
#pragma once

#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "piezo_compensation/can/codec.h"
#include "piezo_compensation/can/command_limiter.h"
#include "piezo_compensation/can/transport.h"

namespace piezo::can {

struct DriverConfig {
  ProtocolConfig protocol;
  LimiterConfig limits;
  double encoder_timeout_s = 0.5;     // [s, wall] no encoder frame for this long → reported as silent
  double silence_reconnect_s = 2.0;   // [s, wall] no frame at all for this long → reopen the transport
  double reconnect_min_s = 0.1;       // [s] first reconnect delay, doubled per failure...
  double reconnect_max_s = 5.0;       // [s] ...up to this
  int receive_poll_ms = 20;           // [ms] receive thread wake-up period
  // Synchronous mode (the node sets it with ~sync_mode): set points wait for the next sync() and go out with the
  // SYNC in one Transport::send_batch (UDP: one datagram per sample, not one per frame). The controller takes them
  // in bus order and uses them only at that SYNC's sample, so it sees the same; the limiter counts a set point as
  // written when its batch is. Between two SYNCs time (the bus time) stands still, so an axis proposes at most one
  // set point: a batch is at most one frame per axis and the SYNC.
  bool hold_until_sync = false;
};
void validate(const DriverConfig& config);  // std::invalid_argument naming the field

enum class BusState { kDisconnected, kConnected, kActive, kErrorPassive, kBusOff };
const char* to_string(BusState state);

struct AxisStatus {
  std::uint64_t voltage_frames = 0, encoder_frames = 0;
  std::uint64_t encoder_dropped = 0, encoder_out_of_order = 0;
  std::uint64_t voltage_dropped = 0, voltage_out_of_order = 0;
  std::uint64_t commands = 0, clamped = 0, rejected_non_finite = 0, rejected_held = 0, rejected_no_baseline = 0,
                rejected_no_link = 0, rejected_future_stamp = 0;
  std::uint64_t frames_sent = 0, frames_refused = 0, timeouts = 0, report_mismatches = 0, device_faults = 0;
  double applied_v = 0.0;       // last set point sent
  double target_v = 0.0;        // where the slew ramp is heading
  double reported_v = 0.0;      // last voltage the device reported
  double position_m = 0.0;      // last encoder position
  double encoder_age_s = -1.0;  // [s, wall] since the last encoder frame; -1 = none yet
  bool has_baseline = false, timed_out = false, halted = false, multiple_commanders = false;
  bool encoder_valid = true, amplifier_fault = false;
  bool device_fault = false;  // held: the device did not follow (restart, not operational, reports away)
  bool paused = false;        // the last report matched no written value: the ramp waits for the next one
  std::string fault;          // "axis a: controller restarted ...: reported 0.000 V, commanded 42.000 V"
};

struct BusStatus {
  BusState state = BusState::kDisconnected;
  std::string transport;         // describe() of the transport
  std::string last_error;        // last transport or bus error, "" if none
  std::string last_error_frame;  // candump text of the last error frame
  std::uint64_t error_frames = 0, bus_off_events = 0, malformed_frames = 0, unknown_frames = 0;
  std::uint64_t send_failures = 0, connects = 0, connect_failures = 0;
  std::uint64_t syncs_sent = 0;  // synchronous mode
  bool heartbeat_seen = false;
  DeviceState device_state = DeviceState::kBoot;
  std::uint8_t device_fault_flags = 0;
  double heartbeat_age_s = -1.0;  // [s, wall]
  double next_reconnect_in_s = 0.0;
};

struct DriverCallbacks {
  // Called on the receive thread, outside the driver's lock. sequence is unwrapped to 32 bit.
  std::function<void(const VoltageReport&, std::uint32_t sequence, double receive_time_s)> on_voltage;
  std::function<void(const EncoderReport&, std::uint32_t sequence, double receive_time_s)> on_encoder;
  // Bus events worth a log line (connect, disconnect, bus-off, malformed frame); error=true for problems.
  std::function<void(const std::string& text, bool error)> on_event;
};

class DriverCore {
 public:
  using TransportFactory = std::function<std::unique_ptr<Transport>()>;

  DriverCore(const DriverConfig& config, TransportFactory factory, DriverCallbacks callbacks);
  ~DriverCore();
  DriverCore(const DriverCore&) = delete;
  DriverCore& operator=(const DriverCore&) = delete;

  void start();  // starts the receive thread (which opens the transport, retrying with back-off)
  void stop();

  // A command for one axis at time now_s (caller's clock: ROS time). command_time_s is when the commander
  // issued it (its header stamp; NaN = now_s): the watchdog counts from min(command_time_s, now_s), so a stale
  // command holds, and one stamped more than max_stamp_ahead_s ahead is refused. Writes a frame at once when
  // the slew limit allows a change.
  CommandOutcome command(int axis, double voltage_v, double now_s, double command_time_s = std::nan(""));
  // Advances slew ramps and watchdogs of all axes (call at the output rate).
  void tick(double now_s);
  // Synchronous mode: asks the controller for its next sample now (a SYNC frame). Call after the set points
  // of that sample have been written (command()/tick()): the bus keeps the order. False when the link is down.
  // With hold_until_sync the set points held since the last SYNC go out with it, in the order they were written.
  bool sync();

  void halt();                 // hold every axis where it is and refuse commands until recover()
  void recover();              // clear halt and device faults, reopen the transport now, reset the back-off
  void set_multiple_commanders(int axis, bool on);

  AxisStatus axis_status(int axis) const;
  BusStatus bus_status() const;
  const Codec& codec() const { return codec_; }

  // The receive loop's body, exposed so tests can drive it without the thread.
  void poll_once(int timeout_ms);

 private:
  using Clock = std::chrono::steady_clock;
  struct Axis;
  struct Pending;
  struct Held;
  void send_locked(int axis, double voltage_v, double now_s, std::vector<Pending>& events);
  void written_locked(int axis, double voltage_v, double now_s);
  void trip_locked(int axis, const std::string& why, std::vector<Pending>& events);
  void refused_locked(Axis& a);
  void close_locked(const std::string& reason, BusState state, std::vector<Pending>& events);
  void flush(std::vector<Pending>& events);
  // poll_once's parts, under the lock: an open attempt when due (true: open); one received frame (false: the bus
  // went off, stop reading this batch); a voltage report.
  bool connect_locked(std::vector<Pending>& events);
  bool frame_locked(const ReceivedFrame& rf, std::vector<Pending>& events);
  void voltage_report_locked(const VoltageReport& v, double receive_time_s, std::vector<Pending>& events);
  double since(Clock::time_point t) const;

  DriverConfig config_;
  Codec codec_;
  TransportFactory factory_;
  DriverCallbacks callbacks_;

  mutable std::mutex mutex_;
  std::unique_ptr<Transport> transport_;
  std::array<std::unique_ptr<Axis>, kAxisCount> axes_;
  BusStatus bus_;
  bool halted_ = false;
  std::uint32_t command_counter_ = 0;
  std::uint8_t sync_counter_ = 0;
  std::vector<Held> held_;  // hold_until_sync: set points written since the last SYNC, in order
  std::vector<can_frame> batch_;  // sync(): the held frames and the SYNC, as sent
  double last_now_s_ = 0.0;  // latest caller time seen (command/tick): the time reports are checked at
  Clock::time_point last_rx_{}, last_heartbeat_{}, next_attempt_{};
  double backoff_s_ = 0.0;
  bool ever_connected_ = false;
  std::atomic<bool> recover_requested_{false};
  std::atomic<bool> running_{false};
  std::thread thread_;
};

}  // namespace piezo::can
