#include "piezo_compensation/can/driver_core.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>

namespace piezo::can {

void validate(const DriverConfig& c) {
  validate(c.protocol);
  validate(c.limits);
  auto positive = [](double v) { return std::isfinite(v) && v > 0; };
  if (!positive(c.encoder_timeout_s)) throw std::invalid_argument("encoder_timeout_s must be a finite value > 0");
  if (!positive(c.silence_reconnect_s)) throw std::invalid_argument("silence_reconnect_s must be a finite value > 0");
  if (!positive(c.reconnect_min_s)) throw std::invalid_argument("reconnect_min_s must be a finite value > 0");
  if (!positive(c.reconnect_max_s) || c.reconnect_max_s < c.reconnect_min_s)
    throw std::invalid_argument("reconnect_max_s must be finite and >= reconnect_min_s");
  if (c.receive_poll_ms < 1 || c.receive_poll_ms > 1000) throw std::invalid_argument("receive_poll_ms must be 1..1000");
}

const char* to_string(BusState state) {
  switch (state) {
    case BusState::kDisconnected: return "disconnected";
    case BusState::kConnected: return "connected, no frame from the device yet";
    case BusState::kActive: return "active";
    case BusState::kErrorPassive: return "error passive";
    case BusState::kBusOff: return "bus-off";
  }
  return "unknown";
}

struct DriverCore::Axis {
  explicit Axis(const LimiterConfig& c) : limiter(c) {}
  CommandLimiter limiter;
  SequenceTracker voltage_seq, encoder_seq;
  AxisStatus status;
  Clock::time_point last_encoder{};
  bool has_encoder = false;
};

// A set point waiting for the next SYNC (hold_until_sync): its frame as encoded, for the limiter when it is written.
struct DriverCore::Held {
  int axis;
  can_frame frame;
  double voltage_v;  // encoded
  double now_s;
  std::uint32_t counter;
};

// Callbacks are collected under the lock and run after it is released.
struct DriverCore::Pending {
  enum Kind { kVoltage, kEncoder, kEvent } kind;
  VoltageReport voltage;
  EncoderReport encoder;
  std::uint32_t sequence = 0;
  double time_s = 0;
  std::string text;
  bool error = false;
};

DriverCore::DriverCore(const DriverConfig& config, TransportFactory factory, DriverCallbacks callbacks)
    : config_(config), codec_(config.protocol), factory_(std::move(factory)), callbacks_(std::move(callbacks)) {
  validate(config_);
  for (int i = 0; i < kAxisCount; ++i) {
    axes_[i] = std::make_unique<Axis>(config_.limits);
    axes_[i]->limiter.set_name(std::string("axis ") + kAxisNames[i]);
  }
  backoff_s_ = config_.reconnect_min_s;
  transport_ = factory_();
  if (!transport_) throw std::invalid_argument("transport factory returned nothing");
  bus_.transport = transport_->describe();
  next_attempt_ = Clock::now();
}

DriverCore::~DriverCore() { stop(); }

void DriverCore::start() {
  if (running_.exchange(true)) return;
  thread_ = std::thread([this] {
    while (running_) poll_once(config_.receive_poll_ms);
  });
}

void DriverCore::stop() {
  running_ = false;
  if (thread_.joinable()) thread_.join();
  std::lock_guard<std::mutex> lock(mutex_);
  if (transport_) transport_->close();
}

double DriverCore::since(Clock::time_point t) const {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

void DriverCore::flush(std::vector<Pending>& events) {
  for (auto& e : events) {
    switch (e.kind) {
      case Pending::kVoltage:
        if (callbacks_.on_voltage) callbacks_.on_voltage(e.voltage, e.sequence, e.time_s);
        break;
      case Pending::kEncoder:
        if (callbacks_.on_encoder) callbacks_.on_encoder(e.encoder, e.sequence, e.time_s);
        break;
      case Pending::kEvent:
        if (callbacks_.on_event) callbacks_.on_event(e.text, e.error);
        break;
    }
  }
  events.clear();
}

void DriverCore::close_locked(const std::string& reason, BusState state, std::vector<Pending>& events) {
  transport_->close();
  held_.clear();  // never reached the bus; every axis takes a new baseline below
  bus_.state = state;
  bus_.last_error = reason;
  next_attempt_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(backoff_s_));
  Pending p{Pending::kEvent, {}, {}, 0, 0, reason + "; reconnecting in " + std::to_string(backoff_s_).substr(0, 5) + " s", true};
  events.push_back(std::move(p));
  backoff_s_ = std::min(backoff_s_ * 2, config_.reconnect_max_s);
  // The device may move on its own meanwhile: take its next report as the baseline again.
  for (auto& a : axes_) {
    a->limiter.rebaseline();
    a->voltage_seq.reset();
    a->encoder_seq.reset();
  }
}

void DriverCore::send_locked(int axis, double voltage_v, double now_s, std::vector<Pending>& events) {
  Axis& a = *axes_[axis];
  // Last line of defence: the limiter never proposes such a value, and the bus never sees one.
  if (!a.limiter.sendable(voltage_v)) return;
  const double lo = std::min(config_.limits.min_voltage_v, voltage_v);
  const double hi = std::max(config_.limits.max_voltage_v, voltage_v);
  CommandFrame m;
  m.axis = axis;
  m.voltage_v = voltage_v;
  m.counter = command_counter_;
  can_frame f;
  double encoded_v;
  try {
    f = codec_.encode_command(m, lo, hi);
    encoded_v = std::get<CommandFrame>(codec_.decode(f).message_value).voltage_v;
  } catch (const std::exception& e) {
    trip_locked(axis, std::string("cannot encode set point: ") + e.what(), events);
    return;
  }
  if (!a.limiter.sendable(encoded_v)) return;
  if (config_.hold_until_sync) {  // written with the next SYNC (sync()); the counter is this frame's already
    held_.push_back({axis, f, encoded_v, now_s, command_counter_});
    ++command_counter_;
    return;
  }
  try {
    if (transport_->send(f)) {
      ++command_counter_;
      written_locked(axis, encoded_v, now_s);
    } else {
      refused_locked(a);
    }
  } catch (const TransportError& e) {
    refused_locked(a);
    // The receive thread owns reconnection; it sees the same failure on its next poll.
    bus_.last_error = e.what();
  }
}

void DriverCore::written_locked(int axis, double voltage_v, double now_s) {
  Axis& a = *axes_[axis];
  ++a.status.frames_sent;
  a.limiter.sent(voltage_v, now_s);  // only a written frame moves the applied voltage
}

void DriverCore::refused_locked(Axis& a) {
  ++bus_.send_failures;
  ++a.status.frames_refused;
  // A refusal can stand for earlier frames of any axis that were lost as well (UDP: the ICMP error of one
  // datagram fails the next send): every axis waits for the device's next report and slews on from there.
  for (auto& axis : axes_) axis->limiter.refused();
}

void DriverCore::trip_locked(int axis, const std::string& why, std::vector<Pending>& events) {
  Axis& a = *axes_[axis];
  if (a.limiter.held_for(HoldReason::kDeviceFault)) return;
  char buf[96];
  std::snprintf(buf, sizeof buf, ": reported %.3f V, commanded %.3f V", a.status.reported_v, a.limiter.applied_v());
  a.limiter.trip(why + buf);
  ++a.status.device_faults;
  events.push_back({Pending::kEvent, {}, {}, 0, 0, a.limiter.fault(), true});
}

CommandOutcome DriverCore::command(int axis, double voltage_v, double now_s, double command_time_s) {
  if (axis < 0 || axis >= kAxisCount) throw std::invalid_argument("axis index out of range");
  std::vector<Pending> events;
  CommandOutcome outcome;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    Axis& a = *axes_[axis];
    ++a.status.commands;
    last_now_s_ = now_s;
    const bool link = transport_->is_open() && bus_.state != BusState::kBusOff;
    if (!std::isfinite(voltage_v)) {
      outcome = CommandOutcome::kRejectedNonFinite;
    } else if (!link) {
      ++a.status.rejected_no_link;
      return CommandOutcome::kRejectedHeld;
    } else {
      outcome = a.limiter.command(voltage_v, now_s, command_time_s);
    }
    switch (outcome) {
      case CommandOutcome::kRejectedNonFinite: ++a.status.rejected_non_finite; break;
      case CommandOutcome::kRejectedHeld: ++a.status.rejected_held; break;
      case CommandOutcome::kRejectedNoBaseline: ++a.status.rejected_no_baseline; break;
      case CommandOutcome::kRejectedFutureStamp: ++a.status.rejected_future_stamp; break;
      case CommandOutcome::kClamped: ++a.status.clamped; break;
      case CommandOutcome::kAccepted: break;
    }
    if (link) {
      if (auto v = a.limiter.step(now_s)) send_locked(axis, *v, now_s, events);
    }
  }
  flush(events);
  return outcome;
}

