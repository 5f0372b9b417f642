// Inverse, drift forecast, ideal line and the per-axis compensator on small known models.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <iostream>

#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/base_handover.h"
#include "piezo_compensation/compensation/drift_forecast.h"
#include "piezo_compensation/compensation/ideal_line.h"
#include "piezo_compensation/compensation/inverse.h"
#include "piezo_compensation/compensation/live_inputs.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model_stream.h"
#include "test_compensation_models.h"

using namespace piezo;
using namespace piezo::compensation;

namespace {

// Drives `m` through a voltage history so the inverse is tested on a non-trivial state.
void excite(models::Model& m, const std::vector<double>& volts) {
  for (double v : volts) {
    const models::ModelInput in{v, nullptr};
    m.commit(in, m.predict(in));
  }
}

}  // namespace

TEST(CompensationInverse, ClosedFormForAffineModel) {
  test::LinearCreepModel m(12.0, 2.0, 60.0, 11.0);
  m.reset(0.0, 0.0);
  excite(m, {10, 30, 50, 20});
  const InverseResult r = invert(m, 321.0, {});
  ASSERT_TRUE(r.ok) << r.error;
  EXPECT_TRUE(r.closed_form);
  EXPECT_LE(r.evaluations, 3);
  EXPECT_NEAR(m.predict({r.voltage_v, nullptr}), 321.0, 1e-9);
}

TEST(CompensationInverse, BracketedForHysteresisModel) {
  auto m = test::make_pi_creep();
  m->reset(0.0, 0.0);
  excite(*m, {10, 40, 60, 30, -20, 5});
  for (double target : {-700.0, -100.0, 0.0, 250.0, 800.0}) {
    const InverseResult r = invert(*m, target, {});
    ASSERT_TRUE(r.ok) << target << ": " << r.error;
    EXPECT_FALSE(r.closed_form);
    EXPECT_NEAR(m->predict({r.voltage_v, nullptr}), target, 0.011);
    EXPECT_LE(r.evaluations, 40);
    EXPECT_GE(r.voltage_v, -80.0);
    EXPECT_LE(r.voltage_v, 80.0);
  }
}

TEST(CompensationInverse, ReportsTargetOutsideTheLimits) {
  auto m = test::make_pi_creep();
  m->reset(0.0, 0.0);
  const InverseResult r = invert(*m, 1e6, {});
  EXPECT_FALSE(r.ok);
  EXPECT_NE(r.error.find("no inverse inside the voltage limits"), std::string::npos) << r.error;
  EXPECT_EQ(r.voltage_v, 80.0);
  test::LinearCreepModel lin(12.0, 2.0, 60.0, 11.0);
  lin.reset(0.0, 0.0);
  const InverseResult rl = invert(lin, -1e6, {});
  EXPECT_FALSE(rl.ok);
  EXPECT_EQ(rl.voltage_v, -80.0);
  EXPECT_NE(rl.error.find("no inverse"), std::string::npos);
}

TEST(CompensationInverse, ReportsNonFiniteModel) {
  test::FailingModel m(test::make_pi_creep(), 0);
  m.reset(0.0, 0.0);
  const InverseResult r = invert(m, 10.0, {});
  EXPECT_FALSE(r.ok);
  EXPECT_NE(r.error.find("not finite"), std::string::npos) << r.error;
}

TEST(CompensationDriftForecast, MatchesSingleModeCreepAnalytically) {
  const double rate = 11.0, a = 12.0, b = 2.0, tau = 60.0;
  test::LinearCreepModel m(a, b, tau, rate);
  m.reset(0.0, 0.0);
  const double before = m.predict({10.0, nullptr});
  const DriftForecast f = forecast_drift(m, 50.0, {0.0, 1.0, 60.0, 1800.0}, rate);
  ASSERT_TRUE(f.ok) << f.error;
  // z after the step: α·50; then z_n = 50 − (50 − z_0)(1 − α)^n, so drift = b (50 − z_0)(1 − (1 − α)^n).
  const double al = m.alpha(), z0 = al * 50.0;
  for (std::size_t i = 0; i < f.horizons_s.size(); ++i) {
    const double n = std::round(f.horizons_s[i] * rate);
    EXPECT_NEAR(f.drift_nm[i], b * (50.0 - z0) * (1.0 - std::pow(1.0 - al, n)), 1e-9) << f.horizons_s[i];
  }
  EXPECT_EQ(f.steps, 19800u);
  EXPECT_EQ(m.predict({10.0, nullptr}), before) << "forecast must not change the model";
}

