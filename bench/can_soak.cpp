// Soak test of the command path (`scripts/piezo bench --soak MINUTES`): three simulated manipulators, each a
// real mm3e_driver process and a real piezo_predictor process (axis c) under their own rosmaster, the
// controllers simulated in this process (can::DeviceCore over UDP loopback, 11 Hz reports echoing the set
// points). Axes a and b get VoltageCommand at --rate-hz (1 kHz) each, axis c gets IntendedMotion at the same
// rate through the predictor, and a second commander on mm1/b/command is refused (the driver holds that axis).
// Per window (--window-minutes, 10) it prints command → frame latency p50/p99/max (axes a, b: publish time to
// the kernel receive stamp of the matching frame at the device socket; frames matched by voltage, every
// command a distinct 0.1 mV step), commands without a frame (dropped: superseded in the queue-1 subscriber or
// lost) and frames later than 10 ms, frames on axis c, and the RSS of every driver and predictor process.
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
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <unordered_map>
#include <vector>

#include "child_process.h"
#include "latency_histogram.h"
#include "piezo_compensation/IntendedMotion.h"
#include "piezo_compensation/VoltageCommand.h"
#include "piezo_compensation/can/device_core.h"
#include "piezo_compensation/can/transport.h"

using namespace piezo::can;
namespace fs = std::filesystem;
using piezo::bench::spawn;
using piezo::bench::stop;
using piezo::bench::wall_s;

namespace {

constexpr int kManipulators = 3;


double rss_mb(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("VmRSS:", 0) == 0) return std::strtod(line.c_str() + 6, nullptr) / 1024.0;
  return std::nan("");
}

bool alive(pid_t pid) { return waitpid(pid, nullptr, WNOHANG) == 0; }

// A triangle in 0.1 mV counts: every command differs from the one before, no jumps.
std::int32_t triangle(long long k, std::int32_t base) {
  const long long period = 200000;
  const long long p = k % period;
  return base + static_cast<std::int32_t>(p < period / 2 ? p : period - p);
}

struct Window {
  std::vector<double> latency_us;
  std::uint64_t dropped = 0, late = 0, c_frames = 0, commands = 0;
};

}  // namespace

