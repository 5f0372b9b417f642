// The residual loop on synthetic data (test_residual_loop_cases.h): an effect of the temperature column.
#include "test_residual_loop_cases.h"

using namespace residual_loop;

TEST(ResidualLoop, FindsTemperatureColumn) {
  const Outcome o = run(Planted::kAuxTemperature, 22);
  ASSERT_NO_FATAL_FAILURE(expect_found(o, "aux_signal"));
  EXPECT_EQ(o.res.effects.front().labels.at("signal"), "temperature_c");
}