TEST(CompensationDriftForecast, RejectsBadHorizonAndReportsNaN) {
  auto m = test::make_pi_creep();
  m->reset(0, 0);
  EXPECT_FALSE(forecast_drift(*m, 0.0, {-1.0}, 11.0).ok);
  EXPECT_FALSE(forecast_drift(*m, 0.0, {1.0}, 0.0).ok);
  test::FailingModel bad(test::make_pi_creep(), 5);
  bad.reset(0, 0);
  const DriftForecast f = forecast_drift(bad, 1.0, {60.0}, 11.0);
  EXPECT_FALSE(f.ok);
  EXPECT_NE(f.error.find("not finite"), std::string::npos) << f.error;
}

TEST(CompensationIdealLine, LongHoldGainOfLinearCreepModel) {
  test::LinearCreepModel m(12.0, 2.0, 60.0, 11.0);
  IdealLineOptions o;
  o.hold_s = 1800.0;
  const IdealLine line = ideal_line_from_model(m, o);
  EXPECT_NEAR(line.gain_nm_per_v, 14.0, 1e-6);
  EXPECT_NEAR(line.offset_nm, 0.0, 1e-6);
  EXPECT_NEAR(line.voltage_v(line.position_nm(33.0)), 33.0, 1e-12);
  test::FailingModel bad(test::make_pi_creep(), 3);
  EXPECT_THROW(ideal_line_from_model(bad, o), std::runtime_error);
}

// A gain on ROS time (the residual tool's time_gain, fitted on a ~snapshot) is read at its training centre: the
// live loop once computed the line at time 0, i.e. 7·10⁶ standard deviations away, and got 10⁸ nm targets.
TEST(CompensationIdealLine, GainOnTimeIsReadAtItsTrainingCentre) {
  auto base = std::make_unique<test::LinearCreepModel>(12.0, 2.0, 60.0, 11.0);
  IdealLineOptions o;
  o.hold_s = 1800.0;
  const IdealLine base_line = ideal_line_from_model(*base, o);
  models::EffectTerm g;
  g.type = "gain";
  g.signal = models::kSignalTime;
  g.scales = models::kSignalPosition;
  g.pre_center = 1795564646.5;
  g.pre_scale = 242.5;
  g.center = {-83.5};
  g.scale = {649.6};
  g.weight = {18.6};
  models::AugmentedModel aug(std::move(base), {g}, 0.0, 11.0);
  EXPECT_DOUBLE_EQ(neutral_input(aug, models::kSignalTime), 1795564646.5);
  const IdealLine line = ideal_line_from_model(aug, o);
  EXPECT_NEAR(line.gain_nm_per_v, base_line.gain_nm_per_v, 1e-9);
}

