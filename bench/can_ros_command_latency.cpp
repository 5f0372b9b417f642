// End-to-end command latency through ROS: a 1 kHz VoltageCommand stream published over TCPROS to a real
// mm3e_driver process (UDP transport), timed until the command frame is in the kernel at the simulated device's
// socket (SO_TIMESTAMP). Starts its own rosmaster on a free port and the driver as a child process, so it needs
// no running ROS. Frames are matched to commands by voltage (every command is a distinct 0.1 mV step).
// Run by `scripts/piezo bench`; options: --seconds S --rate-hz R.
#include <ros/ros.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <unordered_map>
#include <vector>

#include "child_process.h"
#include "latency_histogram.h"
#include "piezo_compensation/VoltageCommand.h"
#include "piezo_compensation/can/codec.h"
#include "piezo_compensation/can/transport.h"

using namespace piezo::can;
namespace fs = std::filesystem;
using piezo::bench::spawn;
using piezo::bench::stop;
using piezo::bench::wall_s;

namespace {

// The simulated device: a live controller that reports what it was last commanded, and timestamps the command
// frames that arrive, matched to the commands by voltage.
class MeasuringDevice {
 public:
  MeasuringDevice(int dev_port, int drv_port) {
    UdpOptions dev;
    dev.local_port = dev_port;
    dev.remote_port = drv_port;
    dev.filters = codec_.device_filters();
    device_ = make_udp_transport(dev);
    device_->open();
    receiver_ = std::thread([this] { receive_loop(); });
  }
  void stop() {
    done_ = true;
    receiver_.join();
  }
  // A command of `counts` (0.1 mV) about to be published at wall time t.
  void sending(std::int32_t counts, double t) {
    std::lock_guard<std::mutex> l(m_);
    sent_at_[counts] = t;
  }
  // Forgets what the warm-up sent and matched.
  void clear() {
    std::lock_guard<std::mutex> l(m_);
    sent_at_.clear();
    latency_us_.clear();
  }
  std::uint64_t frames() const { return frames_; }
  // The matched latencies and the commands whose frame never came (dropped by the queue-1 subscriber).
  std::vector<double> latency_us() {
    std::lock_guard<std::mutex> l(m_);
    return latency_us_;
  }
  std::size_t dropped() {
    std::lock_guard<std::mutex> l(m_);
    return sent_at_.size();
  }

 private:
  void receive_loop() {
    std::vector<ReceivedFrame> in;
    auto next_report = std::chrono::steady_clock::now();
    std::array<double, kAxisCount> reported{};
    std::uint32_t seq = 0;
    while (!done_) {
      if (std::chrono::steady_clock::now() >= next_report) {  // a live controller: what it was last commanded
        for (int a = 0; a < kAxisCount; ++a)
          device_->send(codec_.encode(VoltageReport{a, reported[a], seq, false}));
        ++seq;
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
        ++frames_;
        reported[c->axis] = c->voltage_v;
        auto it = sent_at_.find(static_cast<std::int32_t>(std::lround(c->voltage_v / 1e-4)));
        if (it == sent_at_.end()) continue;
        latency_us_.push_back((rf.receive_time_s - it->second) * 1e6);
        sent_at_.erase(it);
      }
    }
  }

  const Codec codec_{ProtocolConfig{}};
  std::unique_ptr<Transport> device_;
  std::mutex m_;
  std::unordered_map<std::int32_t, double> sent_at_;  // voltage counts → wall time before publish()
  std::vector<double> latency_us_;
  std::atomic<bool> done_{false};
  std::atomic<std::uint64_t> frames_{0};
  std::thread receiver_;
};

// The driver's parameters, then the driver as a child process; its pid.
pid_t start_driver(const fs::path& driver_bin, int drv_port, int dev_port, const std::string& log_dir) {
  ros::NodeHandle p("/latency/mm3e_driver");
  p.setParam("transport", "udp");
  p.setParam("udp_local_port", drv_port);
  p.setParam("udp_remote_port", dev_port);
  p.setParam("slew_rate_v_per_s", 2000.0);  // every command (a 0.1 mV step) is one frame
  p.setParam("command_timeout_s", 1.0);
  p.setParam("silence_reconnect_s", 3600.0);
  return spawn({driver_bin.string(), "__name:=mm3e_driver", "__ns:=/latency"}, log_dir + "/driver.log");
}

// The VoltageCommand publisher, each command timed at the device.
class Commander {
 public:
  explicit Commander(MeasuringDevice& device)
      : device_(device),
        pub_(ros::NodeHandle("/latency").advertise<piezo_compensation::VoltageCommand>("a/command", 1)) {}
  void publish(std::int32_t counts) {
    piezo_compensation::VoltageCommand c;
    c.voltage = counts * 1e-4;
    const double t = wall_s();
    c.header.stamp = ros::Time(t);
    device_.sending(counts, t);
    pub_.publish(c);
  }
  // Warm-up: waits for the connection and for the driver to act on commands at all.
  bool warm_up() {
    bool ready = false;
    for (int i = 0; i < 300 && !ready; ++i) {
      if (pub_.getNumSubscribers() > 0)
        publish(-350000 - 300 + i);  // within max_unconfirmed_v of the −35 V start
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
      ready = device_.frames() > 0;
    }
    return ready;
  }

