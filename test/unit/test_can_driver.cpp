// DriverCore against DeviceCore over the UDP transport on loopback: reports, commands, garbage, bus-off,
// silence, missing interface. Real sockets and threads, no ROS.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <mutex>
#include <thread>

#include "piezo_compensation/can/device_core.h"
#include "piezo_compensation/can/driver_core.h"

using namespace piezo::can;
using namespace std::chrono_literals;

namespace {

int base_port() { return 30000 + static_cast<int>(getpid() % 10000) * 2; }

ProtocolConfig fast_protocol() {
  ProtocolConfig p;
  p.encoder_rate_hz = 100.0;  // fast reports keep the test short
  p.heartbeat_period_s = 0.1;
  return p;
}

// A plant whose position is 25 nm/V of the applied voltage: enough to see a command arrive.
piezo::sim::StepResult linear_plant(const std::array<double, 3>& v, double) {
  piezo::sim::StepResult r;
  for (int i = 0; i < 3; ++i) {
    r.axes[i].voltage_v = v[i];
    r.axes[i].true_position_nm = 25.0 * v[i];
    r.axes[i].measured_position_nm = 25.0 * v[i];
  }
  return r;
}

// The simulated controller on its own thread.
class Device {
 public:
  explicit Device(int port_offset = 0)
      : core_(DeviceConfig{fast_protocol(), -80, 80, {1.0, 2.0, 3.0}}, linear_plant) {
    UdpOptions o;
    o.local_port = base_port() + 1 + port_offset;
    o.remote_port = base_port() + port_offset;
    o.filters = core_.codec().device_filters();
    transport_ = make_udp_transport(o);
    transport_->open();
    thread_ = std::thread([this] { run(); });
  }
  ~Device() {
    running_ = false;
    thread_.join();
  }
  void send(const can_frame& f) {
    std::lock_guard<std::mutex> lock(mutex_);
    transport_->send(f);
  }
  void set_silent(bool s) { silent_ = s; }
  int syncs() const { return syncs_; }
  std::array<double, 3> voltages_at_last_sync() {
    std::lock_guard<std::mutex> lock(mutex_);
    return voltages_at_sync_;
  }
  std::array<double, 3> voltages() {
    std::lock_guard<std::mutex> lock(mutex_);
    return core_.voltages_v();
  }
  // Largest change one command frame made to an axis' voltage.
  double largest_step(int axis) {
    std::lock_guard<std::mutex> lock(mutex_);
    return largest_step_[axis];
  }

 private:
  void run() {
    auto next = std::chrono::steady_clock::now();
    while (running_) {
      std::vector<ReceivedFrame> in;
      transport_->receive(in, 2);
      std::lock_guard<std::mutex> lock(mutex_);
      for (const auto& rf : in) {
        const auto before = core_.voltages_v();
        const auto handled = core_.handle(rf.frame);
        for (int i = 0; i < 3; ++i)
          largest_step_[i] = std::max(largest_step_[i], std::abs(core_.voltages_v()[i] - before[i]));
        if (handled == DeviceCore::Handled::kSync) {
          ++syncs_;
          voltages_at_sync_ = core_.voltages_v();
        }
      }
      if (std::chrono::steady_clock::now() >= next) {
        next += 10ms;
        const auto out = core_.step();
        if (!silent_)
          for (const auto& f : out.frames) transport_->send(f);
      }
    }
  }
  DeviceCore core_;
  std::unique_ptr<Transport> transport_;
  std::mutex mutex_;
  std::atomic<bool> running_{true}, silent_{false};
  std::atomic<int> syncs_{0};
  std::array<double, 3> voltages_at_sync_{};
  std::array<double, 3> largest_step_{};
  std::thread thread_;
};

DriverConfig driver_config() {
  DriverConfig c;
  c.protocol = fast_protocol();
  c.limits.slew_rate_v_per_s = 1000.0;
  c.limits.command_timeout_s = 5.0;
  c.silence_reconnect_s = 0.5;
  c.reconnect_min_s = 0.05;
  c.reconnect_max_s = 0.2;
  return c;
}

DriverCore::TransportFactory udp_factory(const ProtocolConfig& p) {
  return [p] {
    UdpOptions o;
    o.local_port = base_port();
    o.remote_port = base_port() + 1;
    o.filters = Codec(p).driver_filters();
    return make_udp_transport(o);
  };
}

double now_s() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

template <typename Pred>
bool wait_for(Pred pred, std::chrono::milliseconds limit) {
  const auto end = std::chrono::steady_clock::now() + limit;
  while (std::chrono::steady_clock::now() < end) {
    if (pred()) return true;
    std::this_thread::sleep_for(5ms);
  }
  return pred();
}

struct Recorder {
  std::mutex m;
  std::array<int, 3> encoder{}, voltage{};
  std::array<double, 3> position{}, reported{};
  std::array<std::uint32_t, 3> last_seq{};
  int sequence_regressions = 0;
  DriverCallbacks callbacks() {
    DriverCallbacks cb;
    cb.on_encoder = [this](const EncoderReport& e, std::uint32_t seq, double t) {
      std::lock_guard<std::mutex> l(m);
      if (encoder[e.axis] > 0 && seq <= last_seq[e.axis]) ++sequence_regressions;
      last_seq[e.axis] = seq;
      ++encoder[e.axis];
      position[e.axis] = e.position_m;
      EXPECT_GT(t, 1e9);  // a kernel receive time (epoch seconds), not 0
    };
    cb.on_voltage = [this](const VoltageReport& v, std::uint32_t, double) {
      std::lock_guard<std::mutex> l(m);
      ++voltage[v.axis];
      reported[v.axis] = v.voltage_v;
    };
    return cb;
  }
};

}  // namespace