void DriverCore::tick(double now_s) {
  std::vector<Pending> events;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    last_now_s_ = now_s;
    const bool link = transport_->is_open() && bus_.state != BusState::kBusOff;
    for (int i = 0; i < kAxisCount; ++i) {
      // A refused frame left the applied voltage where it was: the next proposal starts from there again.
      const auto v = axes_[i]->limiter.step(now_s);
      if (link && v) send_locked(i, *v, now_s, events);
    }
  }
  flush(events);
}

bool DriverCore::sync() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!transport_->is_open() || bus_.state == BusState::kBusOff) {
    // held set points cannot go either: refused, like a send on a link that went down
    for (const Held& h : held_) refused_locked(*axes_[h.axis]);
    if (!held_.empty()) command_counter_ = held_.front().counter;
    held_.clear();
    return false;
  }
  std::vector<can_frame>& frames = batch_;  // reused: no allocation per sample
  frames.clear();
  for (const Held& h : held_) frames.push_back(h.frame);
  frames.push_back(codec_.encode(SyncFrame{sync_counter_}));
  std::size_t taken = 0;
  try {
    taken = frames.size() == 1 ? (transport_->send(frames[0]) ? 1 : 0)
                               : transport_->send_batch(frames.data(), frames.size());
  } catch (const TransportError& e) {
    bus_.last_error = e.what();  // the receive thread reconnects
  }
  // in order: the written set points move their axes, the first refused one and every one after it are refused
  for (std::size_t i = 0; i < held_.size(); ++i) {
    const Held& h = held_[i];
    if (i < taken) {
      written_locked(h.axis, h.voltage_v, h.now_s);
    } else {
      if (i == taken) command_counter_ = h.counter;  // the counter counts written frames
      refused_locked(*axes_[h.axis]);
    }
  }
  held_.clear();
  if (taken < frames.size()) {
    ++bus_.send_failures;
    return false;
  }
  ++sync_counter_;
  ++bus_.syncs_sent;
  return true;
}

