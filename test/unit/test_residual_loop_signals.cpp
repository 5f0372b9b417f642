// The residual loop on synthetic data (test_residual_loop_cases.h): an effect of the temperature column.
#include "test_residual_loop_cases.h"

#include <algorithm>

using namespace residual_loop;

TEST(ResidualLoop, FindsTemperatureColumn) {
  const Outcome o = run(Planted::kAuxTemperature, 22);
  ASSERT_NO_FATAL_FAILURE(expect_found(o, "aux_signal"));
  EXPECT_EQ(o.res.effects.front().labels.at("signal"), "temperature_c");
  // The plant feels the temperature through a first-order lag of 300 s: the lag is profiled in that form.
  const pa::FoundEffect& e = o.res.effects.front();
  EXPECT_EQ(e.parameters.at("lag_s"), 0.0);
  EXPECT_NEAR(e.parameters.at("time_constant_s"), 300.0, 60.0);
  ASSERT_GE(e.lag_profile.points.size(), 8u);
  const auto best = std::min_element(e.lag_profile.points.begin(), e.lag_profile.points.end(),
                                     [](const auto& x, const auto& y) { return x.second < y.second; });
  EXPECT_EQ(best->first, e.parameters.at("time_constant_s"));
  // A 150-nm/°C effect over 2 h of TRAIN tells its lag to within a factor 2 (1.51: 212-320 s not clearly worse on
  // the validation part's paired 5-min blocks), enough to tell 90 s from 400 s.
  EXPECT_LE(e.lag_profile.lo_s, e.lag_profile.chosen_s);
  EXPECT_GE(e.lag_profile.hi_s, e.lag_profile.chosen_s);
  EXPECT_LT(e.lag_profile.hi_s / e.lag_profile.lo_s, 2.0);
}
