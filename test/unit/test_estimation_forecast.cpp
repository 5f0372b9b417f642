// The estimator's forecast (estimation/forecast.h): the closed-form propagation against the filter stepped ahead
// without readings, the calibration on a series whose noise model is known, the model file's forecast keys, and the
// drift forecast with its σ (compensation/drift_forecast.h). Milliseconds to a few seconds.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include <yaml-cpp/yaml.h>

#include "piezo_compensation/compensation/drift_forecast.h"
#include "piezo_compensation/compensation/drift_forecast_table.h"
#include "piezo_compensation/compensation/track.h"
#include "piezo_compensation/estimation/error_filter.h"
#include "piezo_compensation/estimation/forecast.h"
#include "test_compensation_models.h"

namespace {

using piezo::estimation::ErrorFilter;
using piezo::estimation::NoiseModel;

constexpr double kDt = 1.0 / 11.0;

NoiseModel known_model() {
  NoiseModel m;
  m.reading_sigma_nm = std::sqrt(400.0 + 400.0 / 12.0);
  m.noise_sigma_nm = 20.0;
  m.step_nm = 20.0;
  m.q_rest_nm2_per_s = 0.02;
  m.q_motion_nm = 0.05;
  m.q_fast_nm = 0.5;
  m.fast_tau_s = 20.0;
  m.initial_sigma_nm = 30.0;
  m.adapt_k = 0.0;
  return m;
}

// Moves to random targets with holds between; truth = prediction + slow random walk + a settling fast error, as the
// noise model says; readings with 20 nm of noise before a 20 nm quantiser.
struct Series {
  std::vector<double> p, truth, y, v;
};
Series make_series(std::size_t n, std::uint32_t seed, const NoiseModel& m, double hold_s = 300.0) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  std::uniform_real_distribution<double> u(-400.0, 400.0);
  Series s;
  double p = 0, target = 0, slow = 5.0, fast = 0.0;
  const double phi = std::exp(-kDt / m.fast_tau_s);
  const std::size_t hold_n = static_cast<std::size_t>(hold_s / kDt);
  for (std::size_t i = 0; i < n; ++i) {
    if (i % hold_n == 0) target = u(rng);
    const double dp = std::clamp(target - p, -40.0, 40.0);
    p += dp;
    slow += std::sqrt(m.q_rest_nm2_per_s * kDt + m.q_motion_nm * std::abs(dp)) * g(rng);
    fast = phi * fast + std::sqrt(m.q_fast_nm * std::abs(dp)) * g(rng);
    s.p.push_back(p);
    s.v.push_back(target / 10.0);
    s.truth.push_back(p + slow + fast);
    s.y.push_back(20.0 * std::round((p + slow + fast + 20.0 * g(rng)) / 20.0));
  }
  return s;
}

TEST(Forecast, ClosedFormEqualsTheFilterSteppedAheadWithoutReadings) {
  NoiseModel m = known_model();
  m.q_drift_nm2_per_s3 = 1e-4;
  const Series s = make_series(3000, 3, m);
  ErrorFilter f(m, kDt);
  for (std::size_t i = 0; i < 2000; ++i) f.step(s.p[i], s.y[i], true);
  const piezo::estimation::FilterState now = f.state();
  const piezo::estimation::PathSums sums(s.p, std::exp(-kDt / m.fast_tau_s));
  ErrorFilter ahead = f;
  for (std::size_t n = 1; n <= 600; ++n) {
    ahead.step(s.p[1999 + n], NAN, false);
    if (n % 100 != 0 && n != 1) continue;
    const auto e = piezo::estimation::forecast_error(m, kDt, now, sums.between(1999, n), true);
    // the filter's own prediction ramps with the slow error's rate; the forecast's mean leaves the ramp out
    EXPECT_NEAR(e.mean_nm + n * kDt * now.drift_nm_per_s, ahead.error_nm(), 1e-9) << n;
    EXPECT_NEAR(std::sqrt(e.var_nm2), ahead.sigma_nm(), 1e-9) << n;
    EXPECT_DOUBLE_EQ(e.sigma_nm, std::sqrt(e.var_nm2));  // no calibration: scale 1
  }
}