int main(int argc, char** argv) {
  double minutes = 1.0, window_min = 10.0, rate_hz = 1000.0;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string k = argv[i];
    const double v = std::strtod(argv[i + 1], nullptr);
    if (k == "--minutes") minutes = v;
    else if (k == "--window-minutes") window_min = v;
    else if (k == "--rate-hz") rate_hz = v;
    else {
      std::fprintf(stderr, "can_soak: unknown option %s (--minutes M --window-minutes W --rate-hz R)\n", k.c_str());
      return 2;
    }
  }
  if (!(minutes > 0) || !(window_min > 0) || !(rate_hz > 0) || rate_hz > 5000) {
    std::fprintf(stderr, "can_soak: --minutes and --window-minutes must be > 0, --rate-hz in (0, 5000]\n");
    return 2;
  }
  const fs::path self = fs::read_symlink("/proc/self/exe");
  const fs::path bin = self.parent_path().parent_path();
  for (const char* b : {"mm3e_driver", "piezo_predictor"})
    if (!fs::exists(bin / b)) {
      std::fprintf(stderr, "can_soak: %s not built\n", (bin / b).c_str());
      return 1;
    }
  const std::string model = std::string(PIEZO_SOURCE_DIR) + "/test/rostest/pi_creep_model_c.yaml";
  const int base = 21000 + static_cast<int>(getpid() % 4000) * 8;
  const std::string log_dir = fs::temp_directory_path() / ("can_soak_" + std::to_string(getpid()));
  fs::create_directories(log_dir);
  const pid_t master_pid = piezo::bench::start_private_master("can_soak", base, log_dir, argc, argv);
  if (master_pid < 0) return 1;

  // Per manipulator: driver + predictor processes, the simulated controller here.
  const Codec codec{ProtocolConfig{}};
  std::vector<pid_t> procs;
  std::vector<std::string> proc_names;
  std::array<std::unique_ptr<Transport>, kManipulators> device_tx;
  std::vector<std::unique_ptr<DeviceCore>> devices;
  for (int k = 0; k < kManipulators; ++k) {
    const std::string ns = "/soak/mm" + std::to_string(k + 1);
    const int drv_port = base + 1 + 2 * k, dev_port = base + 2 + 2 * k;
    ros::NodeHandle d(ns + "/mm3e_driver");
    d.setParam("transport", "udp");
    d.setParam("udp_local_port", drv_port);
    d.setParam("udp_remote_port", dev_port);
    d.setParam("slew_rate_v_per_s", 2000.0);  // every 0.1 mV command one frame
    d.setParam("command_timeout_s", 1.0);
    ros::NodeHandle p(ns + "/predictor");
    p.setParam("model_file", model);
    XmlRpc::XmlRpcValue axes;
    axes[0] = "c";
    p.setParam("axes", axes);
    p.setParam("tf_period_s", 0.0);
    procs.push_back(spawn({(bin / "mm3e_driver").string(), "__name:=mm3e_driver", "__ns:=" + ns},
                          log_dir + "/driver" + std::to_string(k + 1) + ".log"));
    proc_names.push_back("mm" + std::to_string(k + 1) + " driver");
    procs.push_back(spawn({(bin / "piezo_predictor").string(), "__name:=predictor", "__ns:=" + ns},
                          log_dir + "/predictor" + std::to_string(k + 1) + ".log"));
    proc_names.push_back("mm" + std::to_string(k + 1) + " predictor");
    UdpOptions o;
    o.local_port = dev_port;
    o.remote_port = drv_port;
    o.filters = codec.device_filters();
    device_tx[k] = make_udp_transport(o);
    device_tx[k]->open();
    devices.push_back(std::make_unique<DeviceCore>(DeviceConfig{}, [](const std::array<double, 3>& v, double) {
      piezo::sim::StepResult r;
      for (int i = 0; i < 3; ++i) {
        r.axes[i].voltage_v = v[i];
        r.axes[i].true_position_nm = r.axes[i].measured_position_nm = 12.5 * v[i];
      }
      return r;
    }));
  }

  std::mutex m;
  // (manipulator, axis, counts) → publish wall time
  std::unordered_map<std::int64_t, double> sent_at;
  auto key = [](int k, int axis, std::int32_t counts) {
    return (static_cast<std::int64_t>(k * 3 + axis) << 32) | static_cast<std::uint32_t>(counts);
  };
  Window win;
  std::atomic<bool> done{false}, measuring{false};
  std::array<std::atomic<std::uint64_t>, kManipulators> frames_seen{};
  std::vector<std::thread> devthreads;
  for (int k = 0; k < kManipulators; ++k)
    devthreads.emplace_back([&, k] {
      std::vector<ReceivedFrame> in;
      DeviceCore& dev = *devices[k];
      auto next = std::chrono::steady_clock::now();
      while (!done) {
        if (std::chrono::steady_clock::now() >= next) {
          for (const auto& f : dev.step().frames) device_tx[k]->send(f);
          next += std::chrono::microseconds(static_cast<long long>(1e6 * dev.period_s()));
        }
        in.clear();
        device_tx[k]->receive(in, 5);
        for (const auto& rf : in) {
          const DecodeResult r = codec.decode(rf.frame);
          const auto* c = r.ok() ? std::get_if<CommandFrame>(&r.message_value) : nullptr;
          dev.handle(rf.frame);
          if (!c) continue;
          ++frames_seen[k];
          std::lock_guard<std::mutex> l(m);
          if (!measuring) continue;
          if (c->axis == 2) {
            ++win.c_frames;
            continue;
          }
          auto it = sent_at.find(key(k, c->axis, static_cast<std::int32_t>(std::lround(c->voltage_v / 1e-4))));
          if (it == sent_at.end()) continue;
          const double us = (rf.receive_time_s - it->second) * 1e6;
          win.latency_us.push_back(us);
          win.late += us > 10000.0;
          sent_at.erase(it);
        }
        // Run under SCHED_FIFO (docs/driver.md, Soak), two busy controller threads would otherwise keep the
        // main thread off both cores once it stops sleeping between commands.
        std::this_thread::yield();
      }
    });

  std::vector<std::array<ros::Publisher, 3>> pubs(kManipulators);
  for (int k = 0; k < kManipulators; ++k) {
    ros::NodeHandle nh("/soak/mm" + std::to_string(k + 1));
    pubs[k][0] = nh.advertise<piezo_compensation::VoltageCommand>("a/command", 1);
    pubs[k][1] = nh.advertise<piezo_compensation::VoltageCommand>("b/command", 1);
    pubs[k][2] = nh.advertise<piezo_compensation::IntendedMotion>("c/intended", 1);
  }
  // The second commander: its own node handle would share this process' connection; publishing on the same
  // topic from a second process is what the driver detects, so it is a rostopic child.
  const pid_t second = spawn({"rostopic", "pub", "-r", "10", "/soak/mm1/b/command", "piezo_compensation/VoltageCommand",
                              "{voltage: 1.0}"},
                             log_dir + "/second_commander.log");
  procs.push_back(second);
  proc_names.push_back("second commander");

  // Warm-up: every publisher connected, every driver writing frames.
  bool ready = false;
  for (int i = 0; i < 600 && !ready; ++i) {
    ready = true;
    for (int k = 0; k < kManipulators; ++k)
      for (auto& p : pubs[k]) ready &= p.getNumSubscribers() > 0;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  if (!ready) std::fprintf(stderr, "can_soak: not every topic connected after 30 s (logs in %s)\n", log_dir.c_str());

  const auto period = std::chrono::nanoseconds(static_cast<long long>(1e9 / rate_hz));
  const long long total = static_cast<long long>(minutes * 60.0 * rate_hz);
  const long long per_window = std::max(1LL, static_cast<long long>(window_min * 60.0 * rate_hz));
  std::vector<double> rss0;
  std::printf("soak: %d manipulators (mm3e_driver + piezo_predictor processes each), %.0f Hz on a, b (VoltageCommand) "
              "and c (IntendedMotion via the predictor), second commander on mm1/b, %.1f min, windows of %.1f min\n",
              kManipulators, rate_hz, minutes, window_min);
  std::printf("%8s %9s %9s %9s %9s %8s %8s %9s  RSS [MB] per process\n", "t [min]", "commands", "p50 [us]",
              "p99 [us]", "max [us]", "dropped", "late", "c frames");
  std::vector<double> p99s;
  int rc = 0;
  auto next = std::chrono::steady_clock::now();
  const auto t_start = next;
  for (long long n = 0; n < total; ++n) {
    if (n == 0) {
      // ramp every axis to its first value (slew + confirmation), then measure
      for (int rep = 0; rep < 2000; ++rep) {
        for (int k = 0; k < kManipulators; ++k)
          for (int a = 0; a < 2; ++a) {
            piezo_compensation::VoltageCommand c;
            c.header.stamp = ros::Time(wall_s());
            c.voltage = triangle(0, a == 0 ? -30000 : 30000) * 1e-4;
            pubs[k][a].publish(c);
          }
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
      }
      for (pid_t pid : procs) rss0.push_back(rss_mb(pid));
      next = std::chrono::steady_clock::now();
      measuring = true;
    }
    next += period;
    std::this_thread::sleep_until(next);
    const double t = wall_s();
    for (int k = 0; k < kManipulators; ++k) {
      for (int a = 0; a < 2; ++a) {
        const std::int32_t counts = triangle(n + 1, a == 0 ? -30000 : 30000);
        piezo_compensation::VoltageCommand c;
        c.header.stamp = ros::Time(t);
        c.voltage = counts * 1e-4;
        {
          std::lock_guard<std::mutex> l(m);
          if (!(k == 0 && a == 1)) sent_at[key(k, a, counts)] = t;  // mm1/b is held: nothing to match
          ++win.commands;
        }
        pubs[k][a].publish(c);
      }
      piezo_compensation::IntendedMotion im;
      im.header.stamp = ros::Time(t);
      im.mode = piezo_compensation::IntendedMotion::VOLTAGE;
      im.voltage = 5.0 * std::sin(2 * M_PI * 0.05 * n / rate_hz);
      pubs[k][2].publish(im);
    }
    if ((n + 1) % per_window == 0 || n + 1 == total) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
      Window w;
      {
        std::lock_guard<std::mutex> l(m);
        // commands older than 1 s with no frame: superseded in the queue or lost
        for (auto it = sent_at.begin(); it != sent_at.end();) {
          if (t - it->second > 1.0) {
            ++win.dropped;
            it = sent_at.erase(it);
          } else {
            ++it;
          }
        }
        std::swap(w, win);
      }
      std::sort(w.latency_us.begin(), w.latency_us.end());
      auto pct = [&](double q) {
        return w.latency_us.empty() ? std::nan("") : w.latency_us[std::min(w.latency_us.size() - 1,
                                                                            static_cast<std::size_t>(q * w.latency_us.size()))];
      };
      const double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count() / 60.0;
      std::printf("%8.1f %9llu %9.1f %9.1f %9.1f %8llu %8llu %9llu ", elapsed,
                  static_cast<unsigned long long>(w.commands), pct(0.5), pct(0.99),
                  w.latency_us.empty() ? std::nan("") : w.latency_us.back(),
                  static_cast<unsigned long long>(w.dropped), static_cast<unsigned long long>(w.late),
                  static_cast<unsigned long long>(w.c_frames));
      for (std::size_t i = 0; i + 1 < procs.size(); ++i) std::printf(" %.1f", rss_mb(procs[i]));
      std::printf("\n");
      std::fflush(stdout);
      p99s.push_back(pct(0.99));
      for (std::size_t i = 0; i + 1 < procs.size(); ++i)
        if (!alive(procs[i])) {
          std::printf("soak: %s died (log in %s)\n", proc_names[i].c_str(), log_dir.c_str());
          rc = 1;
        }
      if (rc) break;
    }
  }
  const double hours = std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count() / 3600.0;
  std::printf("RSS growth over %.2f h (after warm-up):", hours);
  for (std::size_t i = 0; i + 1 < procs.size(); ++i)
    std::printf(" %s %+.2f MB (%+.2f MB/h);", proc_names[i].c_str(), rss_mb(procs[i]) - rss0[i],
                (rss_mb(procs[i]) - rss0[i]) / std::max(hours, 1e-9));
  std::printf("\n");
  if (!p99s.empty())
    std::printf("p99 per window: first %.1f us, last %.1f us, largest %.1f us\n", p99s.front(), p99s.back(),
                *std::max_element(p99s.begin(), p99s.end()));
  done = true;
  for (auto& th : devthreads) th.join();
  for (pid_t pid : procs) stop(pid);
  ros::shutdown();
  stop(master_pid);
  if (rc == 0) fs::remove_all(log_dir);
  return rc;
}
