// Property test of the whole command path: DriverCore against the simulated controller (DeviceCore) through an
// in-memory bus, driven by random sequences of commands (NaN, ±inf, huge, out of range, stamps from other
// clocks), caller-time jumps back and forth, lost, late and duplicated reports, refused sends, controller
// restarts and halts, bus-offs, receive failures, reconnects, halt and recover. On every frame written:
//   - it decodes, and its voltage is within the limits (or a ramp-in step between them and a device that
//     started outside them);
//   - when the device applies it, it is within slew_rate × Δt of the voltage the device really had, Δt being
//     the time the driver's clock gave since that voltage was set (each step's increment clamped to
//     [0, max_step_dt_s], as the driver sees it);
//   - it is within max_frame_step_v of the driver's previous frame on that axis since the last baseline.
// PIEZO_PROPERTY_STEPS (default 100000) and PIEZO_PROPERTY_SEED (default 1) select the run; scripts/test runs
// the default, `PIEZO_PROPERTY_STEPS=10000000 build/devel/lib/piezo_compensation/test_can_command_path` is the
// long mode.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <deque>
#include <limits>
#include <memory>
#include <random>
#include <string>

#include "piezo_compensation/can/device_core.h"
#include "piezo_compensation/can/driver_core.h"

using namespace piezo::can;

namespace {

struct Bus {
  std::deque<ReceivedFrame> to_driver;
  std::vector<can_frame> written;  // frames the driver wrote, not yet seen by the device
  bool open = false;
  int refuse_steps = 0;   // send() returns false (queue full) while > 0
  bool fail_receive = false;
  std::uint64_t refused = 0;
};

class MemoryTransport : public Transport {
 public:
  explicit MemoryTransport(Bus* bus) : bus_(bus) {}
  void open() override { bus_->open = true; }
  void close() override { bus_->open = false; }
  bool is_open() const override { return bus_->open; }
  bool send(const can_frame& f) override {
    if (!bus_->open) throw TransportError("memory: closed");
    if (bus_->refuse_steps > 0) {
      ++bus_->refused;
      return false;
    }
    bus_->written.push_back(f);
    return true;
  }
  int receive(std::vector<ReceivedFrame>& out, int) override {
    if (bus_->fail_receive) {
      bus_->fail_receive = false;
      throw TransportError("memory: receive failed");
    }
    int n = 0;
    for (; !bus_->to_driver.empty(); ++n) {
      out.push_back(bus_->to_driver.front());
      bus_->to_driver.pop_front();
    }
    return n;
  }
  std::string describe() const override { return "memory"; }

 private:
  Bus* bus_;
};

long env_long(const char* name, long fallback) {
  const char* v = std::getenv(name);
  return v && *v ? std::strtol(v, nullptr, 10) : fallback;
}

}  // namespace

// One run of the property: the driver and the simulated device on one in-memory bus, the random source that
// drives them, and what the checks keep track of.
class CanCommandPathProperty : public ::testing::Test {
 protected:
  CanCommandPathProperty()
      : steps_(env_long("PIEZO_PROPERTY_STEPS", 100000)),
        seed_(static_cast<unsigned>(env_long("PIEZO_PROPERTY_SEED", 1))),
        rng_(seed_),
        config_(driver_config()),
        lim_(config_.limits),
        lsb_(config_.protocol.voltage_lsb_v),
        driver_(config_, [this] { return std::make_unique<MemoryTransport>(&bus_); }, {}),
        device_(device_config(),
                [](const std::array<double, kAxisCount>&, double) { return piezo::sim::StepResult{}; }),
        codec_(config_.protocol) {}

  static DriverConfig driver_config() {
    ProtocolConfig protocol;
    protocol.encoder_rate_hz = 50.0;  // one device sample every 4 driver steps of 5 ms
    protocol.heartbeat_period_s = 0.2;
    DriverConfig config;
    config.protocol = protocol;
    config.limits.min_voltage_v = -60.0;
    config.limits.max_voltage_v = 70.0;
    config.limits.slew_rate_v_per_s = 300.0;
    config.limits.command_timeout_s = 0.3;
    config.limits.max_step_dt_s = 0.1;
    config.limits.max_frame_step_v = 4.0;
    config.silence_reconnect_s = 3600.0;  // reconnects come from bus-offs, receive failures and recover()
    config.reconnect_min_s = 1e-6;
    config.reconnect_max_s = 1e-5;
    return config;
  }

