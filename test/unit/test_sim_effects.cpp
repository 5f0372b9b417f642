// Each extra effect: present (with its documented equation and size) when on, no influence when off.
#include <gtest/gtest.h>

#include <cmath>
#include <numeric>

#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"

using namespace piezo;

namespace {

constexpr double kRate = 11.0;

const io::Dataset& walk_program() {  // 2 h of independent random walks on a, b, c
  static const io::Dataset p =
      protocols::make_protocol("random_walk", YAML::Load("{duration_s: 7200}"), kRate, 4)->program();
  return p;
}

io::Dataset run(const sim::SimulatorConfig& cfg, const io::Dataset& prog = walk_program()) {
  sim::ManipulatorSimulator s(cfg, 4);
  return s.run(prog);
}

// Least-squares amplitude of sin/cos at phase argument arg[i] in signal x (mean removed).
double harmonic_amplitude(const std::vector<double>& x, const std::vector<double>& arg) {
  double ss = 0, cc = 0, sc = 0, xs = 0, xc = 0;
  const double m = std::accumulate(x.begin(), x.end(), 0.0) / x.size();
  for (std::size_t i = 0; i < x.size(); ++i) {
    const double s = std::sin(arg[i]), c = std::cos(arg[i]);
    ss += s * s, cc += c * c, sc += s * c, xs += (x[i] - m) * s, xc += (x[i] - m) * c;
  }
  const double det = ss * cc - sc * sc;
  const double a = (xs * cc - xc * sc) / det, b = (xc * ss - xs * sc) / det;
  return std::hypot(a, b);
}

double correlation(const std::vector<double>& x, const std::vector<double>& y) {
  const double mx = std::accumulate(x.begin(), x.end(), 0.0) / x.size();
  const double my = std::accumulate(y.begin(), y.end(), 0.0) / y.size();
  double sxy = 0, sxx = 0, syy = 0;
  for (std::size_t i = 0; i < x.size(); ++i)
    sxy += (x[i] - mx) * (y[i] - my), sxx += (x[i] - mx) * (x[i] - mx), syy += (y[i] - my) * (y[i] - my);
  return sxy / std::sqrt(sxx * syy);
}

std::vector<double> diff(const std::vector<double>& a, const std::vector<double>& b) {
  std::vector<double> d(a.size());
  for (std::size_t i = 0; i < a.size(); ++i) d[i] = a[i] - b[i];
  return d;
}

}  // namespace

// Disabled effects have no influence at all, whatever their parameters.
TEST(SimEffects, DisabledEffectsLeaveDataUntouched) {
  const auto base = run(sim::default_simulator_config());
  auto cfg = sim::default_simulator_config();
  cfg.thermal_drift.gain_nm_per_c = 1e4;
  cfg.cross_axis.gain = 0.5;
  cfg.encoder_periodic.amplitude_nm = 1e3;
  cfg.rate_dependent.gain = 5.0;
  cfg.periodic_disturbance.amplitude_nm = 1e3;
  const auto d = run(cfg);
  for (int k = 0; k < 3; ++k) {
    EXPECT_EQ(d.axes[k].position_nm, base.axes[k].position_nm);
    EXPECT_EQ(d.axes[k].true_position_nm, base.axes[k].true_position_nm);
  }
  EXPECT_TRUE(d.aux.empty());
}

TEST(SimEffects, ThermalDriftFollowsTemperatureChannel) {
  auto cfg = sim::default_simulator_config();
  sim::enable_effect(cfg, "thermal_drift");
  const auto on = run(cfg), off = run(sim::default_simulator_config());
  const auto* temp = on.find_aux("temperature_c");
  ASSERT_NE(temp, nullptr);
  ASSERT_EQ(temp->values.size(), on.size());
  const auto d = diff(on.axis("c").true_position_nm, off.axis("c").true_position_nm);
  // Lag the temperature as the mechanics do (first order, lag_s) and compare.
  std::vector<double> lagged(temp->values.size());
  double l = temp->values[0];
  const double a = 1.0 - std::exp(-1.0 / kRate / cfg.thermal_drift.lag_s);
  for (std::size_t i = 0; i < lagged.size(); ++i) lagged[i] = (l += (temp->values[i] - l) * a);
  EXPECT_GT(correlation(d, lagged), 0.97);
  const auto [lo, hi] = std::minmax_element(d.begin(), d.end());
  EXPECT_GT(*hi - *lo, 40.0);  // tens of nm: clearly above 20.79 nm noise over hours
  const auto [tlo, thi] = std::minmax_element(temp->values.begin(), temp->values.end());
  EXPECT_GT(*thi - *tlo, 0.5);
  EXPECT_EQ(off.find_aux("temperature_c"), nullptr);
}