// ~reload_model onto the running base: the stage is the base + 20 nm. The fresh augmented model's offset was fitted
// (as `piezo residual` does) against the base started at rest at the window's first voltage, so it carries that
// cold start's error. After the hand-over its base is the running one and its offset the true 20 nm, so it
// predicts the stage exactly from then on; warmed from rest alone it is off.
TEST(CompensationBaseHandover, TakesTheRunningBaseAndReestimatesTheOffset) {
  const double fs = 11.0;
  const std::size_t n_hist = 3000, n_win = 2000, n_after = 1500;
  const test::PiCreepWalk stage = test::pi_creep_walk(n_hist + n_win + n_after, fs, 20.0);
  const std::vector<double>& v = stage.voltage_v;
  const std::vector<double>& truth = stage.position_nm;
  // the running model: the base since the stage's rest, up to the reload at the window's end
  auto run_base = test::make_pi_creep(fs);
  run_base->reset(v[0], 0.0);
  for (std::size_t i = 0; i < n_hist + n_win; ++i) {
    const models::ModelInput in{v[i], nullptr};
    run_base->commit(in, run_base->predict(in));
  }
  io::Dataset win;
  io::AxisSeries& c = win.add_axis("c");
  for (std::size_t i = n_hist; i < n_hist + n_win; ++i) {
    win.time_s.push_back(static_cast<double>(i) / fs);
    c.voltage_v.push_back(v[i]);
    c.position_nm.push_back(truth[i]);
  }
  std::vector<double> running_base(n_win);
  for (std::size_t i = 0; i < n_win; ++i) running_base[i] = truth[n_hist + i] - 20.0;
  // the offset a fit against the cold-started base would give: mean of measured − cold base over the window
  std::vector<double> cold;
  {
    auto b = test::make_pi_creep(fs);
    cold = models::stream_model(*b, win, "c").prediction;
  }
  double off = 0.0;
  for (std::size_t i = 0; i < n_win; ++i) off += (truth[n_hist + i] - cold[i]) / n_win;
  models::AugmentedModel fresh(test::make_pi_creep(fs), {}, off, fs);
  std::vector<double> warm_base;  // the base part of the warm-up stream
  fresh.set_base_trace(&warm_base);
  const std::vector<double> warm = models::stream_model(fresh, win, "c").prediction;
  fresh.set_base_trace(nullptr);
  ASSERT_EQ(warm_base.size(), n_win);
  // the base inside the augmented model ran its own free run: what streaming the base alone again gives
  for (std::size_t i = 0; i < n_win; ++i) ASSERT_EQ(warm_base[i], cold[i]) << "row " << i;
  std::unique_ptr<models::Model> from_rest = fresh.clone();
  const BaseHandover h = hand_over_base(fresh, *run_base, win, "c", warm, warm_base, running_base);
  ASSERT_TRUE(h.done) << h.why;
  EXPECT_NEAR(fresh.offset_nm() , 20.0, 1e-6);
  double worst = 0.0, worst_rest = 0.0;
  for (std::size_t i = n_hist + n_win; i < v.size(); ++i) {
    const models::ModelInput in{v[i], nullptr};
    const double p = fresh.predict(in), q = from_rest->predict(in);
    fresh.commit(in, p);
    from_rest->commit(in, q);
    worst = std::max(worst, std::abs(p - truth[i]));
    worst_rest = std::max(worst_rest, std::abs(q - truth[i]));
  }
  EXPECT_LT(worst, 1e-6);
  EXPECT_GT(worst_rest, 1.0) << "the window's cold start should matter in this test";
  std::cout << "after the reload, worst error: hand-over " << worst << " nm, warmed from rest " << worst_rest << " nm\n";
  // another base is not taken
  models::AugmentedModel other(std::make_unique<test::LinearCreepModel>(12.0, 2.0, 60.0, fs), {}, off, fs);
  EXPECT_FALSE(hand_over_base(other, *run_base, win, "c", warm, warm_base, running_base).done);
}

// With a perfect model the compensated plant follows the ideal line; uncompensated it shows the hysteresis.
TEST(CompensationAxis, PerfectModelRemovesHysteresisAndCreep) {
  const double rate = 11.0;
  auto proto = test::make_pi_creep(rate);
  IdealLineOptions lo;
  const IdealLine line = ideal_line_from_model(*proto, lo);
  const double stroke = std::abs(line.gain_nm_per_v) * 160.0;

  for (bool compensate : {false, true}) {
    auto plant = test::make_pi_creep(rate);
    plant->reset(0.0, 0.0);
    AxisCompensator comp(test::make_pi_creep(rate), line, {});
    comp.on_sample(0.0, 0.0, true);
    double max_dev = 0.0;
    // Sawtooth of increasing amplitude (10 s periods, amplitudes 20..60 V), then a 30 min hold.
    std::vector<double> intent;
    for (double amp : {20.0, 40.0, 60.0})
      for (int i = 0; i < 110; ++i) intent.push_back(amp * (i < 55 ? i / 55.0 : (110 - i) / 55.0));
    const std::size_t hold_start = intent.size();
    intent.resize(hold_start + 19800, 25.0);
    double x_hold0 = 0.0, x = 0.0;
    for (std::size_t k = 0; k < intent.size(); ++k) {
      comp.set_intended_voltage(intent[k]);
      const CommandUpdate c = comp.command(compensate);
      ASSERT_EQ(c.fallback, false) << c.status;
      const models::ModelInput in{c.send_v, nullptr};
      x = plant->predict(in);
      plant->commit(in, x);
      comp.on_sample(c.send_v, x, true);
      if (k < hold_start) max_dev = std::max(max_dev, std::abs(x - line.position_nm(intent[k])));
      if (k == hold_start) x_hold0 = x;
    }
    const double drift = std::abs(x - x_hold0);
    if (compensate) {
      EXPECT_LT(100.0 * max_dev / stroke, 0.01);
      EXPECT_LT(drift, 0.1);
    } else {
      EXPECT_GT(100.0 * max_dev / stroke, 2.0);
      EXPECT_GT(drift, 5.0);
    }
  }
}

