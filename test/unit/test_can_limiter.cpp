// Command path safety rules: clamp, slew, hard cap per frame, NaN rejection, watchdog hold (never 0 V), holds,
// only written frames move the applied voltage, reports that do not match pause and then trip.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <optional>

#include "piezo_compensation/can/command_limiter.h"

using namespace piezo::can;

namespace {
LimiterConfig config() {
  LimiterConfig c;
  c.slew_rate_v_per_s = 100.0;
  c.command_timeout_s = 0.5;
  c.max_step_dt_s = 0.1;
  return c;
}
// One output step whose frame is written and which a following device reports back at once.
std::optional<double> send(CommandLimiter& l, double t) {
  const auto v = l.step(t);
  if (v) {
    l.sent(*v, t);
    l.on_reported_voltage(*v, t);
  }
  return v;
}
// Runs the ramp in 10 ms steps from t0 for `seconds`, returning the largest jump between outputs.
double ramp(CommandLimiter& l, double t0, double seconds) {
  double worst = 0.0;
  for (double t = t0; t <= t0 + seconds + 1e-9; t += 0.01) {
    const double before = l.applied_v();
    if (auto v = send(l, t)) {
      worst = std::max(worst, std::abs(*v - before));
      EXPECT_GE(*v, l.config().min_voltage_v);
      EXPECT_LE(*v, l.config().max_voltage_v);
    }
  }
  return worst;
}
}  // namespace

TEST(CanLimiter, RefusesCommandsBeforeTheDeviceReportsItsVoltage) {
  CommandLimiter l(config());
  EXPECT_EQ(l.command(10.0, 0.0), CommandOutcome::kRejectedNoBaseline);
  EXPECT_FALSE(l.step(0.1).has_value());
  l.on_reported_voltage(5.0, 0.0);
  EXPECT_EQ(l.command(10.0, 0.2), CommandOutcome::kAccepted);
}

TEST(CanLimiter, ClampsToTheLimits) {
  CommandLimiter l(config());
  l.on_reported_voltage(79.0, 0.0);
  l.step(0.0);
  EXPECT_EQ(l.command(500.0, 0.0), CommandOutcome::kClamped);
  EXPECT_DOUBLE_EQ(l.target_v(), 80.0);
  ramp(l, 0.01, 0.2);
  EXPECT_DOUBLE_EQ(l.applied_v(), 80.0);
  EXPECT_EQ(l.command(-1e300, 0.3), CommandOutcome::kClamped);
  EXPECT_DOUBLE_EQ(l.target_v(), -80.0);
}

TEST(CanLimiter, SlewLimitsEveryStep) {
  CommandLimiter l(config());
  l.on_reported_voltage(0.0, 0.0);
  l.step(0.0);
  l.command(50.0, 0.0);
  const double worst = ramp(l, 0.01, 0.25);
  EXPECT_LE(worst, 100.0 * 0.01 + 1e-9);
  EXPECT_NEAR(l.applied_v(), 25.0, 1.01);  // 100 V/s for 0.25 s
  l.command(50.0, 0.26);  // keep the watchdog fed
  ramp(l, 0.27, 0.4);
  EXPECT_DOUBLE_EQ(l.applied_v(), 50.0);
}

TEST(CanLimiter, LongPauseDoesNotAllowAJump) {
  CommandLimiter l(config());
  l.on_reported_voltage(0.0, 0.0);
  l.step(0.0);
  // 100 s of nothing, then a big command: one step may cover at most max_step_dt_s.
  l.command(70.0, 100.0);
  const auto v = send(l, 100.0);
  ASSERT_TRUE(v.has_value());
  EXPECT_LE(*v, 5.0 + 1e-9);  // slew × max_step_dt_s would allow 10 V; the cap per frame is 5 V
  l.command(70.0, 200.0);
  const double before = l.applied_v();
  const auto w = send(l, 200.0);
  ASSERT_TRUE(w.has_value());
  EXPECT_LE(*w - before, 5.0 + 1e-9);
}

TEST(CanLimiter, RejectsNonFiniteAndKeepsTheTarget) {
  CommandLimiter l(config());
  l.on_reported_voltage(0.0, 0.0);
  l.command(20.0, 0.0);
  for (double bad : {std::nan(""), std::numeric_limits<double>::infinity(), -std::numeric_limits<double>::infinity()})
    EXPECT_EQ(l.command(bad, 0.01), CommandOutcome::kRejectedNonFinite);
  EXPECT_DOUBLE_EQ(l.target_v(), 20.0);
}