void DriverCore::halt() {
  std::lock_guard<std::mutex> lock(mutex_);
  halted_ = true;
  for (auto& a : axes_) a->limiter.set_hold(HoldReason::kHalted, true);
}

void DriverCore::recover() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    halted_ = false;
    for (auto& a : axes_) {
      a->limiter.set_hold(HoldReason::kHalted, false);
      a->limiter.clear_fault();
    }
  }
  recover_requested_ = true;
}

void DriverCore::set_multiple_commanders(int axis, bool on) {
  if (axis < 0 || axis >= kAxisCount) return;
  std::lock_guard<std::mutex> lock(mutex_);
  axes_[axis]->limiter.set_hold(HoldReason::kMultipleCommanders, on);
}

AxisStatus DriverCore::axis_status(int axis) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const Axis& a = *axes_.at(axis);
  AxisStatus s = a.status;
  s.applied_v = a.limiter.applied_v();
  s.target_v = a.limiter.target_v();
  s.has_baseline = a.limiter.has_baseline();
  s.timed_out = a.limiter.timed_out();
  s.timeouts = a.limiter.timeouts();
  s.halted = a.limiter.held_for(HoldReason::kHalted);
  s.multiple_commanders = a.limiter.held_for(HoldReason::kMultipleCommanders);
  s.device_fault = a.limiter.held_for(HoldReason::kDeviceFault);
  s.paused = a.limiter.paused();
  s.fault = a.limiter.fault();
  s.report_mismatches = a.limiter.report_mismatches();
  s.encoder_age_s = a.has_encoder ? since(a.last_encoder) : -1.0;
  return s;
}

