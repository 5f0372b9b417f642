// Gain effects on the Preisach/independent-creep stage of test_residual_gain_cases.h: (b) a stroke
// gain drifting linearly in time is named as a gain of the right signal, nothing else added, and ends within
// 10 % of (d)'s free-run MAE against the truth. (c): test_residual_gain_other_axis.cpp. (d) itself:
// test_residual_gain.cpp, which asserts that (d) gets nothing added, so (d)'s MAE is its base's.
#include "test_residual_gain_cases.h"

using namespace piezo::test::gain;

TEST(ResidualGainDrift, StrokeGainDriftingLinearlyInTime) {
  expect_gain(Gain::kTime, "(b) time gain", "time_gain", "", clean_base_truth_mae());
}
