// The noise floor estimated from the data, on simulated stages whose noise is known.
#include <gtest/gtest.h>

#include <cmath>

#include "piezo_compensation/analysis/evaluation/noise_floor.h"
#include "piezo_compensation/sim/stage.h"

using namespace piezo;

namespace {
io::Dataset stage_data(const std::string& name, double duration_s, std::uint64_t seed) {
  const auto stage = sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/" + name + ".yaml");
  return sim::simulate_stage(stage, seed, duration_s);
}
double true_sigma(const io::AxisSeries& a) {
  double s = 0, ss = 0;
  for (std::size_t i = 0; i < a.position_nm.size(); ++i) {
    const double e = a.position_nm[i] - a.true_position_nm[i];
    s += e, ss += e * e;
  }
  const double n = a.position_nm.size();
  return std::sqrt(ss / n - (s / n) * (s / n));
}
}  // namespace

TEST(NoiseFloor, FromHoldsMatchesTheSimulatedEncoderOnEveryStage) {
  // Three stages with different sensors: σ 25 nm / 10 nm steps, 3 nm / 1 nm, 19.97 nm / 20 nm (20.8 measured).
  for (const auto& [name, duration_s] : {std::pair<std::string, double>{"lowvolt_preisach_creep", 50.0},
                                         {"stack150_pi_creep", 10.0},
                                         {"mm3e_preisach_creep", 3 * 3600.0}}) {
    SCOPED_TRACE(name);
    const auto d = stage_data(name, duration_s, 7);
    const auto f = analysis::estimate_noise_floor(d, "c");
    const double truth = true_sigma(d.axis("c"));
    std::printf("%s: %s (true σ %.2f nm)\n", name.c_str(), f.describe().c_str(), truth);
    EXPECT_EQ(f.method, "holds");
    EXPECT_NEAR(f.sigma_nm, truth, 0.08 * truth);
    EXPECT_NEAR(f.floor_mae_nm, truth * std::sqrt(2.0 / M_PI), 0.1 * truth);
  }
}

TEST(NoiseFloor, WithoutHoldsUsesTheResidualsHighFrequencies) {
  auto d = stage_data("stack150_pi", 4.0, 3);
  auto& a = d.axes[0];
  // No holds: every voltage differs from the one before.
  for (std::size_t i = 1; i < a.voltage_v.size(); ++i)
    if (a.voltage_v[i] == a.voltage_v[i - 1]) a.voltage_v[i] += 1e-9 * static_cast<double>(i % 7 + 1);
  const auto pred = a.true_position_nm;  // a perfect model: what is left is the noise
  const auto f = analysis::estimate_noise_floor(d, "c", &pred);
  EXPECT_EQ(f.method, "residual");
  EXPECT_NEAR(f.sigma_nm, true_sigma(a), 0.08 * true_sigma(a));
  // Without a model, motion inflates the estimate: it is an upper bound and labelled so.
  const auto g = analysis::estimate_noise_floor(d, "c");
  EXPECT_EQ(g.method, "all samples");
  EXPECT_GT(g.sigma_nm, f.sigma_nm);
}

TEST(NoiseFloor, CoarseEncoderStepDominates) {
  // 250 nm steps with 20 nm noise (the MM3E's a and b axes): the rounding error q/√12 is the floor.
  io::Dataset d;
  d.time_s.resize(2000);
  auto& a = d.add_axis("c");
  for (std::size_t i = 0; i < 2000; ++i) {
    d.time_s[i] = i / 11.0;
    a.voltage_v.push_back(i < 1000 ? 0.0 : 5.0);
    const double truth = 37.0 + 0.7 * static_cast<double>(i);  // a slow drift over 6 steps
    a.position_nm.push_back(250.0 * std::nearbyint((truth + 20.0 * std::sin(1.7 * i)) / 250.0));
  }
  const auto f = analysis::estimate_noise_floor(d, "c");
  EXPECT_DOUBLE_EQ(f.quantisation_nm, 250.0);
  EXPECT_NEAR(f.sigma_nm, 250.0 / std::sqrt(12.0), 1e-9);
  EXPECT_NEAR(f.floor_mae_nm, 62.5, 1e-9);
}

TEST(NoiseFloor, StepAndOverride) {
  EXPECT_DOUBLE_EQ(analysis::reading_step_nm({0, 20, 60, -40, 100, 20}), 20.0);
  EXPECT_DOUBLE_EQ(analysis::reading_step_nm({0.0, 1.3, 2.9, 3.05, 7.7}), 0.0);
  const auto f = analysis::noise_floor_from_sigma(20.79);
  EXPECT_EQ(f.method, "given");
  EXPECT_NEAR(f.floor_mae_nm, 16.59, 0.01);
  EXPECT_THROW(analysis::noise_floor_from_sigma(-1.0), std::invalid_argument);
  EXPECT_THROW(analysis::noise_floor_from_sigma(NAN), std::invalid_argument);
}