BusStatus DriverCore::bus_status() const {
  std::lock_guard<std::mutex> lock(mutex_);
  BusStatus s = bus_;
  s.heartbeat_age_s = bus_.heartbeat_seen ? since(last_heartbeat_) : -1.0;
  s.malformed_frames += transport_->malformed_count();
  s.next_reconnect_in_s =
      transport_->is_open() ? 0.0 : std::max(0.0, -since(next_attempt_));
  return s;
}

bool DriverCore::connect_locked(std::vector<Pending>& events) {
  if (transport_->is_open()) return true;
  if (Clock::now() < next_attempt_) return false;
  try {
    transport_->open();
    bus_.state = BusState::kConnected;
    ++bus_.connects;
    last_rx_ = Clock::now();
    events.push_back({Pending::kEvent, {}, {}, 0, 0,
                      std::string(ever_connected_ ? "reconnected to " : "connected to ") + transport_->describe(),
                      false});
    ever_connected_ = true;
    return true;
  } catch (const TransportError& e) {
    ++bus_.connect_failures;
    const bool repeated = bus_.last_error == e.what();
    bus_.last_error = e.what();
    bus_.state = BusState::kDisconnected;
    if (!repeated) events.push_back({Pending::kEvent, {}, {}, 0, 0, e.what(), true});
    next_attempt_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(backoff_s_));
    backoff_s_ = std::min(backoff_s_ * 2, config_.reconnect_max_s);
    return false;
  }
}

void DriverCore::poll_once(int timeout_ms) {
  std::vector<Pending> events;
  if (recover_requested_.exchange(false)) {
    std::lock_guard<std::mutex> lock(mutex_);
    backoff_s_ = config_.reconnect_min_s;
    if (transport_->is_open()) close_locked("recover requested", BusState::kDisconnected, events);
    next_attempt_ = Clock::now();
    backoff_s_ = config_.reconnect_min_s;
  }
  bool open;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    open = connect_locked(events);
  }
  flush(events);
  if (!open) {
    std::this_thread::sleep_for(std::chrono::milliseconds(std::min(timeout_ms, 20)));
    return;
  }

  std::vector<ReceivedFrame> frames;
  std::string failure;
  try {
    transport_->receive(frames, timeout_ms);  // only this thread closes the transport, so no lock here
  } catch (const TransportError& e) {
    failure = e.what();
  }

  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!failure.empty()) {
      close_locked(failure, BusState::kDisconnected, events);
    }
    for (const auto& rf : frames)
      if (!frame_locked(rf, events)) break;
    if (transport_->is_open() && since(last_rx_) > config_.silence_reconnect_s) {
      close_locked("no frame from the device for " + std::to_string(config_.silence_reconnect_s).substr(0, 4) + " s",
                   BusState::kDisconnected, events);
    }
  }
  flush(events);
}

