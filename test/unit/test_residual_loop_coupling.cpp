// The residual loop on synthetic data (test_residual_loop_cases.h): a cross-axis coupling.
#include "test_residual_loop_cases.h"

using namespace residual_loop;

TEST(ResidualLoop, FindsCrossAxisCoupling) {
  const Outcome o = run(Planted::kCrossAxis, 23);
  ASSERT_NO_FATAL_FAILURE(expect_found(o, "cross_axis"));
  EXPECT_EQ(o.res.effects.front().labels.at("signal"), "a_voltage_v");
  EXPECT_NEAR(o.res.effects.front().parameters.at("lag_s"), 1.0, 0.51);
  EXPECT_NEAR(o.res.effects.front().parameters.at("gain_nm_per_v"), 1.5, 0.2);
}
