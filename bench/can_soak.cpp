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

struct Options {
  double minutes = 1.0, window_min = 10.0, rate_hz = 1000.0;
};

// The options, or an exit code (2) after saying what is wrong.
int parse_options(int argc, char** argv, Options* o) {
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string k = argv[i];
    const double v = std::strtod(argv[i + 1], nullptr);
    if (k == "--minutes")
      o->minutes = v;
    else if (k == "--window-minutes")
      o->window_min = v;
    else if (k == "--rate-hz")
      o->rate_hz = v;
    else {
      std::fprintf(stderr, "can_soak: unknown option %s (--minutes M --window-minutes W --rate-hz R)\n", k.c_str());
      return 2;
    }
  }
  if (!(o->minutes > 0) || !(o->window_min > 0) || !(o->rate_hz > 0) || o->rate_hz > 5000) {
    std::fprintf(stderr, "can_soak: --minutes and --window-minutes must be > 0, --rate-hz in (0, 5000]\n");
    return 2;
  }
  return 0;
}

// A controller that applies every set point and reports 12.5 nm/V.
piezo::sim::StepResult echo_plant(const std::array<double, 3>& v, double) {
  piezo::sim::StepResult r;
  for (int i = 0; i < 3; ++i) {
    r.axes[i].voltage_v = v[i];
    r.axes[i].true_position_nm = r.axes[i].measured_position_nm = 12.5 * v[i];
  }
  return r;
}

// The soak's processes (drivers, predictors, the second commander), the simulated controllers on their
// threads, the publishers, and the window of matched command → frame latencies.
class Soak {
 public:
  Soak(const Options& opt, fs::path bin, std::string log_dir, int base)
      : opt_(opt), bin_(std::move(bin)), log_dir_(std::move(log_dir)), base_(base) {}

  // Per manipulator: driver + predictor processes, the simulated controller here.
  void start_manipulator(int k, const std::string& model) {
    const std::string ns = "/soak/mm" + std::to_string(k + 1);
    const int drv_port = base_ + 1 + 2 * k, dev_port = base_ + 2 + 2 * k;
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
    procs_.push_back(spawn({(bin_ / "mm3e_driver").string(), "__name:=mm3e_driver", "__ns:=" + ns},
                           log_dir_ + "/driver" + std::to_string(k + 1) + ".log"));
    proc_names_.push_back("mm" + std::to_string(k + 1) + " driver");
    procs_.push_back(spawn({(bin_ / "piezo_predictor").string(), "__name:=predictor", "__ns:=" + ns},
                           log_dir_ + "/predictor" + std::to_string(k + 1) + ".log"));
    proc_names_.push_back("mm" + std::to_string(k + 1) + " predictor");
    UdpOptions o;
    o.local_port = dev_port;
    o.remote_port = drv_port;
    o.filters = codec_.device_filters();
    device_tx_[k] = make_udp_transport(o);
    device_tx_[k]->open();
    devices_.push_back(std::make_unique<DeviceCore>(DeviceConfig{}, echo_plant));
  }

  void start_devices() {
    for (int k = 0; k < kManipulators; ++k) devthreads_.emplace_back([this, k] { device_loop(k); });
  }

  // The publishers, and the second commander: its own node handle would share this process' connection;
  // publishing on the same topic from a second process is what the driver detects, so it is a rostopic child.
  void start_commanders() {
    for (int k = 0; k < kManipulators; ++k) {
      ros::NodeHandle nh("/soak/mm" + std::to_string(k + 1));
      pubs_[k][0] = nh.advertise<piezo_compensation::VoltageCommand>("a/command", 1);
      pubs_[k][1] = nh.advertise<piezo_compensation::VoltageCommand>("b/command", 1);
      pubs_[k][2] = nh.advertise<piezo_compensation::IntendedMotion>("c/intended", 1);
    }
    procs_.push_back(spawn({"rostopic", "pub", "-r", "10", "/soak/mm1/b/command",
                            "piezo_compensation/VoltageCommand", "{voltage: 1.0}"},
                           log_dir_ + "/second_commander.log"));
    proc_names_.push_back("second commander");
  }

