#include "piezo_compensation/nanocontrol/transport.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <stdexcept>
#include <thread>
#include <variant>
#include <vector>

#include "piezo_compensation/can/codec.h"
#include "piezo_compensation/nanocontrol/serial_port.h"

namespace piezo::nanocontrol {

void validate(const LinkOptions& o) {
  if (o.port.empty()) throw std::invalid_argument("port must not be empty");
  if (!supported_baud(o.baud)) throw std::invalid_argument("baud " + std::to_string(o.baud) + " is not a termios speed");
  if (!(o.reply_timeout_s >= 0.001 && o.reply_timeout_s <= 10.0))
    throw std::invalid_argument("reply_timeout_s must be within [0.001, 10] s");
  for (int i = 0; i < 3; ++i) {
    if (channel_index(o.channels[i]) < 0) throw std::invalid_argument("channels must be three of A, B, C, D");
    for (int j = 0; j < i; ++j)
      if (o.channels[i] == o.channels[j]) throw std::invalid_argument("channels must differ");
    if (!std::isfinite(o.nm_per_count[i]) || o.nm_per_count[i] == 0.0 || std::abs(o.nm_per_count[i]) > 1e6)
      throw std::invalid_argument("nm_per_count must be finite, non-zero and within ±1e6 nm");
  }
  if (!(o.counts_per_volt > 0 && o.counts_per_volt <= 1e6)) throw std::invalid_argument("counts_per_volt must be in (0, 1e6]");
  if (o.counter_reads < 1 || o.counter_reads > 100) throw std::invalid_argument("counter_reads must be 1..100");
  if (!(o.min_sample_period_s >= 0 && o.min_sample_period_s <= 60)) throw std::invalid_argument("min_sample_period_s must be within [0, 60] s");
  if (!(o.min_voltage_v < o.max_voltage_v)) throw std::invalid_argument("min_voltage_v must be below max_voltage_v");
  // the DAC's reach: a limit beyond it could never be commanded, and would say the axis could go there
  const double reach_lo = kFine16Min / o.counts_per_volt, reach_hi = (kFine16Max + 1) / o.counts_per_volt;
  if (o.min_voltage_v < reach_lo - 1e-9 || o.max_voltage_v > reach_hi + 1e-9)
    throw std::invalid_argument("voltage limits must lie within the fine16 range [" + std::to_string(reach_lo) + ", " +
                                std::to_string(reach_hi) + "] V at counts_per_volt " + std::to_string(o.counts_per_volt));
}

can::ProtocolConfig frame_protocol() {
  can::ProtocolConfig p;
  p.voltage_lsb_v = 1e-6;    // ±2147 V: below a DAC count (2.4 mV)
  p.position_lsb_m = 1e-11;  // ±21 mm: the coarse range; a mean of reads keeps 0.01 nm
  p.encoder_rate_hz = 10.0;  // the study's ≈10 Hz (only for stamps under simulated time)
  p.heartbeat_period_s = 1.0;
  return p;
}

LinkMonitor::Snapshot LinkMonitor::snapshot() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return snap_;
}

void LinkMonitor::update(const Snapshot& s) {
  std::lock_guard<std::mutex> lock(mutex_);
  snap_ = s;
}

namespace {

double nc_wall_s() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}
double nc_mono_s() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

class NanoControlTransport final : public can::Transport {
 public:
  NanoControlTransport(const LinkOptions& o, std::shared_ptr<LinkMonitor> monitor)
      : o_(o), codec_(frame_protocol()), monitor_(std::move(monitor)) {
    validate(o_);
    if (monitor_) snap_ = monitor_->snapshot();
  }
  ~NanoControlTransport() override { close(); }

  void open() override;
  void close() override {
    std::lock_guard<std::mutex> lock(io_);
    port_.close();
    open_ = false;
  }
  bool is_open() const override { return open_; }
  bool send(const can_frame& frame) override;
  int receive(std::vector<can::ReceivedFrame>& out, int timeout_ms) override;
  std::uint64_t malformed_count() const override { return garbled_; }
  std::string describe() const override { return "nanocontrol:" + o_.port + "@" + std::to_string(o_.baud); }

 private:
  Exchange exchange_locked(const std::string& command);
  bool finish_locked(Exchange e);  // records, publishes; true when ok
  void drain_locked();
  void publish_locked();
  [[noreturn]] void fail_locked(const can::TransportError& e);
  bool sample(std::vector<can::ReceivedFrame>& out);
  bool read_four(const std::string& command, std::int64_t lo, std::int64_t hi, std::array<std::int64_t, 4>& values);

