// Independent physics of the simulator (Preisach hysteresis, explicit creep spectrum) and the stage files of
// the model test matrix (config/stages/*.yaml).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>

#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/piezo_axis.h"
#include "piezo_compensation/sim/simulator_config.h"
#include "piezo_compensation/sim/stage.h"

using namespace piezo;

namespace {

sim::AxisConfig preisach_axis() {
  auto a = sim::default_simulator_config().axes[2];
  a.hysteresis_model = "preisach";
  a.creep_gain = 0.0;
  return a;
}

// Full-range loop of a hysteresis model: ascending and descending branch sampled at the same voltages.
template <class H>
void full_loop(H& h, const sim::AxisConfig& a, std::vector<double>& v, std::vector<double>& up,
               std::vector<double>& down) {
  const int n = 300;  // voltages off the relay grid, so float ties cannot break the symmetry
  v.resize(n);
  for (int i = 0; i < n; ++i) v[i] = a.voltage_min_v + (a.voltage_max_v - a.voltage_min_v) * i / (n - 1);
  h.update(a.voltage_max_v), h.update(a.voltage_min_v);
  up.clear(), down.clear();
  for (int i = 0; i < n; ++i) up.push_back(h.update(v[i]));
  for (int i = n - 1; i >= 0; --i) down.push_back(h.update(v[i]));
  std::reverse(down.begin(), down.end());
}

// Largest departure from point symmetry, up(u) = −down(−u) + const, relative to the span.
template <class H>
double asymmetry_of_loop(H& h, const sim::AxisConfig& a) {
  std::vector<double> v, up, down;
  full_loop(h, a, v, up, down);
  const std::size_t n = v.size();
  const double c = up[0] + down[n - 1];
  double worst = 0.0;
  for (std::size_t i = 0; i < n; ++i) worst = std::max(worst, std::fabs(up[i] + down[n - 1 - i] - c));
  return worst / (down.back() - up.front());
}

}  // namespace

TEST(SimPreisach, LoopSpansStrokeWithConfiguredWidth) {
  const auto a = preisach_axis();
  sim::Preisach h(a);
  EXPECT_EQ(h.relay_count(), 40u * 41u / 2u);
  EXPECT_GT(h.linear_weight_nm_per_v(), 0.0);
  std::vector<double> v, up, down;
  full_loop(h, a, v, up, down);
  EXPECT_NEAR(down.back() - up.front(), a.stroke_nm, 1e-6 * a.stroke_nm);
  EXPECT_NEAR(down[v.size() / 2] - up[v.size() / 2], a.loop_width_fraction * a.stroke_nm, 1e-6 * a.stroke_nm);
  // Monotone branches (an inverse exists).
  for (std::size_t i = 1; i < v.size(); ++i) {
    EXPECT_GE(up[i], up[i - 1]);
    EXPECT_GE(down[i], down[i - 1]);
  }
}

TEST(SimPreisach, AsymmetricUnlikePrandtlIshlinskii) {
  // A PI loop is point-symmetric about its centre; the Preisach density with a centre offset is not.
  auto a = preisach_axis();
  sim::Preisach pr(a);
  a.hysteresis_model = "prandtl_ishlinskii";
  sim::PrandtlIshlinskii pi(a);
  const double pi_asym = asymmetry_of_loop(pi, a), pr_asym = asymmetry_of_loop(pr, a);
  std::printf("loop asymmetry / span: Prandtl-Ishlinskii %.2e, Preisach %.4f\n", pi_asym, pr_asym);
  EXPECT_LT(pi_asym, 1e-9);
  EXPECT_GT(pr_asym, 0.01);  // > 1 % of the stroke
  // No centre offset: symmetric again (the measure can tell the two apart).
  auto b = preisach_axis();
  b.preisach_centre_offset = 0.0;
  sim::Preisach sym(b);
  EXPECT_LT(asymmetry_of_loop(sym, b), 0.003);
}

TEST(SimPreisach, MinorLoopsCloseAndWipeOut) {
  const auto a = preisach_axis();
  sim::Preisach h(a), g(a);
  h.update(80.0);
  const double at = h.update(-20.0);
  h.update(30.0), h.update(10.0), h.update(20.0);
  EXPECT_NEAR(h.update(-20.0), at, 1e-9);
  g.update(80.0), g.update(-20.0), g.update(50.0), g.update(0.0);
  EXPECT_NE(h.update(20.0), g.update(20.0));
  EXPECT_NEAR(h.update(-60.0), g.update(-60.0), 1e-9);
  EXPECT_NEAR(h.update(25.0), g.update(25.0), 1e-9);
  h.reset();
  EXPECT_NEAR(h.update(0.0), 0.0, 1e-9);  // demagnetised start: H = 0 at mid voltage
}

