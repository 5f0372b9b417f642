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

TEST(CanCommandPathProperty, NoFrameOutsideTheLimitsOrFasterThanTheSlewLimit) {
  const long steps = env_long("PIEZO_PROPERTY_STEPS", 100000);
  const unsigned seed = static_cast<unsigned>(env_long("PIEZO_PROPERTY_SEED", 1));
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  auto chance = [&](double p) { return u01(rng) < p; };
  auto uniform = [&](double lo, double hi) { return lo + (hi - lo) * u01(rng); };

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
  const LimiterConfig& lim = config.limits;
  const double lsb = protocol.voltage_lsb_v;

  Bus bus;
  DriverCore driver(config, [&bus] { return std::make_unique<MemoryTransport>(&bus); }, {});
  DeviceConfig dc;
  dc.protocol = protocol;
  dc.min_voltage_v = -100.0;  // the amplifier's own range is wider than the driver's limits
  dc.max_voltage_v = 100.0;
  for (auto& v : dc.initial_voltage_v) v = uniform(-95.0, 95.0);  // may start outside the driver's limits
  DeviceCore device(dc, [](const std::array<double, kAxisCount>&, double) { return piezo::sim::StepResult{}; });
  const Codec codec(protocol);

  double now = 1000.0;           // driver's (caller's) clock
  double allowance = 0.0;        // Σ clamped positive increments of the driver's clock
  double last_call = now;
  std::array<double, kAxisCount> changed_at{};  // allowance when the device's voltage last changed
  std::array<bool, kAxisCount> has_prev{};
  std::array<double, kAxisCount> prev_frame{};
  std::deque<ReceivedFrame> late;  // reports held back to arrive after newer ones
  int halted_samples = 0;
  std::uint64_t frames = 0, applied = 0, ramp_in = 0, restarts = 0, halts = 0, bus_offs = 0, recovers = 0;
  double largest_applied_step = 0.0, furthest = 0.0;
  int failures = 0;

  auto call_time = [&](double t) {
    allowance += std::min(std::max(t - last_call, 0.0), lim.max_step_dt_s);
    last_call = t;
  };
  auto deliver_written = [&](long step) {
    for (const auto& f : bus.written) {
      const DecodeResult r = codec.decode(f);
      ASSERT_TRUE(r.ok()) << "step " << step << ": undecodable frame " << to_candump(f);
      const auto* c = std::get_if<CommandFrame>(&r.message_value);
      ASSERT_NE(c, nullptr) << "step " << step;
      const int a = c->axis;
      const double v = c->voltage_v;
      const double before = device.voltages_v()[a];
      ++frames;
      const bool inside = v >= lim.min_voltage_v && v <= lim.max_voltage_v;
      const bool ramping_in = (v > lim.max_voltage_v && v < before + lsb) || (v < lim.min_voltage_v && v > before - lsb);
      ramp_in += ramping_in;
      if (!inside && !ramping_in && ++failures < 10)
        ADD_FAILURE() << "step " << step << ": axis " << a << " frame " << v << " V outside ["
                      << lim.min_voltage_v << ", " << lim.max_voltage_v << "] (device at " << before << " V)";
      if (has_prev[a] && std::abs(v - prev_frame[a]) > lim.max_frame_step_v + 2 * lsb && ++failures < 10)
        ADD_FAILURE() << "step " << step << ": axis " << a << " frame " << v << " V is "
                      << std::abs(v - prev_frame[a]) << " V from the previous frame (cap " << lim.max_frame_step_v << ")";
      has_prev[a] = true;
      prev_frame[a] = v;
      device.handle(f);
      const double after = device.voltages_v()[a];
      if (device.state() != DeviceState::kOperational) continue;  // ignored: the piezo does not move
      ++applied;
      const double budget = lim.slew_rate_v_per_s * (allowance - changed_at[a]) + 2 * lsb + 1e-9;
      largest_applied_step = std::max(largest_applied_step, std::abs(after - before));
      if (std::getenv("PIEZO_PROPERTY_TRACE") && std::abs(after - before) > lim.max_frame_step_v)
        std::printf("step %ld axis %d: %.3f -> %.3f V, allowance since change %.3f s, prev frame %s%.3f\n", step, a,
                    before, after, allowance - changed_at[a], has_prev[a] ? "" : "(none) ", prev_frame[a]);
      furthest = std::max(furthest, std::abs(after));
      if (std::abs(after - before) > budget && ++failures < 10)
        ADD_FAILURE() << "step " << step << ": axis " << a << " went " << before << " → " << after << " V, "
                      << "slew budget " << budget << " V";
      // A device that ignored set points for a while (halted without saying so) sees at most this on resume.
      const double silent_bound = 2 * lim.max_unconfirmed_v + lim.report_tolerance_v + 2 * lsb + 1e-9;
      if (std::abs(after - before) > silent_bound && ++failures < 10)
        ADD_FAILURE() << "step " << step << ": axis " << a << " went " << before << " → " << after << " V in one frame";
      if (after != before) changed_at[a] = allowance;
    }
    bus.written.clear();
  };

  for (long step = 0; step < steps && failures < 10; ++step) {
    // the driver's clock: mostly 5 ms, sometimes jitter, sometimes a jump back or far ahead
    if (chance(0.001))
      now -= uniform(0.0, 10.0);
    else if (chance(0.001))
      now += uniform(0.0, 100.0);
    else if (chance(0.02))
      now += uniform(-0.005, 0.02);
    else
      now += 0.005;

    // commands
    for (int a = 0; a < kAxisCount; ++a) {
      if (!chance(0.3)) continue;
      double v;
      const double kind = u01(rng);
      if (kind < 0.02) v = std::nan("");
      else if (kind < 0.03) v = std::numeric_limits<double>::infinity();
      else if (kind < 0.04) v = -std::numeric_limits<double>::infinity();
      else if (kind < 0.06) v = chance(0.5) ? 1e300 : -1e300;
      else if (kind < 0.2) v = uniform(-200.0, 200.0);  // often out of range
      else v = uniform(-70.0, 80.0);
      double stamp = std::nan("");
      const double sk = u01(rng);
      if (sk < 0.3) stamp = now;
      else if (sk < 0.4) stamp = now - uniform(0.0, 2.0);   // stale
      else if (sk < 0.45) stamp = now + uniform(0.0, 0.4);  // slightly ahead: taken as now
      else if (sk < 0.5) stamp = now + uniform(1.0, 1e6);   // another clock: refused
      call_time(now);
      driver.command(a, v, now, stamp);
    }
    if (chance(0.7)) {
      call_time(now);
      driver.tick(now);
    }
    deliver_written(step);

    // the device: one sample every 4 steps
    if (step % 4 == 0) {
      if (halted_samples > 0 && --halted_samples == 0) device.set_state(DeviceState::kOperational);
      const auto out = device.step();
      std::vector<ReceivedFrame> now_late;
      for (const auto& f : out.frames) {
        if (chance(0.03)) continue;  // lost
        ReceivedFrame rf{f, 0.0};
        if (chance(0.01)) {
          now_late.push_back(rf);  // arrives after the next sample's frames
          continue;
        }
        bus.to_driver.push_back(rf);
        if (chance(0.01)) bus.to_driver.push_back(rf);  // duplicated
      }
      for (const auto& rf : late) bus.to_driver.push_back(rf);
      late.assign(now_late.begin(), now_late.end());
    }

    // faults and operator actions
    if (chance(0.0005)) {
      device.restart();
      ++restarts;
      for (int a = 0; a < kAxisCount; ++a) changed_at[a] = allowance;
      late.clear();  // frames from before the restart that are still on their way are not delayed further
    }
    if (chance(0.0005) && device.state() == DeviceState::kOperational) {
      device.set_state(DeviceState::kHalted);
      halted_samples = 1 + static_cast<int>(uniform(0, 30));
      ++halts;
    }
    if (chance(0.0005)) {
      BusError e;
      e.error_class = CAN_ERR_BUSOFF;
      bus.to_driver.push_back({Codec::encode(e), 0.0});
      ++bus_offs;
    }
    if (chance(0.0003)) bus.fail_receive = true;
    if (bus.refuse_steps > 0)
      --bus.refuse_steps;
    else if (chance(0.001))
      bus.refuse_steps = 10 + static_cast<int>(uniform(0, 190));
    if (chance(0.0002)) driver.halt();
    bool held = false;
    for (int a = 0; a < kAxisCount; ++a) {
      const AxisStatus s = driver.axis_status(a);
      held |= s.device_fault || s.halted;
    }
    if (held && chance(0.01)) {
      driver.recover();
      ++recovers;
      has_prev.fill(false);  // the cap applies from the new baseline
    }
    const auto connects = driver.bus_status().connects;
    driver.poll_once(0);
    if (driver.bus_status().connects != connects) has_prev.fill(false);  // a reconnect takes a new baseline
  }
  std::uint64_t trips = 0, mismatches = 0, future = 0;
  for (int a = 0; a < kAxisCount; ++a) {
    const AxisStatus s = driver.axis_status(a);
    trips += s.device_faults;
    mismatches += s.report_mismatches;
    future += s.rejected_future_stamp;
  }
  std::printf("property: %ld steps, seed %u: %lu frames written, %lu applied, %lu ramp-in, %lu refused sends, "
              "%lu restarts, %lu halts, %lu bus-offs, %lu recovers, %lu device faults, %lu report mismatches, "
              "%lu future stamps refused; largest applied step %.3f V, furthest %.1f V\n",
              steps, seed, (unsigned long)frames, (unsigned long)applied, (unsigned long)ramp_in,
              (unsigned long)bus.refused, (unsigned long)restarts, (unsigned long)halts, (unsigned long)bus_offs,
              (unsigned long)recovers, (unsigned long)trips, (unsigned long)mismatches, (unsigned long)future,
              largest_applied_step, furthest);
  // The run must have exercised what it claims to (scaled for short runs).
  if (steps >= 100000) {
    EXPECT_GT(applied, 1000u);
    EXPECT_GT(restarts, 5u);
    EXPECT_GT(trips, 5u);
    EXPECT_GT(bus.refused, 100u);
    EXPECT_GT(bus_offs, 5u);
    EXPECT_GT(furthest, 50.0);
  }
}