 private:
  MeasuringDevice& device_;
  ros::Publisher pub_;
};

// The measured stream and its report; returns the exit code (1 when no frame was matched).
int measure(Commander& commander, MeasuringDevice& device, double seconds, double rate_hz) {
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  device.clear();
  const long long total = static_cast<long long>(seconds * rate_hz);
  const auto period = std::chrono::nanoseconds(static_cast<long long>(1e9 / rate_hz));
  auto next = std::chrono::steady_clock::now();
  for (long long k = 0; k < total; ++k) {
    next += period;
    std::this_thread::sleep_until(next);
    commander.publish(
        static_cast<std::int32_t>(-350000 + k));  // −35 V upwards in 0.1 mV steps: unique per command
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  const std::vector<double> latency_us = device.latency_us();
  const std::vector<double> edges = {50, 100, 200, 300, 500, 1000, 2000, 5000};
  std::printf(
      "VoltageCommand published -> mm3e_driver (TCPROS, separate process) -> CAN frame in the kernel at the "
      "device socket (UDP loopback), %.0f Hz for %.1f s\n",
      rate_hz, seconds);
  std::printf("commands %lld, frames matched %zu, dropped by the queue-1 subscriber %zu\n", total,
              latency_us.size(), device.dropped());
  piezo::bench::print_latency_histogram(latency_us, edges);
  const double p99 = piezo::bench::print_latency_percentiles(latency_us);
  std::printf("target p99 <= 1000 us: %s\n", p99 <= 1000.0 ? "met" : "NOT met");
  return latency_us.empty() ? 1 : 0;
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 10.0, rate_hz = 1000.0;
  if (!piezo::bench::parse_latency_options(argc, argv, seconds, rate_hz)) return 2;
  if (!(seconds > 0) || !(rate_hz > 0) || seconds * rate_hz > 700000) {
    std::fprintf(stderr,
                 "can_ros_command_latency: --seconds and --rate-hz must be > 0 (at most 700000 commands)\n");
    return 2;
  }
  const fs::path self = fs::read_symlink("/proc/self/exe");
  const fs::path driver_bin = self.parent_path().parent_path() / "mm3e_driver";
  if (!fs::exists(driver_bin)) {
    std::fprintf(stderr, "can_ros_command_latency: %s not built\n", driver_bin.c_str());
    return 1;
  }
  const int base = 20000 + static_cast<int>(getpid() % 9000) * 3;
  const std::string log_dir = fs::temp_directory_path() / ("can_ros_latency_" + std::to_string(getpid()));
  fs::create_directories(log_dir);
  const pid_t master_pid =
      piezo::bench::start_private_master("can_ros_command_latency", base, log_dir, argc, argv);
  if (master_pid < 0) return 1;
  const int drv_port = base + 1, dev_port = base + 2;
  const pid_t driver_pid = start_driver(driver_bin, drv_port, dev_port, log_dir);
  MeasuringDevice device(dev_port, drv_port);
  Commander commander(device);
  int rc = 0;
  if (!commander.warm_up()) {
    std::fprintf(stderr, "can_ros_command_latency: the driver never wrote a frame (logs in %s)\n", log_dir.c_str());
    rc = 1;
  } else {
    rc = measure(commander, device, seconds, rate_hz);
  }
  device.stop();
  stop(driver_pid);
  ros::shutdown();
  stop(master_pid);
  fs::remove_all(log_dir);
  return rc;
}