  DeviceConfig device_config() {
    DeviceConfig dc;
    dc.protocol = config_.protocol;
    dc.min_voltage_v = -100.0;  // the amplifier's own range is wider than the driver's limits
    dc.max_voltage_v = 100.0;
    for (auto& v : dc.initial_voltage_v) v = uniform(-95.0, 95.0);  // may start outside the driver's limits
    return dc;
  }

  bool chance(double p) { return u01_(rng_) < p; }
  double uniform(double lo, double hi) { return lo + (hi - lo) * u01_(rng_); }

  void call_time(double t) {
    allowance_ += std::min(std::max(t - last_call_, 0.0), lim_.max_step_dt_s);
    last_call_ = t;
  }

  // A frame as the driver wrote it: within the limits (or ramping in) and within the frame-step cap.
  void check_frame(long step, int a, double v, double before) {
    ++frames_;
    const bool inside = v >= lim_.min_voltage_v && v <= lim_.max_voltage_v;
    const bool ramping_in =
        (v > lim_.max_voltage_v && v < before + lsb_) || (v < lim_.min_voltage_v && v > before - lsb_);
    ramp_in_ += ramping_in;
    if (!inside && !ramping_in && ++failures_ < 10)
      ADD_FAILURE() << "step " << step << ": axis " << a << " frame " << v << " V outside ["
                    << lim_.min_voltage_v << ", " << lim_.max_voltage_v << "] (device at " << before << " V)";
    if (has_prev_[a] && std::abs(v - prev_frame_[a]) > lim_.max_frame_step_v + 2 * lsb_ && ++failures_ < 10)
      ADD_FAILURE() << "step " << step << ": axis " << a << " frame " << v << " V is "
                    << std::abs(v - prev_frame_[a]) << " V from the previous frame (cap "
                    << lim_.max_frame_step_v << ")";
    has_prev_[a] = true;
    prev_frame_[a] = v;
  }

  // A frame the device applied: within the slew budget since the axis last moved, and within the bound a
  // silently halted device can see on resume.
  void check_applied(long step, int a, double before, double after) {
    ++applied_;
    const double budget = lim_.slew_rate_v_per_s * (allowance_ - changed_at_[a]) + 2 * lsb_ + 1e-9;
    largest_applied_step_ = std::max(largest_applied_step_, std::abs(after - before));
    if (std::getenv("PIEZO_PROPERTY_TRACE") && std::abs(after - before) > lim_.max_frame_step_v)
      std::printf("step %ld axis %d: %.3f -> %.3f V, allowance since change %.3f s, prev frame %s%.3f\n",
                  step, a, before, after, allowance_ - changed_at_[a], has_prev_[a] ? "" : "(none) ",
                  prev_frame_[a]);
    furthest_ = std::max(furthest_, std::abs(after));
    if (std::abs(after - before) > budget && ++failures_ < 10)
      ADD_FAILURE() << "step " << step << ": axis " << a << " went " << before << " → " << after << " V, "
                    << "slew budget " << budget << " V";
    // A device that ignored set points for a while (halted without saying so) sees at most this on resume.
    const double silent_bound = 2 * lim_.max_unconfirmed_v + lim_.report_tolerance_v + 2 * lsb_ + 1e-9;
    if (std::abs(after - before) > silent_bound && ++failures_ < 10)
      ADD_FAILURE() << "step " << step << ": axis " << a << " went " << before << " → " << after
                    << " V in one frame";
    if (after != before) changed_at_[a] = allowance_;
  }

