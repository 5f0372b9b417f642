// Measures command received → CAN frame written for the driver's command path (can::DriverCore over the UDP
// transport on loopback, its receive thread running as in the node) under a 1 kHz command stream, and prints
// a latency histogram. Latency per command = kernel receive timestamp (SO_TIMESTAMP) of the command frame on
// the device's socket − the wall time the command entered DriverCore::command(). Frames are matched by the
// codec's command counter. Run by `scripts/piezo bench`; options: --seconds S --rate-hz R.
#include <sched.h>
#include <sys/time.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "latency_histogram.h"
#include "piezo_compensation/can/driver_core.h"

using namespace piezo::can;
using piezo::bench::percentile;
using piezo::bench::wall_s;

namespace {

// The device side: a plain UDP transport that reports what it was last commanded (counter running: the driver
// checks both) and timestamps the command frames that arrive, matched to the commands by the codec's counter.
class MeasuringDevice {
 public:
  MeasuringDevice(const Codec& codec, int port) : codec_(codec) {
    UdpOptions dev;
    dev.local_port = port + 1;
    dev.remote_port = port;
    dev.filters = codec.device_filters();
    device_ = make_udp_transport(dev);
    device_->open();
  }

  void report() {
    std::lock_guard<std::mutex> l(m_);
    for (int a = 0; a < kAxisCount; ++a)
      device_->send(codec_.encode(VoltageReport{a, reported_[a], report_seq_, false}));
    ++report_seq_;
  }
  void start() {
    receiver_ = std::thread([this] { receive_loop(); });
  }
  void stop() {
    done_ = true;
    receiver_.join();
  }
  // A command about to enter DriverCore::command(), and its frame's counter; forget() when it wrote none.
  void sending(std::uint32_t counter, double t) {
    std::lock_guard<std::mutex> l(m_);
    sent_at_[counter] = t;
  }
  void forget(std::uint32_t counter) {
    std::lock_guard<std::mutex> l(m_);
    sent_at_.erase(counter);
  }
  // After stop(): the matched latencies, the commands whose frame never came, frames no command matched.
  const std::vector<double>& latency_us() const { return latency_us_; }
  std::size_t lost() const { return sent_at_.size(); }
  std::uint64_t unmatched() const { return unmatched_; }

 private:
  void receive_loop() {
    std::vector<ReceivedFrame> in;
    auto next_report = std::chrono::steady_clock::now();
    while (!done_) {
      if (std::chrono::steady_clock::now() >= next_report) {
        report();
        next_report += std::chrono::milliseconds(50);
      }
      in.clear();
      device_->receive(in, 5);
      std::lock_guard<std::mutex> l(m_);
      for (const auto& rf : in) {
        const DecodeResult r = codec_.decode(rf.frame);
        if (!r.ok()) continue;
        const auto* c = std::get_if<CommandFrame>(&r.message_value);
        if (!c) continue;
        reported_[c->axis] = c->voltage_v;
        auto it = sent_at_.find(c->counter);
        if (it == sent_at_.end()) {
          ++unmatched_;
          continue;
        }
        latency_us_.push_back((rf.receive_time_s - it->second) * 1e6);
        sent_at_.erase(it);
      }
    }
  }

