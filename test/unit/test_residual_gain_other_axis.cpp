// Gain effects (issue 18), on the Preisach/independent-creep stage of test_residual_gain_cases.h: (c) a gain
// driven by another axis' position is named as a gain of that axis, nothing else added, and ends within 10 % of
// (d)'s free-run MAE against the truth (test_residual_gain.cpp asserts that (d) gets nothing added).
#include "test_residual_gain_cases.h"

using namespace piezo::test::gain;

// Measured 37.9 → 4.41 nm = 1.09 × (d)'s 4.05 nm (the gain 1.49 %/µm against 1.5 %/µm, on the output). Before
// another form had to be clearly better than the output gain, the voltage form won by 0.005 nm of 17.5 nm
// validation MAE and this ended at 12.3 nm (3.0 ×).
TEST(ResidualGainDrift, GainDrivenByAnotherAxisPosition) {
  expect_gain(Gain::kOtherAxis, "(c) other-axis gain", "cross_axis_gain", "a_", clean_base_truth_mae());
}
