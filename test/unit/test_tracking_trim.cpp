// The tracking trim (compensation/tracking_trim.h) on its own, in the compensator's closed loop on a simulated stage
// whose hysteresis, creep and gain differ from the model's, and the command path's property test with it on: random
// intents (NaN among them), lost, stuck and glitching readings; no voltage outside the limits, the trims within
// their bounds and slew. About a second (the closed loop simulates 2 seeds × 2 × 40 min).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <random>
#include <string>

#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/ideal_line.h"
#include "piezo_compensation/compensation/tracking_trim.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/stage.h"

namespace {

using namespace piezo;
using compensation::TrackingInput;
using compensation::TrackingState;
using compensation::TrackingTrim;
using compensation::TrackingTrimOptions;

constexpr double kDt = 1.0 / 11.0;

TrackingTrimOptions on(double max_nm = 40.0) {
  TrackingTrimOptions o;
  o.enabled = true;
  o.max_nm = max_nm;
  return o;
}

TrackingInput moving(double error_nm, double sigma_nm = 2.0) {
  TrackingInput in;
  in.fusing = true;
  in.has_intent = true;
  in.error_forecast_nm = error_nm;
  in.sigma_nm = sigma_nm;
  return in;
}

TEST(TrackingTrim, BoundedSlewLimitedAndOppositeTheError) {
  TrackingTrim t(on(40.0), kDt);
  double last = 0.0;
  for (int i = 0; i < 200; ++i) {
    t.step(moving(500.0));
    EXPECT_LE(std::abs(t.trim_nm() - last), t.options().slew_nm_per_s * kDt + 1e-12);
    EXPECT_LE(std::abs(t.trim_nm()), 40.0);
    last = t.trim_nm();
  }
  EXPECT_EQ(t.state(), TrackingState::kActive);
  EXPECT_DOUBLE_EQ(t.trim_nm(), -40.0);  // the target moves against the model's error, to the bound
}

TEST(TrackingTrim, ActsOnlyBeyondTheFusedSigmaAndAtItsPeriod) {
  TrackingTrim t(on(), kDt);
  for (int i = 0; i < 50; ++i) t.step(moving(100.0, 150.0));  // a/b before the crossings: σ larger than the error
  EXPECT_DOUBLE_EQ(t.trim_nm(), 0.0);
  t.step(moving(10.0, 4.0));  // a new aim only at the period
  EXPECT_DOUBLE_EQ(t.aim_nm(), 0.0);
  for (int i = 0; i < 11; ++i) t.step(moving(10.0, 4.0));
  EXPECT_DOUBLE_EQ(t.aim_nm(), -6.0);  // 10 nm less one σ of dead band
}

TEST(TrackingTrim, StuckOrGlitchingEncoderFallsBackAndSaysSo) {
  TrackingTrim t(on(), kDt);
  for (int i = 0; i < 40; ++i) t.step(moving(30.0));
  ASSERT_LT(t.trim_nm(), -20.0);
  TrackingInput stuck = moving(30.0);
  stuck.since_reading_samples = 12;  // > 1 s without a reading taken
  t.step(stuck);
  EXPECT_EQ(t.state(), TrackingState::kFallback);
  EXPECT_NE(t.reason().find("stale"), std::string::npos) << t.reason();
  for (int i = 0; i < 40; ++i) t.step(stuck);
  EXPECT_DOUBLE_EQ(t.trim_nm(), 0.0);  // slewed back to the feedforward

  TrackingTrim g(on(), kDt);
  TrackingInput in = moving(30.0);
  for (int i = 0; i < 40; ++i) {
    in.refused_readings += i % 3 == 0;  // a reading refused every third sample
    g.step(in);
  }
  EXPECT_EQ(g.state(), TrackingState::kFallback);
  EXPECT_NE(g.reason().find("glitching"), std::string::npos) << g.reason();
  EXPECT_EQ(g.fallbacks(), 1u);
  in.refused_readings += 0;
  for (int i = 0; i < 200; ++i) g.step(in);  // 10 s clean: acting again
  EXPECT_EQ(g.state(), TrackingState::kActive);
}

TEST(TrackingTrim, HandOverAndBackKeepTheValue) {
  TrackingTrim t(on(), kDt);
  for (int i = 0; i < 40; ++i) t.step(moving(30.0));
  const double v = t.trim_nm();
  EXPECT_DOUBLE_EQ(t.hand_over(), v);
  EXPECT_DOUBLE_EQ(t.trim_nm(), 0.0);
  t.on_new_intent(v + 3.0);  // the hold trim's value, handed back
  EXPECT_DOUBLE_EQ(t.trim_nm(), v + 3.0);
  TrackingTrimOptions bad = on();
  bad.period_s = 0.0;
  EXPECT_THROW(TrackingTrim(bad, kDt), std::invalid_argument);
}

// The shipped foreign model on a stage with 2 % more stroke, a wider loop and 20 % more creep than it was fitted on
// (the tracking_trim rostest's and demo's device).
sim::SimulatorConfig mismatched_stage() {
  return sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/mm3e_foreign_track_stage.yaml").simulator;
}

struct LoopFigures {
  double move_mean = 0, move_max = 0, hold_mean = 0, hold_max = 0;
  double largest_target_step_nm = 0;  // intended + trims, between samples within a hold or a move
};

// An operator's moves: ramps to random targets at 0.2–2 V/s, then holds of 300 s; |true − intended| during the
// ramps and in the holds from 120 s on.
LoopFigures closed_loop(bool tracking, std::uint64_t seed, double duration_s) {
  models::ModelPtr model = models::load_model(std::string(PIEZO_SOURCE_DIR) + "/config/models/mm3e_foreign_c.yaml");
  compensation::IdealLineOptions lo;
  lo.hold_s = 60.0;
  const compensation::IdealLine line = compensation::ideal_line_from_model(*model, lo);
  compensation::AxisCompensatorConfig cfg;
  cfg.tracking_trim.enabled = tracking;
  cfg.tracking_trim.max_nm = cfg.hold_trim.max_nm = 80.0;  // the mismatch reaches ~60 nm at the ends of the range
  compensation::AxisCompensator comp(std::move(model), line, cfg);
  sim::ManipulatorSimulator stage(mismatched_stage(), seed);
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> target(-60.0, 60.0), rate(0.2, 2.0);
  double v_intent = 0.0, goal = 0.0, speed = 1.0, held_s = 1e9, applied = 0.0;
  LoopFigures f;
  double move_n = 0, hold_n = 0, last_target = NAN;
  sim::StepResult r = stage.step({0.0, 0.0, 0.0}, kDt);
  for (double t = 0; t < duration_s; t += kDt) {
    const bool moving = v_intent != goal;
    if (!moving && held_s >= 300.0) goal = target(rng), speed = rate(rng), held_s = 0.0;
    if (v_intent != goal) {
      v_intent += std::clamp(goal - v_intent, -speed * kDt, speed * kDt);
      held_s = 0.0;
    } else {
      held_s += kDt;
    }
    comp.set_intended_voltage(v_intent);
    const compensation::SampleUpdate u = comp.on_sample(applied, r.axes[2].measured_position_nm, true);
    (void)u;
    const compensation::CommandUpdate c = comp.command(true);
    const double aim = c.intended_nm + comp.hold_trim().trim_nm() + comp.tracking_trim().trim_nm();
    if (std::isfinite(last_target) && held_s > 0.5)
      f.largest_target_step_nm = std::max(f.largest_target_step_nm, std::abs(aim - last_target));
    last_target = aim;
    applied = c.send_v;
    r = stage.step({0.0, 0.0, applied}, kDt);
    const double err = std::abs(r.axes[2].true_position_nm - c.intended_nm);
    if (t < 600.0) continue;  // the estimator's cold start
    if (v_intent != goal || held_s < 1.0) {
      f.move_mean += err, ++move_n, f.move_max = std::max(f.move_max, err);
    } else if (held_s >= 120.0) {
      f.hold_mean += err, ++hold_n, f.hold_max = std::max(f.hold_max, err);
    }
  }
  f.move_mean /= std::max(1.0, move_n);
  f.hold_mean /= std::max(1.0, hold_n);
  return f;
}

TEST(TrackingTrimClosedLoop, QuartersTheMoveErrorOnAMismatchedStageAndKeepsTheHolds) {
  for (std::uint64_t seed : {7u, 8u}) {
    const LoopFigures off = closed_loop(false, seed, 2400.0), with = closed_loop(true, seed, 2400.0);
    std::printf("seed %lu moves |true − intended|: feedforward mean %.1f max %.1f nm, tracking trim mean %.1f max %.1f nm\n"
                "  holds from 120 s: hold trim alone mean %.2f max %.2f nm, with the tracking trim mean %.2f max %.2f nm\n"
                "  largest step of the corrected target in a hold: %.3f nm\n",
                static_cast<unsigned long>(seed), off.move_mean, off.move_max, with.move_mean, with.move_max,
                off.hold_mean, off.hold_max, with.hold_mean, with.hold_max, with.largest_target_step_nm);
    EXPECT_LE(with.move_mean, 0.25 * off.move_mean);
    EXPECT_LE(with.move_max, off.move_max);
    EXPECT_LE(with.hold_max, off.hold_max + 0.5);  // the parked tip no worse than the hold trim alone, within 0.5 nm
    EXPECT_LE(with.hold_mean, off.hold_mean + 0.5);
    // no jump, the hand-over included: the target moves at most both slews per sample
    EXPECT_LE(with.largest_target_step_nm, (20.0 + 1.0) * kDt + 1e-9);
  }
}

// The command path with both trims on: random intents (NaN and out of range among them, refused with an error),
// readings lost, stuck for a while, glitching by microns; the model's inverse is the only way a voltage is chosen.
TEST(TrackingTrimProperty, NoVoltageOutsideTheLimitsNoTrimBeyondItsBoundOrSlew) {
  models::ModelPtr model = models::load_model(std::string(PIEZO_SOURCE_DIR) + "/config/models/mm3e_foreign_c.yaml");
  compensation::IdealLineOptions lo;
  lo.hold_s = 60.0;
  const compensation::IdealLine line = compensation::ideal_line_from_model(*model, lo);
  compensation::AxisCompensatorConfig cfg;
  cfg.voltage_min_v = -50.0;
  cfg.voltage_max_v = 60.0;
  cfg.tracking_trim.enabled = true;
  cfg.tracking_trim.max_nm = 30.0;
  cfg.hold_trim.max_nm = 30.0;
  cfg.hold_trim.settle_s = 1.0;
  compensation::AxisCompensator comp(std::move(model), line, cfg);
  sim::ManipulatorSimulator stage(mismatched_stage(), 3);
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  double applied = 0.0, last_track = 0.0, last_hold = 0.0, stuck_at = NAN;
  int stuck_left = 0;
  std::size_t fallbacks_seen = 0, refused = 0;
  const double slew = cfg.tracking_trim.slew_nm_per_s * kDt + 1e-9;
  for (int i = 0; i < 20000; ++i) {
    const double k = u01(rng);
    if (k < 0.01) {
      EXPECT_THROW(comp.set_intended_voltage(std::nan("")), std::invalid_argument);
    } else if (k < 0.02) {
      comp.set_intended_voltage(200.0 * (u01(rng) - 0.5) * 4.0);  // far outside the limits
    } else if (k < 0.3) {
      comp.set_intended_voltage(-70.0 + 140.0 * u01(rng));
    }
    const sim::StepResult r = stage.step({0.0, 0.0, applied}, kDt);
    double y = r.axes[2].measured_position_nm;
    bool valid = u01(rng) > 0.05;
    if (stuck_left == 0 && u01(rng) < 0.002) stuck_left = 200, stuck_at = y;
    if (stuck_left > 0) --stuck_left, y = stuck_at;  // a frozen counter
    if (u01(rng) < 0.003) y += (u01(rng) < 0.5 ? -1.0 : 1.0) * 2000.0;  // a glitch
    comp.on_sample(applied, y, valid);
    const compensation::CommandUpdate c = comp.command(true);
    ASSERT_TRUE(std::isfinite(c.send_v)) << i;
    ASSERT_GE(c.send_v, cfg.voltage_min_v) << i;
    ASSERT_LE(c.send_v, cfg.voltage_max_v) << i;
    const double tr = comp.tracking_trim().trim_nm(), ho = comp.hold_trim().trim_nm();
    ASSERT_LE(std::abs(tr), 30.0) << i;
    ASSERT_LE(std::abs(ho), 30.0) << i;
    // the correction the model is inverted for (the sum of the trims) moves within the two slews: hand-over and
    // hand-back move value between the trims, never the sum
    const double sum_step = std::abs((tr + ho) - (last_track + last_hold));
    ASSERT_LE(sum_step, slew + cfg.hold_trim.slew_nm_per_s * kDt) << i;
    fallbacks_seen += comp.tracking_trim().state() == TrackingState::kFallback;
    last_track = tr, last_hold = ho;
    applied = c.send_v;
  }
  if (comp.estimator()) refused = comp.estimator()->rejected_readings() + comp.estimator()->stale_readings();
  std::printf("tracking-trim fallbacks: %zu samples; readings refused by the estimator: %zu\n", fallbacks_seen, refused);
  EXPECT_GT(fallbacks_seen, 0u);  // the stuck and glitching stretches were seen
}

}  // namespace
