// Inverse, drift forecast, ideal line and the per-axis compensator on small known models.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/drift_forecast.h"
#include "piezo_compensation/compensation/ideal_line.h"
#include "piezo_compensation/compensation/inverse.h"
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

// A plant 60 nm off the model: pure feedforward keeps the offset, re-anchoring on the encoder removes it.
TEST(CompensationAxis, ReanchoringRemovesSlowModelError) {
  const IdealLine line{14.0, 0.0};
  for (double tau : {0.0, 5.0}) {
    AxisCompensatorConfig cfg;
    cfg.reanchor_time_constant_s = tau;
    AxisCompensator comp(test::make_pi_creep(), line, cfg);
    auto plant = test::make_pi_creep();
    plant->reset(0.0, 0.0);
    comp.on_sample(0.0, 60.0, true);
    comp.set_intended_voltage(20.0);
    double x = 0.0;
    for (int k = 0; k < 11 * 60; ++k) {
      const CommandUpdate c = comp.command(true);
      const models::ModelInput in{c.send_v, nullptr};
      x = plant->predict(in) + 60.0;
      plant->commit(in, x - 60.0);
      comp.on_sample(c.send_v, x, true);
    }
    if (tau == 0.0)
      EXPECT_NEAR(x - 280.0, 60.0, 0.5);
    else
      EXPECT_NEAR(x, 280.0, 0.5) << "anchor " << comp.anchor_offset_nm();
  }
}
