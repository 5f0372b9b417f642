// The NanoControl fault state machine, the simulated device's commands and faults, and the whole serial path
// with no ROS: can::DriverCore over the NanoControl transport over a pseudo-terminal, the simulated device
// answering on the other side (as mm3e_sim does).
#include <gtest/gtest.h>
#include <poll.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <mutex>
#include <thread>
#include <vector>

#include "piezo_compensation/can/driver_core.h"
#include "piezo_compensation/nanocontrol/link_state.h"
#include "piezo_compensation/nanocontrol/pseudo_terminal.h"
#include "piezo_compensation/nanocontrol/sim_device.h"
#include "piezo_compensation/nanocontrol/transport.h"

using namespace piezo;
using namespace piezo::nanocontrol;

TEST(NanoControlLinkState, EachOutcomeCountsAndNamesItself) {
  LinkState s;
  EXPECT_TRUE(s.needs_drain());  // before the first command after an open
  s.drained();
  EXPECT_TRUE(s.record(classify("fine16 C 12", std::string("o\t")), 0.2));
  EXPECT_FALSE(s.record(classify("fine16 C 40000", std::string("e\tvalue out of range")), 0.2));
  EXPECT_EQ(s.counters().refused, 1u);
  EXPECT_EQ(s.counters().last_refusal, "`fine16 C 40000`: value out of range");
  EXPECT_TRUE(s.set_point_allowed());
  EXPECT_FALSE(s.needs_drain());  // an e reply is a whole reply: nothing stray follows
  EXPECT_FALSE(s.record(classify("counterread", std::nullopt), 0.2));
  EXPECT_EQ(s.counters().timeouts, 1u);
  EXPECT_EQ(s.counters().last_timeout, "`counterread`: no reply within 0.2 s");
  EXPECT_TRUE(s.needs_drain());
  s.drained();
  EXPECT_FALSE(s.record(classify("fine16 ?", std::string("o#1 2")), 0.2));
  EXPECT_EQ(s.counters().garbled, 1u);
  EXPECT_NE(s.counters().last_garbled.find("no tab after the status"), std::string::npos) << s.counters().last_garbled;
  EXPECT_TRUE(s.needs_drain());
  EXPECT_FALSE(s.record(classify("fine16 B 5", std::string("i\tPiezo Voltage Breakdown")), 0.2));
  EXPECT_TRUE(s.counters().breakdown);
  EXPECT_FALSE(s.set_point_allowed());
  EXPECT_EQ(s.counters().last_info, "`fine16 B 5`: Piezo Voltage Breakdown");
  EXPECT_TRUE(s.record(classify("counterread", std::string("o\t1 2 3 4")), 0.2));
  EXPECT_FALSE(s.set_point_allowed()) << "an ok reply does not clear the breakdown latch";
  s.reset();
  EXPECT_TRUE(s.set_point_allowed());
  EXPECT_EQ(s.counters().breakdowns, 1u) << "counters survive a reopen";
  EXPECT_EQ(s.counters().exchanges, 6u);
  EXPECT_EQ(s.counters().ok, 2u);
}

namespace {
sim::StepResult flat_plant(const std::array<double, 3>& v, double dt, double& t) {
  t += dt;
  sim::StepResult r;
  r.time_s = t;
  for (int i = 0; i < 3; ++i) {
    r.axes[i].voltage_v = v[i];
    r.axes[i].true_position_nm = 10.0 * v[i];
    r.axes[i].measured_position_nm = 20.0 * std::round(10.0 * v[i] / 20.0);
  }
  return r;
}
}  // namespace

