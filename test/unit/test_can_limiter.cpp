// Command path safety rules: clamp, slew, NaN rejection, watchdog hold (never 0 V), holds.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

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
// Runs the ramp in 10 ms steps from t0 for `seconds`, returning the largest jump between outputs.
double ramp(CommandLimiter& l, double t0, double seconds) {
  double worst = 0.0;
  for (double t = t0; t <= t0 + seconds + 1e-9; t += 0.01) {
    const double before = l.applied_v();
    if (auto v = l.step(t)) {
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
  l.on_reported_voltage(5.0);
  EXPECT_EQ(l.command(10.0, 0.2), CommandOutcome::kAccepted);
}

TEST(CanLimiter, ClampsToTheLimits) {
  CommandLimiter l(config());
  l.on_reported_voltage(79.0);
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
  l.on_reported_voltage(0.0);
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
  l.on_reported_voltage(0.0);
  l.step(0.0);
  // 100 s of nothing, then a big command: one step may cover at most max_step_dt_s.
  l.command(70.0, 100.0);
  const auto v = l.step(100.0);
  ASSERT_TRUE(v.has_value());
  EXPECT_LE(*v, 100.0 * 0.1 + 1e-9);
  l.command(70.0, 200.0);
  const double before = l.applied_v();
  const auto w = l.step(200.0);
  ASSERT_TRUE(w.has_value());
  EXPECT_LE(*w - before, 100.0 * 0.1 + 1e-9);
}

TEST(CanLimiter, RejectsNonFiniteAndKeepsTheTarget) {
  CommandLimiter l(config());
  l.on_reported_voltage(0.0);
  l.command(20.0, 0.0);
  for (double bad : {std::nan(""), std::numeric_limits<double>::infinity(), -std::numeric_limits<double>::infinity()})
    EXPECT_EQ(l.command(bad, 0.01), CommandOutcome::kRejectedNonFinite);
  EXPECT_DOUBLE_EQ(l.target_v(), 20.0);
}

TEST(CanLimiter, TimeoutHoldsTheAppliedVoltageNeverZero) {
  CommandLimiter l(config());
  l.on_reported_voltage(0.0);
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
  l.on_reported_voltage(-5.0);
  l.step(0.0);
  l.command(30.0, 0.0);
  l.step(0.05);
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

TEST(CanLimiter, ReportedVoltageOutsideLimitsIsBroughtInside) {
  CommandLimiter l(config());
  l.on_reported_voltage(95.0);  // device beyond our (narrower) limits
  l.step(0.0);
  l.command(90.0, 0.0);
  const auto v = l.step(0.01);
  ASSERT_TRUE(v.has_value());
  EXPECT_LE(*v, 80.0);
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
}