TEST(CanDriver, ReportsFlowForEveryAxis) {
  Device device;
  Recorder rec;
  DriverCore driver(driver_config(), udp_factory(fast_protocol()), rec.callbacks());
  driver.start();
  ASSERT_TRUE(wait_for([&] { std::lock_guard<std::mutex> l(rec.m); return rec.encoder[2] >= 20; }, 3000ms));
  std::lock_guard<std::mutex> l(rec.m);
  for (int i = 0; i < 3; ++i) {
    EXPECT_GE(rec.encoder[i], 15);
    EXPECT_GE(rec.voltage[i], 15);
    EXPECT_NEAR(rec.reported[i], i + 1.0, 1e-9);
    EXPECT_NEAR(rec.position[i], 25e-9 * (i + 1.0), 1e-12);
  }
  EXPECT_EQ(rec.sequence_regressions, 0);
  const BusStatus bus = driver.bus_status();
  EXPECT_EQ(bus.state, BusState::kActive);
  EXPECT_TRUE(bus.heartbeat_seen);
  EXPECT_EQ(bus.device_state, DeviceState::kOperational);
  EXPECT_EQ(bus.malformed_frames, 0u);
}

TEST(CanDriver, CommandReachesTheDeviceWithinLimits) {
  Device device;
  Recorder rec;
  DriverCore driver(driver_config(), udp_factory(fast_protocol()), rec.callbacks());
  driver.start();
  ASSERT_TRUE(wait_for([&] { return driver.axis_status(1).has_baseline; }, 3000ms));
  // Before any baseline-free command the device still has its initial voltage.
  EXPECT_NEAR(device.voltages()[1], 2.0, 1e-9);
  const auto t0 = std::chrono::steady_clock::now();
  while (std::chrono::steady_clock::now() - t0 < 200ms) {
    driver.command(1, 150.0, now_s());  // clamped to 80 V
    driver.tick(now_s());
    std::this_thread::sleep_for(2ms);
  }
  ASSERT_TRUE(wait_for([&] {
    driver.tick(now_s());
    return std::abs(device.voltages()[1] - 80.0) < 1e-9;
  }, 3000ms));
  EXPECT_TRUE(wait_for([&] { std::lock_guard<std::mutex> l(rec.m); return std::abs(rec.reported[1] - 80.0) < 1e-9; }, 1000ms));
  EXPECT_TRUE(wait_for([&] { std::lock_guard<std::mutex> l(rec.m); return std::abs(rec.position[1] - 2e-6) < 1e-12; }, 1000ms));
  const AxisStatus s = driver.axis_status(1);
  EXPECT_GT(s.clamped, 0u);
  EXPECT_GT(s.frames_sent, 5u);  // ramped, not one jump
  EXPECT_DOUBLE_EQ(s.applied_v, 80.0);
  EXPECT_NEAR(device.voltages()[0], 1.0, 1e-9);  // other axes untouched
  EXPECT_EQ(driver.command(0, std::nan(""), now_s()), CommandOutcome::kRejectedNonFinite);
  EXPECT_EQ(driver.axis_status(0).rejected_non_finite, 1u);
}