  const Codec& codec_;
  std::unique_ptr<Transport> device_;
  std::mutex m_;
  std::array<double, kAxisCount> reported_{};
  std::uint32_t report_seq_ = 0;
  std::map<std::uint32_t, double> sent_at_;  // counter → wall time of command()
  std::vector<double> latency_us_;
  std::atomic<bool> done_{false};
  std::uint64_t unmatched_ = 0;
  std::thread receiver_;
};

DriverConfig driver_config(const ProtocolConfig& protocol) {
  DriverConfig config;
  config.protocol = protocol;
  config.limits.slew_rate_v_per_s = 1000.0;
  config.limits.command_timeout_s = 1.0;
  config.silence_reconnect_s = 1e6;  // the measuring device reports once; silence is not a fault here
  return config;
}

struct CommandRun {
  long long total = 0;
  std::vector<double> call_us;  // duration of each DriverCore::command() call
  std::uint64_t no_frame = 0;   // commands that needed no frame
};

// The command stream on axis 0 at rate_hz: a sine that changes every command, so one frame each.
CommandRun send_commands(DriverCore& driver, MeasuringDevice& device, double seconds, double rate_hz) {
  // Counter of the next command frame = frames already written on every axis.
  std::uint32_t counter = 0;
  for (int a = 0; a < kAxisCount; ++a) counter += driver.axis_status(a).frames_sent;
  CommandRun run;
  const auto period = std::chrono::nanoseconds(static_cast<long long>(1e9 / rate_hz));
  run.total = static_cast<long long>(seconds * rate_hz);
  run.call_us.reserve(run.total);
  auto next = std::chrono::steady_clock::now();
  const double t0 = std::chrono::duration<double>(next.time_since_epoch()).count();
  for (long long k = 0; k < run.total; ++k) {
    next += period;
    std::this_thread::sleep_until(next);
    const double t = std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
    const double v = 10.0 * std::sin(2 * M_PI * 1.0 * (t - t0));  // changes every command: one frame each
    const std::uint64_t before = driver.axis_status(0).frames_sent;
    device.sending(counter, wall_s());
    const auto c0 = std::chrono::steady_clock::now();
    driver.command(0, v, t);
    run.call_us.push_back(
        std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - c0).count());
    if (driver.axis_status(0).frames_sent > before) {
      ++counter;
    } else {
      device.forget(counter);
      ++run.no_frame;
    }
  }
  return run;
}

// Prints the histogram and percentiles; returns the exit code (1 when no frame was matched).
int print_results(const MeasuringDevice& device, const CommandRun& run, double seconds, double rate_hz) {
  const std::vector<double>& latency_us = device.latency_us();
  const std::vector<double> edges = {10, 20, 50, 100, 200, 500, 1000, 2000, 5000};
  std::printf("command received -> CAN frame written (UDP loopback, kernel rx timestamp), %.0f Hz for %.1f s\n",
              rate_hz, seconds);
  std::printf("commands %lld, frames matched %zu, no frame needed %llu, lost %zu, unmatched %llu\n",
              run.total, latency_us.size(), static_cast<unsigned long long>(run.no_frame), device.lost(),
              static_cast<unsigned long long>(device.unmatched()));
  piezo::bench::print_latency_histogram(latency_us, edges);
  const double p99 = piezo::bench::print_latency_percentiles(latency_us);
  std::printf("DriverCore::command() call [us]: p50 %.1f  p99 %.1f  max %.1f\n", percentile(run.call_us, 50),
              percentile(run.call_us, 99), percentile(run.call_us, 100));
  std::printf("target p99 <= 1000 us: %s\n", p99 <= 1000.0 ? "met" : "NOT met");
  return latency_us.empty() ? 1 : 0;
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 10.0, rate_hz = 1000.0;
  if (!piezo::bench::parse_latency_options(argc, argv, seconds, rate_hz)) return 2;
  if (!(seconds > 0) || !(rate_hz > 0)) {
    std::fprintf(stderr, "can_command_latency: --seconds and --rate-hz must be > 0\n");
    return 2;
  }
  const int port = 40000 + static_cast<int>(getpid() % 10000) * 2;
  ProtocolConfig protocol;
  const Codec codec(protocol);
  MeasuringDevice device(codec, port);
  DriverCore driver(driver_config(protocol),
                    [&] {
                      UdpOptions o;
                      o.local_port = port;
                      o.remote_port = port + 1;
                      o.filters = codec.driver_filters();
                      return make_udp_transport(o);
                    },
                    {});
  driver.start();
  for (int tries = 0; tries < 200 && !driver.axis_status(0).has_baseline; ++tries) {
    device.report();
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  if (!driver.axis_status(0).has_baseline) {
    std::fprintf(stderr, "can_command_latency: the driver never connected (%s)\n",
                 driver.bus_status().last_error.c_str());
    return 1;
  }
  device.start();
  const CommandRun run = send_commands(driver, device, seconds, rate_hz);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  device.stop();
  driver.stop();
  return print_results(device, run, seconds, rate_hz);
}