TEST(SimEffects, CrossAxisCouplesAIntoC) {
  auto cfg = sim::default_simulator_config();
  sim::enable_effect(cfg, "cross_axis");
  const auto on = run(cfg), off = run(sim::default_simulator_config());
  const auto d = diff(on.axis("c").true_position_nm, off.axis("c").true_position_nm);
  const auto& a = off.axis("a").true_position_nm;
  EXPECT_GT(correlation(d, a), 0.999);
  double num = 0, den = 0;
  for (std::size_t i = 0; i < d.size(); ++i) num += d[i] * a[i], den += a[i] * a[i];
  EXPECT_NEAR(num / den, 0.02, 0.002);
  const auto [lo, hi] = std::minmax_element(d.begin(), d.end());
  EXPECT_GT(*hi - *lo, 60.0);
  EXPECT_EQ(on.axis("a").true_position_nm, off.axis("a").true_position_nm);
  EXPECT_EQ(on.axis("b").true_position_nm, off.axis("b").true_position_nm);
}

TEST(SimEffects, EncoderPeriodicErrorIsPeriodicInPosition) {
  auto cfg = sim::default_simulator_config();
  sim::enable_effect(cfg, "encoder_periodic");
  const auto on = run(cfg), off = run(sim::default_simulator_config());
  const auto& c_on = on.axis("c");
  // True position untouched; the reading error has a 30 nm harmonic at 400 nm period — and none when off.
  EXPECT_EQ(c_on.true_position_nm, off.axis("c").true_position_nm);
  std::vector<double> arg;
  for (double y : c_on.true_position_nm) arg.push_back(2.0 * M_PI * y / 400.0);
  EXPECT_NEAR(harmonic_amplitude(diff(c_on.position_nm, c_on.true_position_nm), arg), 30.0, 3.0);
  const auto& c_off = off.axis("c");
  EXPECT_LT(harmonic_amplitude(diff(c_off.position_nm, c_off.true_position_nm), arg), 2.0);
}

TEST(SimEffects, PeriodicDisturbanceIsSinusoidInTime) {
  auto cfg = sim::default_simulator_config();
  sim::enable_effect(cfg, "periodic_disturbance");
  const auto on = run(cfg), off = run(sim::default_simulator_config());
  std::vector<double> arg;
  for (double t : on.time_s) arg.push_back(2.0 * M_PI * 0.05 * t);
  EXPECT_NEAR(harmonic_amplitude(diff(on.axis("c").true_position_nm, off.axis("c").true_position_nm), arg), 25.0, 1.0);
  // The measured data carry it too, visible over the noise after removing the effect-free truth.
  EXPECT_NEAR(harmonic_amplitude(diff(on.axis("c").position_nm, off.axis("c").true_position_nm), arg), 25.0, 2.0);
  EXPECT_LT(harmonic_amplitude(diff(off.axis("c").position_nm, off.axis("c").true_position_nm), arg), 2.0);
}

TEST(SimEffects, RateDependentHysteresisWidensFastLoops) {
  auto cfg = sim::default_simulator_config();
  for (auto& a : cfg.axes) a.encoder_noise_sigma_nm = 0.0;
  auto on_cfg = cfg;
  sim::enable_effect(on_cfg, "rate_dependent");
  // Full-range triangle at 1.25 V per sample (13.75 V/s) and at 0.01 V per sample (0.11 V/s).
  auto width = [](const sim::SimulatorConfig& c, double step_v) {
    io::Dataset p;
    std::vector<double> v;
    for (double x = -80.0; x < 80.0; x += step_v) v.push_back(x);
    for (double x = 80.0; x > -80.0; x -= step_v) v.push_back(x);
    for (double x = -80.0; x <= 0.0; x += step_v) v.push_back(x);  // second up branch to mid voltage
    for (std::size_t i = 0; i < v.size(); ++i) p.time_s.push_back(i / kRate);
    p.add_axis("c").voltage_v = v;
    sim::ManipulatorSimulator s(c, 1);
    const auto d = s.run(p);
    const auto& y = d.axis("c").true_position_nm;
    const std::size_t n_half = static_cast<std::size_t>(std::lround(160.0 / step_v));
    return y[n_half + n_half / 2] - y.back();  // descending minus ascending branch at 0 V
  };
  const double fast_off = width(cfg, 1.25), fast_on = width(on_cfg, 1.25);
  const double slow_off = width(cfg, 0.01), slow_on = width(on_cfg, 0.01);
  EXPECT_GT(fast_on - fast_off, 60.0);
  EXPECT_LT(std::fabs(slow_on - slow_off), 5.0);
}
