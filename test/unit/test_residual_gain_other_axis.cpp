// Gain effects on the Preisach/independent-creep stage of test_residual_gain_cases.h: (c) a gain
// driven by another axis' position is named as a gain of that axis, nothing else added, and ends within 10 % of
// (d)'s free-run MAE against the truth (test_residual_gain.cpp asserts that (d) gets nothing added).
#include "test_residual_gain_cases.h"

using namespace piezo::test::gain;

// Within 1.10 × (d): the gain acts on the output, and another form replaces the output gain only when it is
// clearly better on validation (a near tie keeps the output form). Figures: docs/validation/residual-loop.md.
TEST(ResidualGainDrift, GainDrivenByAnotherAxisPosition) {
  expect_gain(Gain::kOtherAxis, "(c) other-axis gain", "cross_axis_gain", "a_", clean_base_truth_mae());
}