TEST(NanoControlSimDevice, CommandsAndInjectedFaults) {
  double t = 0;
  SimDevice d({}, [&t](const std::array<double, 3>& v, double dt) { return flat_plant(v, dt, t); });
  EXPECT_EQ(d.handle("version", 0.0).bytes.substr(0, 2), "o\t");
  auto set = d.handle("fine16 C 4096", 0.1);  // 10 V
  EXPECT_EQ(set.bytes, "o\t\r");
  EXPECT_TRUE(set.set_point);
  EXPECT_EQ(set.axis, 2);
  EXPECT_DOUBLE_EQ(set.voltage_v, 10.0);
  EXPECT_EQ(d.handle("fine16 ?", 0.2).bytes, "o\t0 0 4096 0\r");
  EXPECT_EQ(d.handle("fine16 C ?", 0.2).bytes, "o\t4096\r");
  // 100 nm at 10 V, -20 nm per count on c
  EXPECT_EQ(d.handle("counterread", 0.3).bytes, "o\t0 0 -5 0\r");
  EXPECT_EQ(d.handle("fine16 C 40000", 0.3).bytes.substr(0, 2), "e\t");
  EXPECT_EQ(d.handle("fine16 X 1", 0.3).bytes.substr(0, 2), "e\t");
  EXPECT_EQ(d.handle("bogus", 0.3).bytes.substr(0, 2), "e\t");
  d.inject(SimFault::kErrorReply);
  EXPECT_EQ(d.handle("counterread", 0.4).bytes.substr(0, 2), "o\t") << "the e fault waits for a set point";
  auto refused = d.handle("fine16 C 0", 0.4);
  EXPECT_EQ(refused.bytes.substr(0, 2), "e\t");
  EXPECT_FALSE(refused.set_point);
  EXPECT_DOUBLE_EQ(d.voltages_v()[2], 10.0) << "a refused set point is not applied";
  d.inject(SimFault::kBreakdown);
  EXPECT_EQ(d.handle("fine16 C 0", 0.5).bytes, "i\tPiezo Voltage Breakdown\r");
  EXPECT_DOUBLE_EQ(d.voltages_v()[2], 10.0);
  d.inject(SimFault::kLostReply);
  auto lost = d.handle("fine16 C 0", 0.6);
  EXPECT_EQ(lost.bytes, "");
  EXPECT_TRUE(lost.set_point) << "a lost reply's command was carried out";
  d.inject(SimFault::kPartial);
  const std::string partial = d.handle("counterread", 0.7).bytes;
  EXPECT_FALSE(partial.empty());
  EXPECT_EQ(partial.find('\r'), std::string::npos);
  d.inject(SimFault::kGarbled);
  const std::string garbled = d.handle("counterread", 0.8).bytes;
  EXPECT_EQ(garbled.back(), '\r');
  EXPECT_FALSE(parse_reply(garbled.substr(0, garbled.size() - 1)));
  EXPECT_EQ(d.handle("counterreset", 0.9).bytes, "o\t\r");
  d.handle("fine16 C 8192", 1.0);
  EXPECT_EQ(d.handle("counterread", 1.1).bytes, "o\t0 0 -10 0\r") << "counts from the reset";
}

namespace {

// The simulated device on a pseudo-terminal, answered on a thread (mm3e_sim's loop in small).
class PtyDevice {
 public:
  explicit PtyDevice(const std::string& link)
      : pty_(link), device_({}, [this](const std::array<double, 3>& v, double dt) { return flat_plant(v, dt, t_); }) {
    thread_ = std::thread([this] { run(); });
  }
  ~PtyDevice() {
    running_ = false;
    thread_.join();
  }
  void inject(SimFault f) {
    std::lock_guard<std::mutex> l(m_);
    device_.inject(f);
  }
  void vanish() {
    std::lock_guard<std::mutex> l(m_);
    pty_.vanish();
  }
  void reappear() {
    std::lock_guard<std::mutex> l(m_);
    pty_.reappear();
  }
  double voltage_c() {
    std::lock_guard<std::mutex> l(m_);
    return device_.voltages_v()[2];
  }
  void set_c_directly(int counts) {  // the controller's own knob moved the axis while the driver was away
    std::lock_guard<std::mutex> l(m_);
    device_.handle("fine16 C " + std::to_string(counts), now());
  }
  std::vector<double> set_points_c() {
    std::lock_guard<std::mutex> l(m_);
    return set_points_;
  }