TEST(CanDriver, SyncFollowsTheSetPointsOnTheBus) {
  // synchronous mode: the set point written before sync() is in place when the device sees the SYNC
  Device device;
  Recorder rec;
  DriverCore driver(driver_config(), udp_factory(fast_protocol()), rec.callbacks());
  driver.start();
  ASSERT_TRUE(wait_for([&] { return driver.axis_status(2).has_baseline; }, 3000ms));
  double t = 100.0;  // bus time: one period per SYNC, whatever the wall clock does
  driver.tick(t);
  for (int k = 1; k <= 5; ++k) {
    t += 0.1;
    const double target = 3.0 + 2.0 * k;  // within one period's slew (1000 V/s · 0.1 s)
    driver.command(2, target, t, t);
    ASSERT_TRUE(driver.sync());
    ASSERT_TRUE(wait_for([&] { return device.syncs() >= k; }, 2000ms));
    EXPECT_NEAR(device.voltages_at_last_sync()[2], target, 1e-3) << "SYNC " << k << " overtook its set point";
  }
  EXPECT_EQ(driver.bus_status().syncs_sent, 5u);
}

TEST(CanDriver, HeldSetPointsGoOutWithTheirSync) {
  // hold_until_sync (the node's sync mode): a set point waits for sync() and goes out in one datagram with the
  // SYNC; it counts as written (and moves the limiter) only then, and the device has it in place at that SYNC
  Device device;
  Recorder rec;
  DriverConfig c = driver_config();
  c.hold_until_sync = true;
  DriverCore driver(c, udp_factory(fast_protocol()), rec.callbacks());
  driver.start();
  ASSERT_TRUE(wait_for([&] { return driver.axis_status(2).has_baseline; }, 3000ms));
  double t = 100.0;
  driver.tick(t);
  for (int k = 1; k <= 5; ++k) {
    t += 0.1;
    const double target = 3.0 + 2.0 * k;
    const auto sent_before = driver.axis_status(2).frames_sent;
    driver.command(2, target, t, t);
    EXPECT_EQ(driver.axis_status(2).frames_sent, sent_before) << "a held set point was counted before its SYNC";
    ASSERT_TRUE(driver.sync());
    EXPECT_EQ(driver.axis_status(2).frames_sent, sent_before + 1);
    ASSERT_TRUE(wait_for([&] { return device.syncs() >= k; }, 2000ms));
    EXPECT_NEAR(device.voltages_at_last_sync()[2], target, 1e-3) << "SYNC " << k << " went without its set point";
  }
  EXPECT_EQ(driver.bus_status().syncs_sent, 5u);
  EXPECT_EQ(driver.bus_status().send_failures, 0u);
}

TEST(CanDriver, GarbageDatagramsAreCountedNotFatal) {
  Device device;
  Recorder rec;
  DriverCore driver(driver_config(), udp_factory(fast_protocol()), rec.callbacks());
  driver.start();
  ASSERT_TRUE(wait_for([&] { return driver.bus_status().state == BusState::kActive; }, 3000ms));
  int fd = socket(AF_INET, SOCK_DGRAM, 0);
  sockaddr_in to{};
  to.sin_family = AF_INET;
  to.sin_port = htons(base_port());
  inet_pton(AF_INET, "127.0.0.1", &to.sin_addr);
  unsigned seed = 12345;
  for (int i = 0; i < 200; ++i) {
    unsigned char buf[40];
    for (auto& b : buf) b = static_cast<unsigned char>(rand_r(&seed));
    const std::size_t len = (i % 3 == 0) ? 16 : (rand_r(&seed) % 40);
    if (i % 3 == 0) {  // a well-sized frame of ours with broken content
      can_frame f = Codec(fast_protocol()).encode(EncoderReport{i % 3, 0.0, 0, true});
      f.can_dlc = static_cast<std::uint8_t>(9 + i % 7);
      std::memcpy(buf, &f, sizeof f);
    }
    sendto(fd, buf, len, 0, reinterpret_cast<sockaddr*>(&to), sizeof to);
  }
  close(fd);
  ASSERT_TRUE(wait_for([&] { return driver.bus_status().malformed_frames >= 60; }, 2000ms));
  const int before = [&] { std::lock_guard<std::mutex> l(rec.m); return rec.encoder[0]; }();
  EXPECT_TRUE(wait_for([&] { std::lock_guard<std::mutex> l(rec.m); return rec.encoder[0] > before + 5; }, 2000ms));
  EXPECT_NE(driver.bus_status().state, BusState::kDisconnected);
}