TEST(Forecast, CalibrationOfAnHonestNoiseModelKeepsItsSigma) {
  NoiseModel m = known_model();
  const Series s = make_series(60000, 5, m, 1500.0);
  piezo::estimation::calibrate_forecast(m, kDt, s.p, s.y, s.v);
  ASSERT_EQ(m.forecast_horizons_s.size(), 6u);
  for (std::size_t k = 0; k < 6; ++k) {
    // the filter's own model is the truth's: the propagated σ needs no scale beyond the sampling spread
    EXPECT_GT(m.forecast_sigma_scale_hold[k], 0.6) << m.forecast_horizons_s[k];
    EXPECT_LT(m.forecast_sigma_scale_hold[k], 1.5) << m.forecast_horizons_s[k];
  }
  // a noise model that claims four times the variance rates is scaled back
  NoiseModel wide = known_model();
  wide.q_rest_nm2_per_s *= 16.0, wide.q_motion_nm *= 16.0, wide.q_fast_nm *= 16.0;
  piezo::estimation::calibrate_forecast(wide, kDt, s.p, s.y, s.v);
  EXPECT_LT(wide.forecast_sigma_scale_hold.back(), 0.6);
  // scored on another series, the calibrated σ holds about 95 % at every horizon
  const Series test = make_series(60000, 6, known_model(), 1500.0);
  const auto states = piezo::estimation::filter_states(m, kDt, test.p, test.y);
  const auto holds = piezo::compensation::find_holds(test.v, 11.0, 200.0);
  const piezo::compensation::ForecastTable t =
      piezo::compensation::score_forecasts(m, kDt, test.p, test.y, {}, test.v, states, holds);
  for (std::size_t k = 0; k < t.horizons_s.size(); ++k) {
    if (t.hold[k].n < 500 || t.horizons_s[k] > 300.0) continue;  // 20 min: three holds, too few independent windows
    EXPECT_GT(t.hold[k].coverage(), 0.9) << t.horizons_s[k];
    EXPECT_LT(t.hold[k].coverage(), 0.985) << t.horizons_s[k];
  }
}

// Given the holds, the scales come from the rows the forecast table scores only: one hold over the whole series,
// scored from its start, leaves the held windows (the same hold scales as without holds) and no moving window
// (the move scales left at 1).
TEST(Forecast, CalibrationOnTheTablesRowsOnly) {
  const Series s = make_series(20000, 7, known_model(), 600.0);
  NoiseModel all = known_model(), table = known_model();
  piezo::estimation::calibrate_forecast(all, kDt, s.p, s.y, s.v);
  piezo::estimation::ForecastCalibrationOptions o;
  o.holds = {{0, s.p.size()}};
  o.hold_from_s = 0.0;
  piezo::estimation::calibrate_forecast(table, kDt, s.p, s.y, s.v, o);
  ASSERT_EQ(table.forecast_sigma_scale_hold.size(), all.forecast_sigma_scale_hold.size());
  std::size_t moved = 0;  // horizons with enough moving windows to calibrate on every row
  for (std::size_t k = 0; k < table.forecast_horizons_s.size(); ++k) {
    EXPECT_DOUBLE_EQ(table.forecast_sigma_scale_hold[k], all.forecast_sigma_scale_hold[k]) << k;
    EXPECT_DOUBLE_EQ(table.forecast_sigma_scale_move[k], 1.0) << k;
    moved += all.forecast_sigma_scale_move[k] != 1.0;
  }
  EXPECT_GE(moved, 3u);
  EXPECT_NE(table.method.find("on the table's rows"), std::string::npos) << table.method;
}

