// Gain effects (issue 18), on the Preisach/independent-creep stage of test_residual_gain_cases.h: (a) a stroke
// gain driven by a lagged temperature column is named as an aux_gain of temperature_c, nothing else added, and
// ends within 10 % of (d)'s free-run MAE against the truth ((d) gets nothing added: test_residual_gain.cpp, so
// its MAE is its base's).
#include "test_residual_gain_cases.h"

using namespace piezo::test::gain;

// Within the 1.10 × ((d)'s base is within 5.9 nm of the truth, noise σ 21 nm, so 10 % is 0.6 nm). Measured
// 20.1 → 5.59 nm = 0.94 × (3.7 %/°C against 4 %, lag 120 s + low-pass 100 s against the true 45 s + 240 s); without
// the effect found it stays at 3.4 ×. With the earlier Preisach fit ((d) 4.05 nm) this went 1.21 × → 1.00 × with the
// pivot and form rules of docs/closing-the-loop.md ("What limited (a)").
TEST(ResidualGain, StrokeGainDrivenByALaggedTemperatureColumn) {
  expect_gain(Gain::kTemperature, "(a) temperature gain", "aux_gain", "temperature_c", clean_base_truth_mae(), 1.10);
}