TEST(CanDriver, BusOffDisconnectsHoldsAndRecovers) {
  Device device;
  Recorder rec;
  DriverCore driver(driver_config(), udp_factory(fast_protocol()), rec.callbacks());
  driver.start();
  ASSERT_TRUE(wait_for([&] { return driver.axis_status(2).has_baseline; }, 3000ms));
  BusError e;
  e.error_class = CAN_ERR_BUSOFF;
  device.set_silent(true);
  device.send(Codec::encode(e));
  ASSERT_TRUE(wait_for([&] { return driver.bus_status().bus_off_events == 1; }, 2000ms));
  EXPECT_NE(driver.bus_status().last_error.find("bus-off"), std::string::npos) << driver.bus_status().last_error;
  // While the bus is off no command goes out.
  EXPECT_EQ(driver.command(2, 10.0, now_s()), CommandOutcome::kRejectedHeld);
  EXPECT_GE(driver.axis_status(2).rejected_no_link, 1u);
  EXPECT_NEAR(device.voltages()[2], 3.0, 1e-9);
  device.set_silent(false);
  ASSERT_TRUE(wait_for([&] { return driver.bus_status().state == BusState::kActive && driver.axis_status(2).has_baseline; },
                       3000ms));
  EXPECT_GE(driver.bus_status().connects, 2u);
  EXPECT_NE(driver.command(2, 10.0, now_s()), CommandOutcome::kRejectedHeld);
  EXPECT_TRUE(wait_for([&] {
    driver.tick(now_s());
    return std::abs(device.voltages()[2] - 10.0) < 1e-9;
  }, 2000ms));
}

TEST(CanDriver, SilentDeviceIsReportedAndReconnected) {
  Device device;
  Recorder rec;
  DriverCore driver(driver_config(), udp_factory(fast_protocol()), rec.callbacks());
  driver.start();
  ASSERT_TRUE(wait_for([&] { return driver.bus_status().state == BusState::kActive; }, 3000ms));
  device.set_silent(true);
  EXPECT_TRUE(wait_for([&] { return driver.axis_status(0).encoder_age_s > 0.3; }, 2000ms));
  EXPECT_TRUE(wait_for([&] { return driver.bus_status().connects >= 2; }, 3000ms));  // reopened after silence
  device.set_silent(false);
  EXPECT_TRUE(wait_for([&] { return driver.axis_status(0).encoder_age_s >= 0 && driver.axis_status(0).encoder_age_s < 0.1; },
                       3000ms));
}

TEST(CanDriver, MissingInterfaceIsRetriedNeverFatal) {
  SocketCanOptions o;
  o.interface = "nosuchcan7";
  std::vector<std::string> events;
  std::mutex m;
  DriverCallbacks cb;
  cb.on_event = [&](const std::string& text, bool) {
    std::lock_guard<std::mutex> l(m);
    events.push_back(text);
  };
  DriverCore driver(driver_config(), [o] { return make_socketcan_transport(o); }, cb);
  driver.start();
  ASSERT_TRUE(wait_for([&] { return driver.bus_status().connect_failures >= 3; }, 3000ms));
  const BusStatus s = driver.bus_status();
  EXPECT_EQ(s.state, BusState::kDisconnected);
  EXPECT_NE(s.last_error.find("socketcan:nosuchcan7"), std::string::npos) << s.last_error;
  EXPECT_EQ(driver.command(0, 1.0, now_s()), CommandOutcome::kRejectedHeld);
  std::lock_guard<std::mutex> l(m);
  EXPECT_EQ(events.size(), 1u);  // the same failure is logged once, not per retry
}