  // Warm-up: every publisher connected, every driver writing frames.
  void wait_connected() {
    bool ready = false;
    for (int i = 0; i < 600 && !ready; ++i) {
      ready = true;
      for (int k = 0; k < kManipulators; ++k)
        for (auto& p : pubs_[k]) ready &= p.getNumSubscribers() > 0;
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    if (!ready)
      std::fprintf(stderr, "can_soak: not every topic connected after 30 s (logs in %s)\n", log_dir_.c_str());
  }

  // The command loop with a report per window; returns the exit code (1 when a process died).
  int run();
  void shutdown(pid_t master_pid, int rc) {
    done_ = true;
    for (auto& th : devthreads_) th.join();
    for (pid_t pid : procs_) stop(pid);
    ros::shutdown();
    stop(master_pid);
    if (rc == 0) fs::remove_all(log_dir_);
  }

 private:
  static std::int64_t key(int k, int axis, std::int32_t counts) {
    return (static_cast<std::int64_t>(k * 3 + axis) << 32) | static_cast<std::uint32_t>(counts);
  }
  void device_loop(int k);
  void match_frame(int k, const ReceivedFrame& rf, const CommandFrame& c);
  void ramp_in();
  void publish_commands(long long n, double t);
  Window take_window(double t);
  // Prints the window's line; false when a process died.
  bool report_window(Window& w, std::chrono::steady_clock::time_point t_start);
  void print_summary(std::chrono::steady_clock::time_point t_start) const;

  const Options opt_;
  const fs::path bin_;
  const std::string log_dir_;
  const int base_;
  const Codec codec_{ProtocolConfig{}};
  std::vector<pid_t> procs_;
  std::vector<std::string> proc_names_;
  std::array<std::unique_ptr<Transport>, kManipulators> device_tx_;
  std::vector<std::unique_ptr<DeviceCore>> devices_;
  std::vector<std::thread> devthreads_;
  std::vector<std::array<ros::Publisher, 3>> pubs_ =
      std::vector<std::array<ros::Publisher, 3>>(kManipulators);
  std::mutex m_;
  std::unordered_map<std::int64_t, double> sent_at_;  // (manipulator, axis, counts) → publish wall time
  Window win_;
  std::atomic<bool> done_{false}, measuring_{false};
  std::array<std::atomic<std::uint64_t>, kManipulators> frames_seen_{};
  std::vector<double> rss0_, p99s_;
};

void Soak::device_loop(int k) {
  std::vector<ReceivedFrame> in;
  DeviceCore& dev = *devices_[k];
  auto next = std::chrono::steady_clock::now();
  while (!done_) {
    if (std::chrono::steady_clock::now() >= next) {
      for (const auto& f : dev.step().frames) device_tx_[k]->send(f);
      next += std::chrono::microseconds(static_cast<long long>(1e6 * dev.period_s()));
    }
    in.clear();
    device_tx_[k]->receive(in, 5);
    for (const auto& rf : in) {
      const DecodeResult r = codec_.decode(rf.frame);
      const auto* c = r.ok() ? std::get_if<CommandFrame>(&r.message_value) : nullptr;
      dev.handle(rf.frame);
      if (c) match_frame(k, rf, *c);
    }
    // Run under SCHED_FIFO (docs/driver.md, Soak), two busy controller threads would otherwise keep the
    // main thread off both cores once it stops sleeping between commands.
    std::this_thread::yield();
  }
}

void Soak::match_frame(int k, const ReceivedFrame& rf, const CommandFrame& c) {
  ++frames_seen_[k];
  std::lock_guard<std::mutex> l(m_);
  if (!measuring_) return;
  if (c.axis == 2) {
    ++win_.c_frames;
    return;
  }
  auto it = sent_at_.find(key(k, c.axis, static_cast<std::int32_t>(std::lround(c.voltage_v / 1e-4))));
  if (it == sent_at_.end()) return;
  const double us = (rf.receive_time_s - it->second) * 1e6;
  win_.latency_us.push_back(us);
  win_.late += us > 10000.0;
  sent_at_.erase(it);
}

// Ramps every axis to its first value (slew + confirmation), then measures.
void Soak::ramp_in() {
  for (int rep = 0; rep < 2000; ++rep) {
    for (int k = 0; k < kManipulators; ++k)
      for (int a = 0; a < 2; ++a) {
        piezo_compensation::VoltageCommand c;
        c.header.stamp = ros::Time(wall_s());
        c.voltage = triangle(0, a == 0 ? -30000 : 30000) * 1e-4;
        pubs_[k][a].publish(c);
      }
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  for (pid_t pid : procs_) rss0_.push_back(rss_mb(pid));
  measuring_ = true;
}

void Soak::publish_commands(long long n, double t) {
  for (int k = 0; k < kManipulators; ++k) {
    for (int a = 0; a < 2; ++a) {
      const std::int32_t counts = triangle(n + 1, a == 0 ? -30000 : 30000);
      piezo_compensation::VoltageCommand c;
      c.header.stamp = ros::Time(t);
      c.voltage = counts * 1e-4;
      {
        std::lock_guard<std::mutex> l(m_);
        if (!(k == 0 && a == 1)) sent_at_[key(k, a, counts)] = t;  // mm1/b is held: nothing to match
        ++win_.commands;
      }
      pubs_[k][a].publish(c);
    }
    piezo_compensation::IntendedMotion im;
    im.header.stamp = ros::Time(t);
    im.mode = piezo_compensation::IntendedMotion::VOLTAGE;
    im.voltage = 5.0 * std::sin(2 * M_PI * 0.05 * n / opt_.rate_hz);
    pubs_[k][2].publish(im);
  }
}

// The window so far, a new one started; commands older than 1 s with no frame count as dropped (superseded in
// the queue or lost).
Window Soak::take_window(double t) {
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  Window w;
  std::lock_guard<std::mutex> l(m_);
  for (auto it = sent_at_.begin(); it != sent_at_.end();) {
    if (t - it->second > 1.0) {
      ++win_.dropped;
      it = sent_at_.erase(it);
    } else {
      ++it;
    }
  }
  std::swap(w, win_);
  return w;
}

bool Soak::report_window(Window& w, std::chrono::steady_clock::time_point t_start) {
  std::sort(w.latency_us.begin(), w.latency_us.end());
  auto pct = [&](double q) {
    return w.latency_us.empty() ? std::nan("")
                                : w.latency_us[std::min(w.latency_us.size() - 1,
                                                        static_cast<std::size_t>(q * w.latency_us.size()))];
  };
  const double elapsed =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count() / 60.0;
  std::printf("%8.1f %9llu %9.1f %9.1f %9.1f %8llu %8llu %9llu ", elapsed,
              static_cast<unsigned long long>(w.commands), pct(0.5), pct(0.99),
              w.latency_us.empty() ? std::nan("") : w.latency_us.back(),
              static_cast<unsigned long long>(w.dropped), static_cast<unsigned long long>(w.late),
              static_cast<unsigned long long>(w.c_frames));
  for (std::size_t i = 0; i + 1 < procs_.size(); ++i) std::printf(" %.1f", rss_mb(procs_[i]));
  std::printf("\n");
  std::fflush(stdout);
  p99s_.push_back(pct(0.99));
  bool all_alive = true;
  for (std::size_t i = 0; i + 1 < procs_.size(); ++i)
    if (!alive(procs_[i])) {
      std::printf("soak: %s died (log in %s)\n", proc_names_[i].c_str(), log_dir_.c_str());
      all_alive = false;
    }
  return all_alive;
}

void Soak::print_summary(std::chrono::steady_clock::time_point t_start) const {
  const double hours =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count() / 3600.0;
  std::printf("RSS growth over %.2f h (after warm-up):", hours);
  for (std::size_t i = 0; i + 1 < procs_.size(); ++i)
    std::printf(" %s %+.2f MB (%+.2f MB/h);", proc_names_[i].c_str(), rss_mb(procs_[i]) - rss0_[i],
                (rss_mb(procs_[i]) - rss0_[i]) / std::max(hours, 1e-9));
  std::printf("\n");
  if (!p99s_.empty())
    std::printf("p99 per window: first %.1f us, last %.1f us, largest %.1f us\n", p99s_.front(), p99s_.back(),
                *std::max_element(p99s_.begin(), p99s_.end()));
}

int Soak::run() {
  const auto period = std::chrono::nanoseconds(static_cast<long long>(1e9 / opt_.rate_hz));
  const long long total = static_cast<long long>(opt_.minutes * 60.0 * opt_.rate_hz);
  const long long per_window = std::max(1LL, static_cast<long long>(opt_.window_min * 60.0 * opt_.rate_hz));
  std::printf(
      "soak: %d manipulators (mm3e_driver + piezo_predictor processes each), %.0f Hz on a, b "
      "(VoltageCommand) "
      "and c (IntendedMotion via the predictor), second commander on mm1/b, %.1f min, windows of %.1f min\n",
      kManipulators, opt_.rate_hz, opt_.minutes, opt_.window_min);
  std::printf("%8s %9s %9s %9s %9s %8s %8s %9s  RSS [MB] per process\n", "t [min]", "commands", "p50 [us]",
              "p99 [us]", "max [us]", "dropped", "late", "c frames");
  int rc = 0;
  auto next = std::chrono::steady_clock::now();
  const auto t_start = next;
  for (long long n = 0; n < total; ++n) {
    if (n == 0) {
      ramp_in();
      next = std::chrono::steady_clock::now();
    }
    next += period;
    std::this_thread::sleep_until(next);
    const double t = wall_s();
    publish_commands(n, t);
    if ((n + 1) % per_window == 0 || n + 1 == total) {
      Window w = take_window(t);
      if (!report_window(w, t_start)) rc = 1;
      if (rc) break;
    }
  }
  print_summary(t_start);
  return rc;
}

}  // namespace

int main(int argc, char** argv) {
  Options opt;
  if (const int rc = parse_options(argc, argv, &opt)) return rc;
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

  Soak soak(opt, bin, log_dir, base);
  for (int k = 0; k < kManipulators; ++k) soak.start_manipulator(k, model);
  soak.start_devices();
  soak.start_commanders();
  soak.wait_connected();
  const int rc = soak.run();
  soak.shutdown(master_pid, rc);
  return rc;
}