  LinkOptions o_;
  can::Codec codec_;
  std::shared_ptr<LinkMonitor> monitor_;
  std::mutex io_;  // the port, the line buffer, the state: one exchange at a time
  SerialPort port_;
  LineBuffer lines_;
  LinkState state_;
  LinkMonitor::Snapshot snap_;
  std::string failed_;  // a send() lost the port: the receive thread reports it (and reconnects)
  std::atomic<bool> open_{false};
  std::atomic<std::uint64_t> garbled_{0};
  std::uint32_t sequence_ = 0;
  bool breakdown_reported_ = false;  // the latched breakdown went out in a heartbeat
  double next_sample_s_ = 0.0, last_sample_s_ = -1.0;
};

void NanoControlTransport::open() {
  std::lock_guard<std::mutex> lock(io_);
  failed_.clear();
  port_.open(o_.port, o_.baud);
  state_.reset();
  breakdown_reported_ = false;
  lines_.clear();
  Exchange e;
  try {
    e = exchange_locked("version");
  } catch (const can::TransportError&) {
    port_.close();
    throw;
  }
  const Outcome outcome = e.outcome;
  const std::string message = e.message;
  finish_locked(e);
  if (outcome != Outcome::kOk) {
    port_.close();
    throw can::TransportError("nanocontrol " + o_.port + ": `version` got " + to_string(outcome) +
                              (message.empty() ? "" : " (" + message + ")") + ": no NanoControl answering");
  }
  snap_.version = message;
  publish_locked();
  next_sample_s_ = nc_mono_s();
  open_ = true;
}

void NanoControlTransport::fail_locked(const can::TransportError& e) {
  failed_ = e.what();
  open_ = port_.is_open();
  throw e;
}

void NanoControlTransport::drain_locked() {
  // stray bytes (a late reply, the rest of a partial line): discard until 20 ms pass without one
  const double end = nc_mono_s() + o_.reply_timeout_s;
  std::string junk;
  while (nc_mono_s() < end) {
    junk.clear();
    if (port_.read_some(junk, 0.02) == 0) break;
  }
  port_.flush_input();
  lines_.clear();
}

Exchange NanoControlTransport::exchange_locked(const std::string& command) {
  if (state_.needs_drain()) {
    drain_locked();
    state_.drained();
  }
  port_.flush_input();  // as the study did before each command: only this command's reply is read
  lines_.clear();
  port_.write_all(write_command(command), o_.reply_timeout_s);
  const double deadline = nc_mono_s() + o_.reply_timeout_s;
  std::string chunk;
  for (;;) {
    if (auto line = lines_.next_line()) return classify(command, line);
    const double left = deadline - nc_mono_s();
    if (left <= 0) return classify(command, std::nullopt);
    chunk.clear();
    if (port_.read_some(chunk, left) > 0) lines_.append(chunk.data(), chunk.size());
  }
}

bool NanoControlTransport::finish_locked(Exchange e) {
  if (e.outcome == Outcome::kGarbled) ++garbled_;
  const bool ok = state_.record(e, o_.reply_timeout_s);
  publish_locked();
  return ok;
}

void NanoControlTransport::publish_locked() {
  snap_.counters = state_.counters();
  if (monitor_) monitor_->update(snap_);
}

bool NanoControlTransport::send(const can_frame& frame) {
  const can::DecodeResult r = codec_.decode(frame);
  const auto* c = r.ok() ? std::get_if<can::CommandFrame>(&r.message_value) : nullptr;
  if (!c) return false;  // only set points go to the controller (no SYNC: refused at start-up)
  std::lock_guard<std::mutex> lock(io_);
  if (!failed_.empty()) throw can::TransportError(failed_);
  if (!port_.is_open()) throw can::TransportError("nanocontrol " + o_.port + ": port not open");
  if (!state_.set_point_allowed()) return false;  // an i reply is latched: nothing moves until ~recover
  const auto counts = counts_for_voltage(c->voltage_v, o_.counts_per_volt, std::min(o_.min_voltage_v, c->voltage_v),
                                         std::max(o_.max_voltage_v, c->voltage_v));
  if (!counts) return false;  // no DAC count within the limits (validate() makes this unreachable for valid limits)
  try {
    return finish_locked(exchange_locked(set_fine16(o_.channels[c->axis], *counts)));
  } catch (const can::TransportError& e) {
    fail_locked(e);
  }
}