  void deliver_written(long step) {
    for (const auto& f : bus_.written) {
      const DecodeResult r = codec_.decode(f);
      ASSERT_TRUE(r.ok()) << "step " << step << ": undecodable frame " << to_candump(f);
      const auto* c = std::get_if<CommandFrame>(&r.message_value);
      ASSERT_NE(c, nullptr) << "step " << step;
      const int a = c->axis;
      const double before = device_.voltages_v()[a];
      check_frame(step, a, c->voltage_v, before);
      device_.handle(f);
      if (device_.state() != DeviceState::kOperational) continue;  // ignored: the piezo does not move
      check_applied(step, a, before, device_.voltages_v()[a]);
    }
    bus_.written.clear();
  }

  // The driver's clock: mostly 5 ms, sometimes jitter, sometimes a jump back or far ahead.
  void advance_clock() {
    if (chance(0.001))
      now_ -= uniform(0.0, 10.0);
    else if (chance(0.001))
      now_ += uniform(0.0, 100.0);
    else if (chance(0.02))
      now_ += uniform(-0.005, 0.02);
    else
      now_ += 0.005;
  }

  // Commands on random axes: NaN, ±inf, huge, out of range or in range, stamped now, stale, ahead or from
  // another clock.
  void send_commands() {
    for (int a = 0; a < kAxisCount; ++a) {
      if (!chance(0.3)) continue;
      double v;
      const double kind = u01_(rng_);
      if (kind < 0.02)
        v = std::nan("");
      else if (kind < 0.03)
        v = std::numeric_limits<double>::infinity();
      else if (kind < 0.04)
        v = -std::numeric_limits<double>::infinity();
      else if (kind < 0.06)
        v = chance(0.5) ? 1e300 : -1e300;
      else if (kind < 0.2)
        v = uniform(-200.0, 200.0);  // often out of range
      else
        v = uniform(-70.0, 80.0);
      double stamp = std::nan("");
      const double sk = u01_(rng_);
      if (sk < 0.3)
        stamp = now_;
      else if (sk < 0.4)
        stamp = now_ - uniform(0.0, 2.0);  // stale
      else if (sk < 0.45)
        stamp = now_ + uniform(0.0, 0.4);  // slightly ahead: taken as now
      else if (sk < 0.5)
        stamp = now_ + uniform(1.0, 1e6);  // another clock: refused
      call_time(now_);
      driver_.command(a, v, now_, stamp);
    }
  }

  // One device sample; its reports are lost, late or duplicated now and then.
  void device_sample() {
    if (halted_samples_ > 0 && --halted_samples_ == 0) device_.set_state(DeviceState::kOperational);
    const auto out = device_.step();
    std::vector<ReceivedFrame> now_late;
    for (const auto& f : out.frames) {
      if (chance(0.03)) continue;  // lost
      ReceivedFrame rf{f, 0.0};
      if (chance(0.01)) {
        now_late.push_back(rf);  // arrives after the next sample's frames
        continue;
      }
      bus_.to_driver.push_back(rf);
      if (chance(0.01)) bus_.to_driver.push_back(rf);  // duplicated
    }
    for (const auto& rf : late_) bus_.to_driver.push_back(rf);
    late_.assign(now_late.begin(), now_late.end());
  }

  // Controller restarts and halts, bus-offs, receive failures, refused sends.
  void inject_faults() {
    if (chance(0.0005)) {
      device_.restart();
      ++restarts_;
      for (int a = 0; a < kAxisCount; ++a) changed_at_[a] = allowance_;
      late_.clear();  // frames from before the restart that are still on their way are not delayed further
    }
    if (chance(0.0005) && device_.state() == DeviceState::kOperational) {
      device_.set_state(DeviceState::kHalted);
      halted_samples_ = 1 + static_cast<int>(uniform(0, 30));
      ++halts_;
    }
    if (chance(0.0005)) {
      BusError e;
      e.error_class = CAN_ERR_BUSOFF;
      bus_.to_driver.push_back({Codec::encode(e), 0.0});
      ++bus_offs_;
    }
    if (chance(0.0003)) bus_.fail_receive = true;
    if (bus_.refuse_steps > 0)
      --bus_.refuse_steps;
    else if (chance(0.001))
      bus_.refuse_steps = 10 + static_cast<int>(uniform(0, 190));
  }