 private:
  static double now() {
    return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
  }
  void run() {
    while (running_) {
      int fd;
      {
        std::lock_guard<std::mutex> l(m_);
        fd = pty_.present() ? pty_.master_fd() : -1;
      }
      if (fd < 0) {
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
        continue;
      }
      pollfd p{fd, POLLIN, 0};
      if (poll(&p, 1, 10) <= 0 || !(p.revents & POLLIN)) continue;
      char buf[256];
      std::lock_guard<std::mutex> l(m_);
      if (!pty_.present()) continue;
      const ssize_t n = ::read(pty_.master_fd(), buf, sizeof buf);
      if (n <= 0) continue;
      lines_.append(buf, static_cast<std::size_t>(n));
      while (auto line = lines_.next_line()) {
        const SimDevice::Answer a = device_.handle(*line, now());
        if (a.set_point && a.axis == 2) set_points_.push_back(a.voltage_v);
        if (!a.bytes.empty() && ::write(pty_.master_fd(), a.bytes.data(), a.bytes.size()) < 0) break;
      }
    }
  }
  std::mutex m_;
  PseudoTerminal pty_;
  double t_ = 0;
  SimDevice device_;
  LineBuffer lines_;
  std::vector<double> set_points_;
  std::atomic<bool> running_{true};
  std::thread thread_;
};

double now_s() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

template <typename Pred>
bool wait_for(Pred p, double seconds) {
  const double end = now_s() + seconds;
  while (now_s() < end) {
    if (p()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return p();
}

struct Rig {
  explicit Rig(const std::string& name)
      : link("/tmp/piezo_nc_test_" + name + "_" + std::to_string(getpid())), device(link) {
    LinkOptions o;
    o.port = link;
    o.reply_timeout_s = 0.1;
    o.min_sample_period_s = 0.02;
    o.min_voltage_v = -20.0;
    o.max_voltage_v = 20.0;
    can::DriverConfig c;
    c.protocol = frame_protocol();
    c.limits.min_voltage_v = -20.0;
    c.limits.max_voltage_v = 20.0;
    c.limits.slew_rate_v_per_s = 100.0;
    c.limits.command_timeout_s = 3600.0;
    c.silence_reconnect_s = 1.0;
    c.reconnect_min_s = 0.05;
    c.reconnect_max_s = 0.2;
    can::DriverCallbacks cb;
    cb.on_encoder = [this](const can::EncoderReport& e, std::uint32_t, double t) {
      std::lock_guard<std::mutex> l(m);
      if (e.axis == 2) {
        encoder_c.push_back(e.position_m);
        stamps.push_back(t);
      }
    };
    monitor = std::make_shared<LinkMonitor>();
    core = std::make_unique<can::DriverCore>(c, [o, this] { return make_transport(o, monitor); }, cb);
    core->start();
  }
  ~Rig() { core->stop(); }
  std::size_t encoders() {
    std::lock_guard<std::mutex> l(m);
    return encoder_c.size();
  }
  // Commands v on c (ticking the ramp) until the device holds it, or seconds pass.
  bool drive_c(double v, double seconds = 5.0) {
    return wait_for([&] {
      core->command(2, v, now_s());
      core->tick(now_s());
      return std::abs(device.voltage_c() - v) < 0.01 && std::abs(core->axis_status(2).reported_v - v) < 0.01;
    }, seconds);
  }
  std::string link;
  PtyDevice device;
  std::shared_ptr<LinkMonitor> monitor;
  std::unique_ptr<can::DriverCore> core;
  std::mutex m;
  std::vector<double> encoder_c, stamps;
};

}  // namespace

TEST(NanoControlPath, SamplesDriveAndReadBack) {
  Rig rig("samples");
  ASSERT_TRUE(wait_for([&] { return rig.core->axis_status(2).has_baseline && rig.encoders() >= 3; }, 10.0));
  EXPECT_FALSE(rig.monitor->snapshot().version.empty());
  ASSERT_TRUE(rig.drive_c(12.5));
  const std::size_t n = rig.encoders();
  ASSERT_TRUE(wait_for([&] { return rig.encoders() >= n + 3; }, 5.0));
  {
    std::lock_guard<std::mutex> l(rig.m);
    // 125 nm → 120 nm quantised → 6 counts of -20 nm: -6 × -20 nm = 120 nm
    EXPECT_NEAR(rig.encoder_c.back(), 120e-9, 1e-12);
    for (std::size_t i = 1; i < rig.stamps.size(); ++i) EXPECT_GE(rig.stamps[i], rig.stamps[i - 1]);
  }
  const auto snap = rig.monitor->snapshot();
  EXPECT_GE(snap.counters.samples, 3u);
  EXPECT_DOUBLE_EQ(snap.sigma_m[2], 0.0);  // the flat plant reads the same count every time
  EXPECT_GE(snap.sample_period_s, 0.02);
  for (double v : rig.device.set_points_c()) {
    EXPECT_LE(v, 20.0);
    EXPECT_GE(v, -20.0);
  }
  // beyond the limits: clamped, never sent beyond
  ASSERT_TRUE(rig.drive_c(20.0, 5.0));
  rig.core->command(2, 35.0, now_s());
  rig.core->tick(now_s() + 0.2);
  for (double v : rig.device.set_points_c()) EXPECT_LE(v, 20.0);
}

TEST(NanoControlPath, ErrorReplyIsRefusedAndTheAxisWaitsForTheReadBack) {
  Rig rig("error");
  ASSERT_TRUE(wait_for([&] { return rig.core->axis_status(2).has_baseline; }, 10.0));
  ASSERT_TRUE(rig.drive_c(1.0));
  rig.device.inject(SimFault::kErrorReply);
  const std::size_t before = rig.device.set_points_c().size();
  rig.core->command(2, 1.5, now_s());
  const auto st = rig.core->axis_status(2);
  EXPECT_EQ(st.frames_refused, 1u);
  EXPECT_NEAR(rig.device.voltage_c(), 1.0, 0.0025);  // 1 V is 409.6 counts: 410 went out
  EXPECT_EQ(rig.monitor->snapshot().counters.refused, 1u);
  EXPECT_NE(rig.monitor->snapshot().counters.last_refusal.find("fine16 C"), std::string::npos);
  // no second attempt until the read-back came
  rig.core->tick(now_s() + 0.001);
  EXPECT_EQ(rig.device.set_points_c().size(), before);
  ASSERT_TRUE(rig.drive_c(1.5));
}

TEST(NanoControlPath, LostAndGarbledRepliesTimeOutAndRecover) {
  Rig rig("timeout");
  ASSERT_TRUE(wait_for([&] { return rig.core->axis_status(2).has_baseline; }, 10.0));
  ASSERT_TRUE(rig.drive_c(2.0));
  rig.device.inject(SimFault::kLostReply);
  ASSERT_TRUE(wait_for([&] { return rig.monitor->snapshot().counters.timeouts >= 1; }, 5.0));
  rig.device.inject(SimFault::kPartial);
  ASSERT_TRUE(wait_for([&] { return rig.monitor->snapshot().counters.timeouts >= 2; }, 5.0));
  rig.device.inject(SimFault::kGarbled);
  ASSERT_TRUE(wait_for([&] { return rig.monitor->snapshot().counters.garbled >= 1; }, 5.0));
  EXPECT_GE(rig.core->bus_status().malformed_frames, 1u);
  // the link carries on: samples come and the axis follows
  const auto samples = rig.monitor->snapshot().counters.samples;
  ASSERT_TRUE(wait_for([&] { return rig.monitor->snapshot().counters.samples >= samples + 3; }, 5.0));
  ASSERT_TRUE(rig.drive_c(-3.0));
  EXPECT_EQ(rig.core->bus_status().connects, 1u) << "a lost reply is no reason to reconnect";
}

TEST(NanoControlPath, BreakdownHoldsEveryAxisUntilRecover) {
  Rig rig("breakdown");
  ASSERT_TRUE(wait_for([&] { return rig.core->axis_status(2).has_baseline; }, 10.0));
  ASSERT_TRUE(rig.drive_c(1.0));
  rig.device.inject(SimFault::kBreakdown);
  ASSERT_TRUE(wait_for([&] { return rig.core->axis_status(0).device_fault && rig.core->axis_status(2).device_fault; }, 5.0));
  EXPECT_TRUE(rig.monitor->snapshot().counters.breakdown);
  EXPECT_NE(rig.monitor->snapshot().counters.last_info.find("Breakdown"), std::string::npos);
  const std::size_t before = rig.device.set_points_c().size();
  EXPECT_EQ(rig.core->command(2, 3.0, now_s()), can::CommandOutcome::kRejectedHeld);
  rig.core->tick(now_s() + 0.05);
  EXPECT_EQ(rig.device.set_points_c().size(), before);
  rig.core->recover();
  ASSERT_TRUE(wait_for([&] { return rig.core->bus_status().connects >= 2 && !rig.core->axis_status(2).device_fault &&
                                    rig.core->axis_status(2).has_baseline; }, 5.0));
  EXPECT_FALSE(rig.monitor->snapshot().counters.breakdown);
  ASSERT_TRUE(rig.drive_c(3.0));
}

TEST(NanoControlPath, PortLostReconnectsAndRebaselinesFromTheReadBack) {
  Rig rig("portlost");
  ASSERT_TRUE(wait_for([&] { return rig.core->axis_status(2).has_baseline; }, 10.0));
  ASSERT_TRUE(rig.drive_c(4.0));
  rig.device.vanish();
  ASSERT_TRUE(wait_for([&] { return rig.core->bus_status().state == can::BusState::kDisconnected; }, 5.0));
  EXPECT_NE(rig.core->bus_status().last_error.find("port lost"), std::string::npos) << rig.core->bus_status().last_error;
  EXPECT_EQ(rig.core->command(2, 5.0, now_s()), can::CommandOutcome::kRejectedHeld);
  rig.device.set_c_directly(-4096);  // -10 V: moved while the driver was away
  rig.device.reappear();
  ASSERT_TRUE(wait_for([&] { return rig.core->bus_status().connects >= 2 && rig.core->axis_status(2).has_baseline; }, 10.0));
  ASSERT_TRUE(wait_for([&] { return std::abs(rig.core->axis_status(2).applied_v + 10.0) < 0.01; }, 5.0))
      << "baseline from the read-back, not the last command: " << rig.core->axis_status(2).applied_v;
  const std::size_t before = rig.device.set_points_c().size();
  ASSERT_TRUE(rig.drive_c(-9.0));
  const auto sp = rig.device.set_points_c();
  ASSERT_GT(sp.size(), before);
  EXPECT_GE(sp[before], -10.0 - 0.0025) << "the first step after the reconnect starts from -10 V, not from 4 V";
  EXPECT_LE(sp[before], -9.0 + 0.0025);  // within a DAC count (2.4 mV)
}
