// mm3e_sim's ~set_thermal_drift: the simulator's thermal drift switched on mid-run starts from the ambient
// temperature (no position jump), then adds gain · (lagged temperature − ambient) like the effect enabled from t = 0.
#include <gtest/gtest.h>

#include <cmath>

#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"

using namespace piezo;

TEST(SimThermalSwitch, SwitchedOnMidRunWithoutAJumpThenDrifts) {
  sim::SimulatorConfig cfg = sim::default_simulator_config();
  cfg.thermal_drift.period_s = 200.0;
  cfg.thermal_drift.amplitude_c = 1.5;
  cfg.thermal_drift.lag_s = 20.0;
  sim::ManipulatorSimulator with(cfg, 4), without(cfg, 4);
  const double dt = 1.0 / 11.0;
  const std::array<double, 3> v{0.0, 0.0, 30.0};
  for (int i = 0; i < 1100; ++i) {  // 100 s, effect off: identical, the sensor reads the ambient temperature
    const auto a = with.step(v, dt), b = without.step(v, dt);
    ASSERT_EQ(a.axes[2].true_position_nm, b.axes[2].true_position_nm);
    ASSERT_EQ(a.temperature_c, cfg.thermal_drift.ambient_c);
  }
  with.set_thermal_drift(true);
  const auto a = with.step(v, dt), b = without.step(v, dt);
  EXPECT_LT(std::fabs(a.axes[2].true_position_nm - b.axes[2].true_position_nm), 1.0) << "the position jumped";
  EXPECT_NE(a.temperature_c, cfg.thermal_drift.ambient_c);
  double largest = 0.0;
  for (int i = 0; i < 11 * 200; ++i) {  // one temperature cycle
    const auto x = with.step(v, dt), y = without.step(v, dt);
    largest = std::max(largest, std::fabs(x.axes[2].true_position_nm - y.axes[2].true_position_nm));
  }
  // 60 nm/°C × 1.5 °C through a 20 s lag of a 200 s cycle: |H| = 0.85 → up to ≈ 76 nm
  EXPECT_GT(largest, 60.0);
  EXPECT_LT(largest, 95.0);
  with.set_thermal_drift(false);  // off: the offset goes at once, the sensor reads the ambient again
  const auto x = with.step(v, dt), y = without.step(v, dt);
  EXPECT_EQ(x.axes[2].true_position_nm, y.axes[2].true_position_nm);
  EXPECT_EQ(x.temperature_c, cfg.thermal_drift.ambient_c);
}