TEST(CompensationAxis, FallsBackWithBoundedStepOnModelFailure) {
  const IdealLine line{14.0, 0.0};
  AxisCompensatorConfig cfg;
  cfg.fallback_max_step_v = 2.0;
  AxisCompensator comp(std::make_unique<test::FailingModel>(test::make_pi_creep(), 3), line, cfg);
  comp.on_sample(0.0, 0.0, true);
  comp.set_intended_voltage(30.0);
  double v = 0.0;
  for (int k = 0; k < 3; ++k) {
    const CommandUpdate c = comp.command(true);
    EXPECT_FALSE(c.fallback) << c.status;
    v = c.send_v;
    comp.on_sample(v, 14.0 * v, true);
  }
  // The model now yields NaN: the sample is reported, the command steps toward 30 V by at most 2 V.
  const SampleUpdate s = comp.on_sample(v, 14.0 * v, true);
  EXPECT_FALSE(s.ok);
  EXPECT_NE(s.status.find("not finite"), std::string::npos) << s.status;
  const CommandUpdate c = comp.command(true);
  EXPECT_TRUE(c.fallback);
  EXPECT_FALSE(c.compensation_active);
  EXPECT_NEAR(c.send_v, v + std::clamp(30.0 - v, -2.0, 2.0), 1e-12);
  EXPECT_GT(std::abs(30.0 - v), 2.0) << "the test needs a step larger than the bound";
  EXPECT_NE(c.status.find("not finite"), std::string::npos) << c.status;
  EXPECT_GE(comp.command_fallbacks(), 1u);
}

TEST(CompensationAxis, UnreachableIntentFallsBack) {
  const IdealLine line{14.0, 0.0};
  AxisCompensator comp(test::make_pi_creep(), line, {});
  comp.on_sample(0.0, 0.0, true);
  comp.set_intended_position_nm(5000.0);  // beyond 80 V on a ~14 nm/V piezo
  const CommandUpdate c = comp.command(true);
  EXPECT_TRUE(c.fallback);
  EXPECT_NE(c.status.find("no inverse inside the voltage limits"), std::string::npos) << c.status;
  EXPECT_NEAR(c.send_v, 1.0, 1e-12);  // default 1 V bounded step from 0 V
  EXPECT_THROW(comp.set_intended_voltage(std::nan("")), std::invalid_argument);
}

// A plant 60 nm off the model: pure feedforward keeps the offset; the hold trim on the fused estimate removes it.
TEST(CompensationAxis, HoldTrimRemovesSlowModelError) {
  const IdealLine line{14.0, 0.0};
  for (bool trim : {false, true}) {
    AxisCompensatorConfig cfg;
    cfg.hold_trim.enabled = trim;
    cfg.hold_trim.max_nm = 100.0;
    auto model = test::make_pi_creep();
    estimation::NoiseModel nm;
    nm.reading_sigma_nm = 1.0;
    nm.q_rest_nm2_per_s = 1e-4;
    nm.initial_sigma_nm = 100.0;
    model->meta.estimator = nm.to_yaml();
    AxisCompensator comp(std::move(model), line, cfg);
    auto plant = test::make_pi_creep();
    plant->reset(0.0, 0.0);
    comp.on_sample(0.0, 60.0, true);
    comp.set_intended_voltage(20.0);
    double x = 0.0;
    for (int k = 0; k < 11 * 300; ++k) {
      const CommandUpdate c = comp.command(true);
      const models::ModelInput in{c.send_v, nullptr};
      x = plant->predict(in) + 60.0;
      plant->commit(in, x - 60.0);
      comp.on_sample(c.send_v, x, true);
    }
    if (!trim)
      EXPECT_NEAR(x - 280.0, 60.0, 0.5);
    else
      EXPECT_NEAR(x, 280.0, 0.5) << "trim " << comp.hold_trim().trim_nm();
  }
}