TEST(CanDriver, HaltHoldsUntilRecover) {
  Device device;
  Recorder rec;
  DriverCore driver(driver_config(), udp_factory(fast_protocol()), rec.callbacks());
  driver.start();
  ASSERT_TRUE(wait_for([&] { return driver.axis_status(0).has_baseline; }, 3000ms));
  driver.halt();
  EXPECT_EQ(driver.command(0, 30.0, now_s()), CommandOutcome::kRejectedHeld);
  std::this_thread::sleep_for(100ms);
  driver.tick(now_s());
  EXPECT_NEAR(device.voltages()[0], 1.0, 1e-9);
  driver.recover();
  ASSERT_TRUE(wait_for([&] { return driver.axis_status(0).has_baseline && driver.bus_status().state == BusState::kActive; },
                       3000ms));
  EXPECT_EQ(driver.command(0, 30.0, now_s()), CommandOutcome::kAccepted);
}

TEST(CanDriver, UdpTransportRejectsBadOptions) {
  UdpOptions o;
  o.local_port = 0;
  o.remote_port = 1;
  EXPECT_THROW(make_udp_transport(o)->open(), TransportError);
  o.local_port = base_port() + 7;
  o.host = "not-an-ip";
  EXPECT_THROW(make_udp_transport(o)->open(), TransportError);
}

namespace {
// The UDP transport, but send() reports a full queue (ENOBUFS) while `refuse` is set.
class RefusingTransport : public Transport {
 public:
  RefusingTransport(std::unique_ptr<Transport> inner, std::atomic<bool>* refuse) : inner_(std::move(inner)), refuse_(refuse) {}
  void open() override { inner_->open(); }
  void close() override { inner_->close(); }
  bool is_open() const override { return inner_->is_open(); }
  bool send(const can_frame& f) override { return *refuse_ ? false : inner_->send(f); }
  int receive(std::vector<ReceivedFrame>& out, int ms) override { return inner_->receive(out, ms); }
  std::string describe() const override { return inner_->describe(); }

 private:
  std::unique_ptr<Transport> inner_;
  std::atomic<bool>* refuse_;
};
}  // namespace

TEST(CanDriver, SendsRefusedForHalfASecondDoNotJumpAfterwards) {
  Device device;
  Recorder rec;
  std::atomic<bool> refuse{false};
  const auto udp = udp_factory(fast_protocol());
  DriverConfig c = driver_config();
  c.limits.slew_rate_v_per_s = 100.0;
  c.limits.max_frame_step_v = 5.0;
  DriverCore driver(c, [&] { return std::make_unique<RefusingTransport>(udp(), &refuse); }, rec.callbacks());
  driver.start();
  ASSERT_TRUE(wait_for([&] { return driver.axis_status(2).has_baseline; }, 3000ms));
  auto run_for = [&](std::chrono::milliseconds d) {
    const auto t0 = std::chrono::steady_clock::now();
    while (std::chrono::steady_clock::now() - t0 < d) {
      driver.command(2, 70.0, now_s());
      driver.tick(now_s());
      std::this_thread::sleep_for(2ms);
    }
  };
  run_for(150ms);  // ramping from 3 V
  refuse = true;
  run_for(30ms);  // a frame sent just before the refusal may still be on its way to the device
  const double before = device.voltages()[2];
  EXPECT_GT(before, 5.0);
  EXPECT_LT(before, 40.0);
  run_for(470ms);  // the ramp would have moved 50 V in the half second
  // after a refusal the axis waits for the next report (100 Hz here) before it tries again
  EXPECT_GT(driver.axis_status(2).frames_refused, 20u);
  EXPECT_NEAR(device.voltages()[2], before, 1e-9);
  refuse = false;
  run_for(100ms);
  const double after = device.voltages()[2];
  EXPECT_GT(after, before) << "the ramp did not resume";
  EXPECT_LT(after, before + 100.0 * 0.1 + 5.0) << "the refused half second was made up at once";
  EXPECT_LE(device.largest_step(2), 5.0 + 1e-6) << "a frame carried more than the cap";
}