bool DriverCore::frame_locked(const ReceivedFrame& rf, std::vector<Pending>& events) {
  const DecodeResult r = codec_.decode(rf.frame);
  if (!r.ok()) {
    if (r.error == DecodeError::kUnknownId) {
      ++bus_.unknown_frames;
    } else {
      ++bus_.malformed_frames;
      // Count every one, log the first of a run so garbage cannot flood the log.
      if (bus_.malformed_frames < 10 || bus_.malformed_frames % 1000 == 0)
        events.push_back({Pending::kEvent, {}, {}, 0, 0,
                          "malformed frame " + to_candump(rf.frame) + ": " + r.message, true});
    }
    return true;
  }
  if (const auto* e = std::get_if<BusError>(&r.message_value)) {
    ++bus_.error_frames;
    bus_.last_error_frame = to_candump(rf.frame);
    bus_.last_error = "error frame: " + e->description;
    if (e->bus_off) {
      ++bus_.bus_off_events;
      close_locked("bus-off (" + e->description + ")", BusState::kBusOff, events);
      return false;
    }
    if (e->restarted)
      bus_.state = BusState::kActive;
    else if (e->error_passive)
      bus_.state = BusState::kErrorPassive;
    if (bus_.error_frames < 10 || bus_.error_frames % 1000 == 0)
      events.push_back({Pending::kEvent, {}, {}, 0, 0, "CAN error frame: " + e->description, true});
    return true;
  }
  last_rx_ = Clock::now();
  if (bus_.state == BusState::kConnected) {
    bus_.state = BusState::kActive;
    backoff_s_ = config_.reconnect_min_s;  // the link works: start the next back-off from scratch
  }
  if (const auto* v = std::get_if<VoltageReport>(&r.message_value)) {
    voltage_report_locked(*v, rf.receive_time_s, events);
  } else if (const auto* en = std::get_if<EncoderReport>(&r.message_value)) {
    Axis& a = *axes_[en->axis];
    const auto u = a.encoder_seq.update(en->sequence);
    ++a.status.encoder_frames;
    a.status.encoder_dropped += u.dropped;
    a.status.encoder_out_of_order += u.out_of_order;
    a.status.position_m = en->position_m;
    a.status.encoder_valid = en->valid;
    a.last_encoder = Clock::now();
    a.has_encoder = true;
    Pending p{Pending::kEncoder, {}, *en, u.sequence, rf.receive_time_s, {}, false};
    events.push_back(std::move(p));
  } else if (const auto* hb = std::get_if<Heartbeat>(&r.message_value)) {
    bus_.heartbeat_seen = true;
    if (hb->state != DeviceState::kOperational)
      for (int i = 0; i < kAxisCount; ++i)
        trip_locked(i, std::string("controller heartbeat says ") + to_string(hb->state), events);
    bus_.device_state = hb->state;
    bus_.device_fault_flags = hb->fault_flags;
    last_heartbeat_ = Clock::now();
  }
  // Command frames (another commander on the bus) pass the device filter only; ignored here.
  return true;
}

void DriverCore::voltage_report_locked(const VoltageReport& v, double receive_time_s, std::vector<Pending>& events) {
  Axis& a = *axes_[v.axis];
  const auto u = a.voltage_seq.update(v.sequence);
  ++a.status.voltage_frames;
  a.status.voltage_dropped += u.dropped;
  a.status.voltage_out_of_order += u.out_of_order;
  a.status.amplifier_fault = v.fault;
  // A repeated frame says nothing new.
  if (!u.out_of_order) {
    a.status.reported_v = v.voltage_v;
    if (u.restarted) {
      char back[80];
      std::snprintf(back, sizeof back, "report sequence went back to %u (controller restart?)", v.sequence);
      trip_locked(v.axis, back, events);
    }
    const bool was_held = a.limiter.held_for(HoldReason::kDeviceFault);
    a.limiter.on_reported_voltage(v.voltage_v, last_now_s_);
    if (!was_held && a.limiter.held_for(HoldReason::kDeviceFault)) {  // reports away from the commanded value
      ++a.status.device_faults;
      events.push_back({Pending::kEvent, {}, {}, 0, 0, a.limiter.fault(), true});
    }
  }
  Pending p{Pending::kVoltage, v, {}, u.sequence, receive_time_s, {}, false};
  events.push_back(std::move(p));
}

}  // namespace piezo::can