bool NanoControlTransport::read_four(const std::string& command, std::int64_t lo, std::int64_t hi,
                                     std::array<std::int64_t, 4>& values) {
  std::lock_guard<std::mutex> lock(io_);
  try {
    Exchange e = exchange_locked(command);
    if (e.outcome == Outcome::kOk) {
      std::string error;
      if (auto v = parse_four(e.message, lo, hi, &error)) {
        values = *v;
      } else {
        e.outcome = Outcome::kGarbled;
        e.message = error;
      }
    }
    return finish_locked(e);
  } catch (const can::TransportError& err) {
    fail_locked(err);
  }
}

bool NanoControlTransport::sample(std::vector<can::ReceivedFrame>& out) {
  const int n = o_.counter_reads;
  std::array<std::vector<std::int64_t>, 3> reads;
  double time_sum_s = 0;
  const double start_s = nc_mono_s();
  std::array<std::int64_t, 4> values{};
  for (int k = 0; k < n; ++k) {
    if (!read_four("counterread", -1'000'000'000'000LL, 1'000'000'000'000LL, values)) return false;
    time_sum_s += nc_wall_s();
    for (int i = 0; i < 3; ++i) reads[i].push_back(values[channel_index(o_.channels[i])]);
  }
  std::array<std::int64_t, 4> fine{};
  if (!read_four("fine16 ?", kFine16Min, kFine16Max, fine)) return false;
  const double stamp_s = time_sum_s / n;
  const std::uint32_t seq = sequence_++ % can::kSequenceModulo;
  std::vector<can::ReceivedFrame> frames;
  std::lock_guard<std::mutex> lock(io_);
  try {
    for (int i = 0; i < 3; ++i) {
      const ReadStats s = read_stats(reads[i]);
      const double scale_m = o_.nm_per_count[i] * 1e-9;
      snap_.position_m[i] = s.mean * scale_m;
      snap_.sigma_m[i] = s.sigma * std::abs(scale_m);
      const double volts = fine[channel_index(o_.channels[i])] / o_.counts_per_volt;
      frames.push_back({codec_.encode(can::VoltageReport{i, volts, seq, false}), stamp_s});
      frames.push_back({codec_.encode(can::EncoderReport{i, snap_.position_m[i], seq, true}), stamp_s});
    }
  } catch (const std::invalid_argument& e) {  // a counter beyond the frame's ±21 mm
    ++garbled_;
    snap_.counters.last_garbled = std::string("`counterread`: ") + e.what();
    return false;
  }
  // A breakdown is reported once, in the first sample after it: DriverCore then holds every axis until ~recover,
  // and the latch keeps set points off the line until the reopen ~recover makes. A heartbeat saying fault on
  // every sample would trip the axes again with the sample that is under way when ~recover comes.
  const bool report_breakdown = state_.counters().breakdown && !breakdown_reported_;
  breakdown_reported_ = state_.counters().breakdown;
  can::Heartbeat hb;
  hb.state = report_breakdown ? can::DeviceState::kFault : can::DeviceState::kOperational;
  hb.fault_flags = report_breakdown ? 0x07 : 0x00;
  hb.counter = static_cast<std::uint16_t>(seq);
  frames.push_back({codec_.encode(hb), stamp_s});
  out.insert(out.end(), frames.begin(), frames.end());
  const double now = nc_mono_s();
  snap_.sample_duration_s = now - start_s;
  if (last_sample_s_ >= 0) snap_.sample_period_s = start_s - last_sample_s_;
  last_sample_s_ = start_s;
  state_.sample_done(true);
  publish_locked();
  return true;
}

int NanoControlTransport::receive(std::vector<can::ReceivedFrame>& out, int timeout_ms) {
  {
    std::lock_guard<std::mutex> lock(io_);
    if (!failed_.empty()) throw can::TransportError(failed_);
  }
  const double wait_s = next_sample_s_ - nc_mono_s();
  if (wait_s > 0) {
    std::this_thread::sleep_for(std::chrono::duration<double>(std::min(wait_s, timeout_ms / 1000.0)));
    if (next_sample_s_ > nc_mono_s()) return 0;
  }
  next_sample_s_ = nc_mono_s() + o_.min_sample_period_s;
  const std::size_t before = out.size();
  if (!sample(out)) {
    std::lock_guard<std::mutex> lock(io_);
    state_.sample_done(false);
    publish_locked();
  }
  return static_cast<int>(out.size() - before);
}

}  // namespace

std::unique_ptr<can::Transport> make_transport(const LinkOptions& options, std::shared_ptr<LinkMonitor> monitor) {
  return std::make_unique<NanoControlTransport>(options, std::move(monitor));
}

}  // namespace piezo::nanocontrol
