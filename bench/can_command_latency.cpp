// Measures command received → CAN frame written for the driver's command path (can::DriverCore over the UDP
// transport on loopback, its receive thread running as in the node) under a 1 kHz command stream, and prints
// a latency histogram. Latency per command = kernel receive timestamp (SO_TIMESTAMP) of the command frame on
// the device's socket − the wall time the command entered DriverCore::command(). Frames are matched by the
// codec's command counter. Run by `scripts/piezo bench`; options: --seconds S --rate-hz R.
#include <sched.h>
#include <sys/time.h>
#include <unistd.h>

#include <algorithm>
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

#include "piezo_compensation/can/driver_core.h"

using namespace piezo::can;

namespace {

double wall_s() {
  timespec ts;
  clock_gettime(CLOCK_REALTIME, &ts);
  return ts.tv_sec + ts.tv_nsec * 1e-9;
}

double percentile(std::vector<double> v, double p) {
  if (v.empty()) return std::nan("");
  std::sort(v.begin(), v.end());
  const std::size_t k = std::min(v.size() - 1, static_cast<std::size_t>(std::ceil(p / 100.0 * v.size())) - 1);
  return v[k];
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 10.0, rate_hz = 1000.0;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string a = argv[i];
    if (a == "--seconds") seconds = std::atof(argv[i + 1]);
    else if (a == "--rate-hz") rate_hz = std::atof(argv[i + 1]);
    else {
      std::fprintf(stderr, "usage: %s [--seconds S] [--rate-hz R]\n", argv[0]);
      return 2;
    }
  }
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
  for (int tries = 0; tries < 200 && !driver.axis_status(0).has_baseline; ++tries) {
    for (int a = 0; a < kAxisCount; ++a) device->send(codec.encode(VoltageReport{a, 0.0, 0, false}));
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  if (!driver.axis_status(0).has_baseline) {
    std::fprintf(stderr, "can_command_latency: the driver never connected (%s)\n", driver.bus_status().last_error.c_str());
    return 1;
  }

  // Counter of the next command frame = frames already written on every axis.
  std::uint32_t counter = 0;
  for (int a = 0; a < kAxisCount; ++a) counter += driver.axis_status(a).frames_sent;

  std::mutex m;
  std::map<std::uint32_t, double> sent_at;  // counter → wall time of command()
  std::vector<double> latency_us;
  std::atomic<bool> done{false};
  std::uint64_t unmatched = 0;
  std::thread receiver([&] {
    std::vector<ReceivedFrame> in;
    while (!done) {
      in.clear();
      device->receive(in, 5);
      std::lock_guard<std::mutex> l(m);
      for (const auto& rf : in) {
        const DecodeResult r = codec.decode(rf.frame);
        if (!r.ok()) continue;
        const auto* c = std::get_if<CommandFrame>(&r.message_value);
        if (!c) continue;
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
  std::vector<std::size_t> counts(edges.size() + 1, 0);
  for (double x : latency_us) counts[std::upper_bound(edges.begin(), edges.end(), x) - edges.begin()]++;
  std::printf("command received -> CAN frame written (UDP loopback, kernel rx timestamp), %.0f Hz for %.1f s\n",
              rate_hz, seconds);
  std::printf("commands %lld, frames matched %zu, no frame needed %llu, lost %zu, unmatched %llu\n", total,
              latency_us.size(), static_cast<unsigned long long>(no_frame), sent_at.size(),
              static_cast<unsigned long long>(unmatched));
  const std::size_t n = std::max<std::size_t>(1, latency_us.size());
  for (std::size_t b = 0; b < counts.size(); ++b) {
    char label[48];
    if (b == 0)
      std::snprintf(label, sizeof label, "      < %5.0f us", edges[0]);
    else if (b == edges.size())
      std::snprintf(label, sizeof label, "     >= %5.0f us", edges.back());
    else
      std::snprintf(label, sizeof label, "%5.0f - %5.0f us", edges[b - 1], edges[b]);
    const int bar = static_cast<int>(std::round(60.0 * counts[b] / n));
    std::printf("  %s %7zu %6.2f%% %s\n", label, counts[b], 100.0 * counts[b] / n, std::string(bar, '#').c_str());
  }
  const double p99 = percentile(latency_us, 99);
  std::printf("latency [us]: p50 %.1f  p90 %.1f  p99 %.1f  p99.9 %.1f  max %.1f\n", percentile(latency_us, 50),
              percentile(latency_us, 90), p99, percentile(latency_us, 99.9), percentile(latency_us, 100));
  std::printf("DriverCore::command() call [us]: p50 %.1f  p99 %.1f  max %.1f\n", percentile(call_us, 50),
              percentile(call_us, 99), percentile(call_us, 100));
  std::printf("target p99 <= 1000 us: %s\n", p99 <= 1000.0 ? "met" : "NOT met");
  return latency_us.empty() ? 1 : 0;
}