  // The operator's halt and recover, then one poll of the driver (which may reconnect).
  void operator_actions() {
    if (chance(0.0002)) driver_.halt();
    bool held = false;
    for (int a = 0; a < kAxisCount; ++a) {
      const AxisStatus s = driver_.axis_status(a);
      held |= s.device_fault || s.halted;
    }
    if (held && chance(0.01)) {
      driver_.recover();
      ++recovers_;
      has_prev_.fill(false);  // the cap applies from the new baseline
    }
    const auto connects = driver_.bus_status().connects;
    driver_.poll_once(0);
    if (driver_.bus_status().connects != connects) has_prev_.fill(false);  // a reconnect takes a new baseline
  }

  void run() {
    for (long step = 0; step < steps_ && failures_ < 10; ++step) {
      advance_clock();
      send_commands();
      if (chance(0.7)) {
        call_time(now_);
        driver_.tick(now_);
      }
      deliver_written(step);
      if (step % 4 == 0) device_sample();  // the device: one sample every 4 steps
      inject_faults();
      operator_actions();
    }
  }

  void print_summary() {
    for (int a = 0; a < kAxisCount; ++a) {
      const AxisStatus s = driver_.axis_status(a);
      trips_ += s.device_faults;
      mismatches_ += s.report_mismatches;
      future_ += s.rejected_future_stamp;
    }
    std::printf(
        "property: %ld steps, seed %u: %lu frames written, %lu applied, %lu ramp-in, %lu refused sends, "
        "%lu restarts, %lu halts, %lu bus-offs, %lu recovers, %lu device faults, %lu report mismatches, "
        "%lu future stamps refused; largest applied step %.3f V, furthest %.1f V\n",
        steps_, seed_, (unsigned long)frames_, (unsigned long)applied_, (unsigned long)ramp_in_,
        (unsigned long)bus_.refused, (unsigned long)restarts_, (unsigned long)halts_,
        (unsigned long)bus_offs_, (unsigned long)recovers_, (unsigned long)trips_, (unsigned long)mismatches_,
        (unsigned long)future_, largest_applied_step_, furthest_);
  }

  const long steps_;
  const unsigned seed_;
  std::mt19937_64 rng_;
  std::uniform_real_distribution<double> u01_{0.0, 1.0};
  const DriverConfig config_;
  const LimiterConfig& lim_;
  const double lsb_;
  Bus bus_;
  DriverCore driver_;
  DeviceCore device_;
  const Codec codec_;

  double now_ = 1000.0;     // driver's (caller's) clock
  double allowance_ = 0.0;  // Σ clamped positive increments of the driver's clock
  double last_call_ = now_;
  std::array<double, kAxisCount> changed_at_{};  // allowance when the device's voltage last changed
  std::array<bool, kAxisCount> has_prev_{};
  std::array<double, kAxisCount> prev_frame_{};
  std::deque<ReceivedFrame> late_;  // reports held back to arrive after newer ones
  int halted_samples_ = 0;
  std::uint64_t frames_ = 0, applied_ = 0, ramp_in_ = 0, restarts_ = 0, halts_ = 0, bus_offs_ = 0,
                recovers_ = 0;
  std::uint64_t trips_ = 0, mismatches_ = 0, future_ = 0;
  double largest_applied_step_ = 0.0, furthest_ = 0.0;
  int failures_ = 0;
};

TEST_F(CanCommandPathProperty, NoFrameOutsideTheLimitsOrFasterThanTheSlewLimit) {
  run();
  print_summary();
  // The run must have exercised what it claims to (scaled for short runs).
  if (steps_ >= 100000) {
    EXPECT_GT(applied_, 1000u);
    EXPECT_GT(restarts_, 5u);
    EXPECT_GT(trips_, 5u);
    EXPECT_GT(bus_.refused, 100u);
    EXPECT_GT(bus_offs_, 5u);
    EXPECT_GT(furthest_, 50.0);
  }
}