TEST(CanLimiter, TimeoutHoldsTheAppliedVoltageNeverZero) {
  CommandLimiter l(config());
  l.on_reported_voltage(0.0, 0.0);
  l.step(0.0);
  l.command(60.0, 0.0);
  ramp(l, 0.01, 0.3);  // ramping, still below 60 V
  const double mid = l.applied_v();
  EXPECT_GT(mid, 20.0);
  EXPECT_LT(mid, 60.0);
  ramp(l, 0.32, 0.3);  // command is now > 0.5 s old
  EXPECT_TRUE(l.timed_out());
  EXPECT_EQ(l.timeouts(), 1u);
  const double held = l.applied_v();
  EXPECT_GT(held, 0.0);
  ramp(l, 0.7, 5.0);
  EXPECT_DOUBLE_EQ(l.applied_v(), held);  // not 0 V, not 60 V: exactly where it was
  EXPECT_DOUBLE_EQ(l.target_v(), held);
  EXPECT_EQ(l.command(10.0, 6.0), CommandOutcome::kAccepted);  // a fresh command resumes
  EXPECT_FALSE(l.timed_out());
}

TEST(CanLimiter, HoldsRefuseCommandsUntilReleased) {
  CommandLimiter l(config());
  l.on_reported_voltage(-5.0, 0.0);
  l.step(0.0);
  l.command(30.0, 0.0);
  send(l, 0.05);
  l.set_hold(HoldReason::kMultipleCommanders, true);
  const double held = l.applied_v();
  EXPECT_EQ(l.command(40.0, 0.1), CommandOutcome::kRejectedHeld);
  ramp(l, 0.1, 0.3);
  EXPECT_DOUBLE_EQ(l.applied_v(), held);
  l.set_hold(HoldReason::kHalted, true);
  l.set_hold(HoldReason::kMultipleCommanders, false);
  EXPECT_EQ(l.command(40.0, 0.5), CommandOutcome::kRejectedHeld);  // still halted
  l.set_hold(HoldReason::kHalted, false);
  EXPECT_EQ(l.command(40.0, 0.5), CommandOutcome::kAccepted);
}

TEST(CanLimiter, StartOutsideTheLimitsRampsInAtTheSlewRate) {
  CommandLimiter l(config());
  l.on_reported_voltage(95.0, 0.0);  // device beyond our (narrower) limits
  l.step(0.0);
  l.command(90.0, 0.0);  // clamped to 80 V
  double last = 95.0;
  int frames = 0;
  for (double t = 0.01; t < 0.3; t += 0.01) {
    const auto v = l.step(t);
    if (!v) continue;
    ++frames;
    EXPECT_LE(last - *v, 100.0 * 0.01 + 1e-9) << "a jump towards the limit at t=" << t;
    EXPECT_LT(*v, last);  // only inwards, never further out than the device already is
    EXPECT_TRUE(l.sendable(*v));
    l.sent(*v, t);
    l.on_reported_voltage(*v, t);
    last = *v;
  }
  EXPECT_GE(frames, 15);
  EXPECT_DOUBLE_EQ(l.applied_v(), 80.0);
  EXPECT_FALSE(l.sendable(80.5));  // once inside, outside is never sendable again
}

TEST(CanLimiter, OnlyAWrittenFrameMovesTheAppliedVoltage) {
  CommandLimiter l(config());
  l.on_reported_voltage(0.0, 0.0);
  l.step(0.0);
  l.command(50.0, 0.0);
  // 0.5 s of refused sends (queue full): proposals, but nothing accepted
  for (int k = 1; k <= 50; ++k) {
    const double t = 0.01 * k;
    l.command(50.0, t);
    ASSERT_TRUE(l.step(t).has_value());
    EXPECT_DOUBLE_EQ(l.applied_v(), 0.0);
  }
  const auto v = send(l, 0.51);  // the first frame that gets through is one step, not 0.5 s of ramp
  ASSERT_TRUE(v.has_value());
  EXPECT_NEAR(*v, 1.0, 1e-9);
}

// ECONNREFUSED: the frame written just before the refusal may have been lost too. Nothing is proposed until the
// device reports again; that report is checked as usual and the ramp goes on one step at a time.
TEST(CanLimiter, ARefusedFrameWaitsForTheNextReport) {
  CommandLimiter l(config());
  l.on_reported_voltage(0.0, 0.0);
  l.step(0.0);
  l.command(50.0, 0.0);
  for (int k = 1; k <= 10; ++k) ASSERT_TRUE(send(l, 0.01 * k).has_value());
  EXPECT_NEAR(l.applied_v(), 10.0, 1e-9);
  l.refused();
  EXPECT_TRUE(l.paused());
  for (int k = 11; k <= 60; ++k) {
    l.command(50.0, 0.01 * k);
    EXPECT_FALSE(l.step(0.01 * k).has_value()) << "proposed a frame before the device reported";
  }
  EXPECT_NEAR(l.applied_v(), 10.0, 1e-9);
  l.on_reported_voltage(10.0, 0.6);
  EXPECT_FALSE(l.paused());
  l.command(50.0, 0.61);
  const auto v = l.step(0.61);
  ASSERT_TRUE(v.has_value());
  EXPECT_NEAR(*v, 11.0, 1e-9) << "the first frame after the refusal is one step, not the refused half second";
  // A device that lost frames before the refusal reports less than was written: that pauses, then trips.
  l.sent(*v, 0.61);
  l.refused();
  for (int k = 0; k < 3; ++k) l.on_reported_voltage(9.0, 0.7 + 0.1 * k);
  EXPECT_TRUE(l.held_for(HoldReason::kDeviceFault)) << l.fault();
}