// An aux signal is read at the sample's stamp (the newest value stamped at or before it), as the bag snapshot and
// the offline resolver read it: a temperature step whose message arrives after the voltage sample it precedes,
// or before the sample it follows, feeds the same value either way.
TEST(CompensationLiveInputs, AuxIsReadAtTheSampleStampWhateverTheArrivalOrder) {
  models::EffectTerm t;
  t.type = "linear";
  t.signal = "temperature_c";
  t.family = "aux_signal";
  t.center = {22.0};
  t.scale = {1.0};
  t.weight = {40.0};
  models::AugmentedModel model(test::make_pi_creep(), {t}, 0.0, 11.0);
  AuxFeedOptions o;
  o.stale_after_s = 1.0;
  o.recovery_s = 0.0;
  InputFeeder feeder(model, "c", o);
  ASSERT_EQ(feeder.size(), 1u);
  LiveInputs live;
  EXPECT_EQ(live.aux("temperature_c", 100.0), nullptr);
  // stamps 100.0 (22 °C), 100.2 (23 °C, arrives first), 100.1 (22.5 °C, overtaken)
  live.add_aux("temperature_c", 22.0, 100.0, 100.0);
  live.add_aux("temperature_c", 23.0, 100.2, 100.2);
  live.add_aux("temperature_c", 22.5, 100.1, 100.1);
  io::PairedSample s;
  double fed = 0.0;
  const std::vector<std::pair<double, double>> want{{99.9, 22.0}, {100.0, 22.0}, {100.05, 22.0},
                                                    {100.1, 22.5}, {100.15, 22.5}, {100.3, 23.0}};
  for (const auto& [stamp, value] : want) {
    s.stamp_s = stamp;
    ASSERT_TRUE(feeder.fill(live, s, 100.3, false, &fed));
    EXPECT_DOUBLE_EQ(fed, value) << "sample stamped " << stamp;
    EXPECT_FALSE(feeder.any_fallback());
  }
  // staleness counts from the chosen value's own time: 100.0 is 1.5 s old at 101.5
  s.stamp_s = 100.05;
  ASSERT_TRUE(feeder.fill(live, s, 101.5, false, &fed));
  EXPECT_TRUE(feeder.any_fallback());
  EXPECT_NE(feeder.states()[0].status.find("stale"), std::string::npos) << feeder.states()[0].status;
  // only the last kAuxKept values are kept
  for (std::size_t i = 0; i < LiveInputs::kAuxKept + 10; ++i)
    live.add_aux("temperature_c", 30.0 + static_cast<double>(i), 200.0 + static_cast<double>(i), 200.0);
  EXPECT_DOUBLE_EQ(live.aux("temperature_c", 0.0)->value, 40.0);  // the oldest kept
}

// Another axis' fused position as a model input: offline the derived column of that name at the previous row (as a
// reading), refused with a message naming how to get it when the data lack it, never the own axis'; live the
// other axis' fused estimate of the previous sample, waited for like its reading.
TEST(CompensationLiveInputs, AnotherAxisFusedPositionIsReadAtThePreviousSample) {
  models::EffectTerm t;
  t.type = "linear";
  t.signal = io::fused_position_column("a");
  t.family = "cross_axis";
  t.center = {0.0};
  t.scale = {1.0};
  t.weight = {0.05};
  models::AugmentedModel model(test::make_pi_creep(), {t}, 0.0, 11.0);
  EXPECT_EQ(models::classify_input("a_fused_position_nm", "c", {"a", "b", "c"}).kind,
            models::InputSource::Kind::kAxisFused);
  EXPECT_THROW(models::classify_input("c_fused_position_nm", "c", {"a", "b", "c"}), io::DataError);

  io::Dataset d;
  d.add_axis("a");
  d.add_axis("c");
  for (int i = 0; i < 3; ++i) {
    d.time_s.push_back(i / 11.0);
    for (auto& ax : d.axes) ax.voltage_v.push_back(0.0), ax.position_nm.push_back(0.0);
  }
  try {
    models::InputResolver r(d, model.aux_inputs(), "c");
    ADD_FAILURE() << "a missing fused column was accepted";
  } catch (const io::DataError& e) {
    EXPECT_NE(std::string(e.what()).find("--other-model a="), std::string::npos) << e.what();
  }
  d.aux.push_back({"a_fused_position_nm", {10.0, 20.0, 30.0}});
  models::InputResolver r(d, model.aux_inputs(), "c");
  double v = 0.0;
  r.fill(2, &v);
  EXPECT_DOUBLE_EQ(v, 20.0);  // the previous row's

  InputFeeder feeder(model, "c", AuxFeedOptions{});
  LiveInputs live;
  io::PairedSample s;
  s.sequence = 8;
  double fed = 0.0;
  EXPECT_FALSE(feeder.fill(live, s, 1.0, false, &fed));  // a's estimate for sample 7 may still come
  live.add_fused("a", 7, 123.0);
  ASSERT_TRUE(feeder.fill(live, s, 1.0, false, &fed));
  EXPECT_DOUBLE_EQ(fed, 123.0);
  EXPECT_FALSE(feeder.any_fallback());
}