TEST(SimCreepSpectrum, StepResponseIsTheConfiguredModes) {
  auto a = sim::default_simulator_config().axes[2];
  a.creep_spectrum_tau_s = {2.0, 300.0, 9000.0};
  a.creep_spectrum_weights = {0.05, 0.02, 0.1};
  sim::CreepModes m(a);
  ASSERT_EQ(m.tau_s().size(), 3u);
  const double h = 100.0, dt = 0.5;
  double c = 0.0, t = 0.0;
  for (int i = 0; i < 20000; ++i) c = m.update(h, dt), t += dt;
  double expect = 0.0;
  for (int j = 0; j < 3; ++j) expect += a.creep_spectrum_weights[j] * h * (1.0 - std::exp(-t / a.creep_spectrum_tau_s[j]));
  EXPECT_NEAR(c, expect, 1e-9);
}

TEST(SimConfig, NewKeysAreValidated) {
  const std::string path = ::testing::TempDir() + "bad_sim_stage.yaml";
  auto error_of = [&](const std::string& text) -> std::string {
    std::ofstream(path) << text;
    try {
      sim::load_simulator_config(path);
    } catch (const std::invalid_argument& e) {
      return e.what();
    }
    return "";
  };
  EXPECT_NE(error_of("axes: {c: {hysteresis_model: bouc_wen}}").find("axes.c.hysteresis_model"), std::string::npos);
  EXPECT_NE(error_of("axes: {c: {creep_spectrum_tau_s: [1, 2], creep_spectrum_weights: [0.1]}}")
                .find("creep_spectrum_weights"),
            std::string::npos);
  EXPECT_NE(error_of("axes: {c: {creep_spectrum_tau_s: [1, 2], creep_spectrum_weights: [0.6, 0.6]}}")
                .find("sum of |weights|"),
            std::string::npos);
  EXPECT_NE(error_of("axes: {c: {creep_spectrum_tau_s: [1, x], creep_spectrum_weights: [0.1, 0.1]}}")
                .find("expected a list of numbers"),
            std::string::npos);
  EXPECT_NE(error_of("axes: {c: {hysteresis_model: preisach, preisach_width_decay: 0}}")
                .find("preisach_width_decay"),
            std::string::npos);
  EXPECT_EQ(error_of("axes: {c: {hysteresis_model: preisach, creep_spectrum_tau_s: [3, 3000], "
                     "creep_spectrum_weights: [0.1, 0.2]}}"),
            "");
}

TEST(SimStages, EveryStageFileBuildsDataOfItsRange) {
  const std::filesystem::path dir = std::filesystem::path(PIEZO_SOURCE_DIR) / "config" / "stages";
  int files = 0;
  for (const auto& entry : std::filesystem::directory_iterator(dir)) {
    if (entry.path().extension() != ".yaml") continue;
    ++files;
    SCOPED_TRACE(entry.path().string());
    const auto stage = sim::load_stage(entry.path().string());
    // the stage's last driven axis (c where it drives c; a/b on the coarse-encoder stages)
    const std::string name = stage.axes.back();
    const int k = io::axis_index_or_none(name);
    ASSERT_GE(k, 0) << name;
    const auto& c = stage.simulator.axes[static_cast<std::size_t>(k)];
    // A short piece is enough to check ranges and determinism: 2000 samples.
    const double d = 2000.0 / stage.simulator.sample_rate_hz;
    const auto x = sim::simulate_stage(stage, 4, d), y = sim::simulate_stage(stage, 4, d);
    ASSERT_EQ(x.size(), 2000u);
    const auto& ax = x.axis(name);
    EXPECT_EQ(ax.position_nm, y.axis(name).position_nm);
    for (std::size_t i = 0; i < x.size(); ++i) {
      ASSERT_GE(ax.voltage_v[i], c.voltage_min_v);
      ASSERT_LE(ax.voltage_v[i], c.voltage_max_v);
      ASSERT_LE(std::fabs(ax.true_position_nm[i]), 1.5 * c.stroke_nm);
    }
  }
  EXPECT_GE(files, 13);
  const std::string path = ::testing::TempDir() + "bad_stage.yaml";
  std::ofstream(path) << "protocol: random_walk\nsimulator: {axes: {c: {stroke_nm: -1}}}\n";
  try {
    sim::load_stage(path);
    FAIL() << "bad stage accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("stroke_nm"), std::string::npos);
  }
  std::ofstream(path) << "protocol: random_walk\nvoltage_ofset_v: 2\n";
  EXPECT_THROW(sim::load_stage(path), std::invalid_argument);
}