TEST(CanLimiter, FutureStampsAreRefusedAndStampsNeverAfterNow) {
  CommandLimiter l(config());
  l.on_reported_voltage(0.0, 0.0);
  EXPECT_EQ(l.command(10.0, 1.0, 100.0), CommandOutcome::kRejectedFutureStamp);
  EXPECT_EQ(l.command(10.0, 1.0, 1.3), CommandOutcome::kAccepted);  // within max_stamp_ahead_s: taken as now
  ramp(l, 1.0, 0.49);
  EXPECT_FALSE(l.timed_out());
  ramp(l, 1.5, 0.1);  // 0.5 s after now (not after the stamp) the watchdog holds
  EXPECT_TRUE(l.timed_out());
}

TEST(CanLimiter, ReportsAwayFromTheCommandedValuePauseThenTrip) {
  CommandLimiter l(config());
  l.set_name("axis b");
  l.on_reported_voltage(0.0, 0.0);
  l.step(0.0);
  l.command(20.0, 0.0);
  ramp(l, 0.01, 0.05);
  const double at = l.applied_v();
  l.on_reported_voltage(at, 0.06);  // a report showing what was written: fine
  EXPECT_FALSE(l.paused());
  l.on_reported_voltage(-7.0, 0.07);  // the amplifier is somewhere else
  EXPECT_TRUE(l.paused());
  EXPECT_FALSE(l.step(0.08).has_value()) << "ramp continues while the device does not follow";
  l.on_reported_voltage(-7.0, 0.09);
  EXPECT_FALSE(l.held());
  l.on_reported_voltage(-7.0, 0.1);  // third in a row: device fault
  EXPECT_TRUE(l.held_for(HoldReason::kDeviceFault));
  EXPECT_NE(l.fault().find("axis b"), std::string::npos) << l.fault();
  EXPECT_NE(l.fault().find("-7.000"), std::string::npos) << l.fault();
  EXPECT_NE(l.fault().find(std::to_string(at).substr(0, 4)), std::string::npos) << l.fault();
  EXPECT_DOUBLE_EQ(l.applied_v(), -7.0);  // re-baselined on the device's real voltage
  EXPECT_EQ(l.command(20.0, 0.11), CommandOutcome::kRejectedHeld);
  l.clear_fault();
  EXPECT_EQ(l.command(20.0, 0.12), CommandOutcome::kAccepted);
  const auto v = send(l, 0.13);
  ASSERT_TRUE(v.has_value());
  EXPECT_NEAR(*v, -7.0 + 100.0 * (0.13 - 0.08), 1e-9);  // one slew step (since the last step) from the report
}

TEST(CanLimiter, TheRampWaitsForTheDeviceToConfirm) {
  CommandLimiter l(config());
  l.on_reported_voltage(0.0, 0.0);
  l.step(0.0);
  l.command(30.0, 0.0);
  for (int k = 1; k <= 30; ++k) {  // frames written, no report comes back
    const double t = 0.01 * k;
    l.command(30.0, t);
    if (const auto v = l.step(t)) l.sent(*v, t);
  }
  EXPECT_DOUBLE_EQ(l.applied_v(), l.config().max_unconfirmed_v);  // stopped ahead of the baseline by that much
  l.on_reported_voltage(l.applied_v(), 0.31);  // the device confirms
  const auto v = l.step(0.32);
  ASSERT_TRUE(v.has_value());
  EXPECT_GT(*v, l.config().max_unconfirmed_v);
}

TEST(CanLimiter, AReportThatLagsTheRampStillMatches) {
  CommandLimiter l(config());
  l.on_reported_voltage(0.0, 0.0);
  l.step(0.0);
  l.command(30.0, 0.0);
  ramp(l, 0.01, 0.2);
  l.on_reported_voltage(l.applied_v() - 5.0, 0.21);  // written 50 ms ago, within report_lag_s
  EXPECT_FALSE(l.paused());
}

TEST(CanLimiter, InvalidConfigNamesTheField) {
  LimiterConfig c;
  c.slew_rate_v_per_s = -1;
  try {
    CommandLimiter l(c);
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("slew_rate_v_per_s"), std::string::npos);
  }
  c = LimiterConfig{};
  c.min_voltage_v = 10;
  c.max_voltage_v = -10;
  EXPECT_THROW(CommandLimiter{c}, std::invalid_argument);
  c = LimiterConfig{};
  c.max_voltage_v = kVoltageCeilingV + 1;  // beyond the compile-time ceiling
  EXPECT_THROW(CommandLimiter{c}, std::invalid_argument);
  c = LimiterConfig{};
  c.slew_rate_v_per_s = 1e7;
  EXPECT_THROW(CommandLimiter{c}, std::invalid_argument);
  c = LimiterConfig{};
  c.max_frame_step_v = kFrameStepCeilingV * 2;
  EXPECT_THROW(CommandLimiter{c}, std::invalid_argument);
}
