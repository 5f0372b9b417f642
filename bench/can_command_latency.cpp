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
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "latency_histogram.h"
#include "piezo_compensation/can/driver_core.h"

using namespace piezo::can;
using piezo::bench::percentile;
using piezo::bench::wall_s;

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

  // The device side: a plain UDP transport that reports a baseline and timestamps what arrives.
  UdpOptions dev;
  dev.local_port = port + 1;
  dev.remote_port = port;
  dev.filters = codec.device_filters();
  auto device = make_udp_transport(dev);
  device->open();

  DriverConfig config;
  config.protocol = protocol;
  config.limits.slew_rate_v_per_s = 1000.0;
  config.limits.command_timeout_s = 1.0;
  config.silence_reconnect_s = 1e6;  // the measuring device reports once; silence is not a fault here
  DriverCore driver(config, [&] {
    UdpOptions o;
    o.local_port = port;
    o.remote_port = port + 1;
    o.filters = codec.driver_filters();
    return make_udp_transport(o);
  }, {});
  driver.start();
  // The controller's reports: what it was last commanded, counter running (the driver checks both).
  std::mutex m;
  std::array<double, kAxisCount> reported{};
  std::uint32_t report_seq = 0;
  auto report = [&] {
    std::lock_guard<std::mutex> l(m);
    for (int a = 0; a < kAxisCount; ++a) device->send(codec.encode(VoltageReport{a, reported[a], report_seq, false}));
    ++report_seq;
  };
  for (int tries = 0; tries < 200 && !driver.axis_status(0).has_baseline; ++tries) {
    report();
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  if (!driver.axis_status(0).has_baseline) {
    std::fprintf(stderr, "can_command_latency: the driver never connected (%s)\n", driver.bus_status().last_error.c_str());
    return 1;
  }

  // Counter of the next command frame = frames already written on every axis.
  std::uint32_t counter = 0;
  for (int a = 0; a < kAxisCount; ++a) counter += driver.axis_status(a).frames_sent;

  std::map<std::uint32_t, double> sent_at;  // counter → wall time of command()
  std::vector<double> latency_us;
  std::atomic<bool> done{false};
  std::uint64_t unmatched = 0;
  std::thread receiver([&] {
    std::vector<ReceivedFrame> in;
    auto next_report = std::chrono::steady_clock::now();
    while (!done) {
      if (std::chrono::steady_clock::now() >= next_report) {
        report();
        next_report += std::chrono::milliseconds(50);
      }
      in.clear();
      device->receive(in, 5);
      std::lock_guard<std::mutex> l(m);
      for (const auto& rf : in) {
        const DecodeResult r = codec.decode(rf.frame);
        if (!r.ok()) continue;
        const auto* c = std::get_if<CommandFrame>(&r.message_value);
        if (!c) continue;
        reported[c->axis] = c->voltage_v;
        auto it = sent_at.find(c->counter);
        if (it == sent_at.end()) {
          ++unmatched;
          continue;
        }
        latency_us.push_back((rf.receive_time_s - it->second) * 1e6);
        sent_at.erase(it);
      }
    }
  });

  const auto period = std::chrono::nanoseconds(static_cast<long long>(1e9 / rate_hz));
  const long long total = static_cast<long long>(seconds * rate_hz);
  std::vector<double> call_us;
  call_us.reserve(total);
  std::uint64_t no_frame = 0;
  auto next = std::chrono::steady_clock::now();
  const double t0 = std::chrono::duration<double>(next.time_since_epoch()).count();
  for (long long k = 0; k < total; ++k) {
    next += period;
    std::this_thread::sleep_until(next);
    const double t = std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
    const double v = 10.0 * std::sin(2 * M_PI * 1.0 * (t - t0));  // changes every command: one frame each
    const std::uint64_t before = driver.axis_status(0).frames_sent;
    {
      std::lock_guard<std::mutex> l(m);
      sent_at[counter] = wall_s();
    }
    const auto c0 = std::chrono::steady_clock::now();
    driver.command(0, v, t);
    call_us.push_back(std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - c0).count());
    if (driver.axis_status(0).frames_sent > before) {
      ++counter;
    } else {
      std::lock_guard<std::mutex> l(m);
      sent_at.erase(counter);
      ++no_frame;
    }
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  done = true;
  receiver.join();
  driver.stop();

  std::lock_guard<std::mutex> l(m);
  const std::vector<double> edges = {10, 20, 50, 100, 200, 500, 1000, 2000, 5000};
  std::printf("command received -> CAN frame written (UDP loopback, kernel rx timestamp), %.0f Hz for %.1f s\n",
              rate_hz, seconds);
  std::printf("commands %lld, frames matched %zu, no frame needed %llu, lost %zu, unmatched %llu\n", total,
              latency_us.size(), static_cast<unsigned long long>(no_frame), sent_at.size(),
              static_cast<unsigned long long>(unmatched));
  piezo::bench::print_latency_histogram(latency_us, edges);
  const double p99 = piezo::bench::print_latency_percentiles(latency_us);
  std::printf("DriverCore::command() call [us]: p50 %.1f  p99 %.1f  max %.1f\n", percentile(call_us, 50),
              percentile(call_us, 99), percentile(call_us, 100));
  std::printf("target p99 <= 1000 us: %s\n", p99 <= 1000.0 ? "met" : "NOT met");
  return latency_us.empty() ? 1 : 0;
}