TEST(Forecast, ModelFileKeysRoundTripAndAreChecked) {
  NoiseModel m = known_model();
  m.forecast_horizons_s = {0.1, 60.0};
  m.forecast_sigma_scale_hold = {1.1, 0.5};
  m.forecast_sigma_scale_move = {1.2, 0.8};
  const NoiseModel back = NoiseModel::from_yaml(m.to_yaml(), "test");
  EXPECT_EQ(back.forecast_sigma_scale_hold, m.forecast_sigma_scale_hold);
  EXPECT_DOUBLE_EQ(piezo::estimation::forecast_sigma_scale(back, 0.05, true), 1.1);
  EXPECT_DOUBLE_EQ(piezo::estimation::forecast_sigma_scale(back, 600.0, false), 0.8);
  EXPECT_NEAR(piezo::estimation::forecast_sigma_scale(back, std::sqrt(6.0), true), 0.8, 1e-12);  // midway in log h
  YAML::Node bad = m.to_yaml();
  bad["forecast_sigma_scale_move"] = std::vector<double>{1.0};
  EXPECT_THROW(NoiseModel::from_yaml(bad, "test"), std::invalid_argument);
  bad = m.to_yaml();
  bad.remove("forecast_sigma_scale_hold");
  EXPECT_THROW(NoiseModel::from_yaml(bad, "test"), std::invalid_argument);
  bad = m.to_yaml();
  bad["forecast_horizons_s"] = std::vector<double>{60.0, 0.1};
  EXPECT_THROW(NoiseModel::from_yaml(bad, "test"), std::invalid_argument);
  NoiseModel none = NoiseModel::from_yaml(known_model().to_yaml(), "test");
  EXPECT_TRUE(none.forecast_horizons_s.empty());
  EXPECT_DOUBLE_EQ(piezo::estimation::forecast_sigma_scale(none, 10.0, true), 1.0);
}

// The live path: the drift forecast run with the estimator's state gives the model's run plus the error forecast,
// counted from the fused position now, with the σ of the model's path from the filter's last prediction.
TEST(Forecast, DriftForecastWithTheEstimatorsState) {
  NoiseModel m = known_model();
  m.q_fast_nm = 0.0;  // the path alone then sets the motion's variance: a monotone creep's path is its span
  auto model = piezo::test::make_pi_creep();
  model->reset(0.0, 0.0);
  ErrorFilter f(m, kDt);
  std::mt19937 rng(2);
  std::normal_distribution<double> g(0.0, 20.0);
  for (int i = 0; i < 400; ++i) {
    const piezo::models::ModelInput in{30.0, nullptr};
    const double p = model->predict(in);
    model->commit(in, p);
    f.step(p, 20.0 * std::round((p + 12.0 + g(rng)) / 20.0), true);
  }
  const piezo::compensation::EstimatorState est{m, f.state()};
  const std::vector<double> hs{0.0, 10.0, 600.0};
  const auto d = piezo::compensation::forecast_drift(*model, 30.0, hs, 11.0, nullptr, &est);
  ASSERT_TRUE(d.ok) << d.error;
  ASSERT_EQ(d.forecast_sigma_nm.size(), 3u);
  EXPECT_DOUBLE_EQ(d.fused_now_nm, f.fused_nm());
  for (std::size_t k = 0; k < hs.size(); ++k) {
    piezo::estimation::ForecastPath path;
    path.steps = static_cast<std::size_t>(std::lround(hs[k] * 11.0)) + 1;
    path.path_nm = std::abs(d.position_nm[k] - est.state.last_predicted_nm);
    const auto e = piezo::estimation::forecast_error(m, kDt, est.state, path, true);
    EXPECT_NEAR(d.forecast_nm[k], d.position_nm[k] + e.mean_nm, 1e-9) << hs[k];
    EXPECT_NEAR(d.forecast_drift_nm[k], d.forecast_nm[k] - f.fused_nm(), 1e-9) << hs[k];
    EXPECT_NEAR(d.forecast_sigma_nm[k], e.sigma_nm, 1e-6 * e.sigma_nm) << hs[k];
  }
  EXPECT_GT(d.forecast_sigma_nm[2], d.forecast_sigma_nm[0]);  // the error wanders further the longer the horizon
  // without the estimator's state: the model's drift only, as before
  const auto plain = piezo::compensation::forecast_drift(*model, 30.0, hs, 11.0);
  EXPECT_TRUE(plain.forecast_nm.empty());
  EXPECT_EQ(plain.drift_nm, d.drift_nm);
}

}  // namespace
