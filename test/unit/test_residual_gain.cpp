// Gain effects (issue 18), on the Preisach/independent-creep stage of test_residual_gain_cases.h: (d) the stage
// without an effect gets nothing added; (a) a stroke gain driven by a lagged temperature column is named as an
// aux_gain of temperature_c, nothing else added, and ends within 10 % of (d)'s free-run MAE against the truth; a
// gain driven by a signal that is not in the file ends in "not explained" with the size of what is left.
// (b) time and (c) other-axis gains: test_residual_gain_drift.cpp.
#include "test_residual_gain_cases.h"

using namespace piezo::test::gain;

namespace {
const pa::ResidualResult& clean() {
  static const pa::ResidualResult r = [] {
    pa::ResidualResult res = trace(Gain::kNone);
    print("(d) no effect", res);
    return res;
  }();
  return r;
}
}  // namespace

TEST(ResidualGain, NoEffectAddsNothing) {
  const pa::ResidualResult& r = clean();
  EXPECT_TRUE(r.effects.empty()) << "(d): added " << r.effects.front().family;
}
// Within the 1.10 × ((d)'s base is within 5.9 nm of the truth, noise σ 21 nm, so 10 % is 0.6 nm). Measured
// 20.1 → 5.59 nm = 0.94 × (3.7 %/°C against 4 %, lag 120 s + low-pass 100 s against the true 45 s + 240 s); without
// the effect found it stays at 3.4 ×. With the earlier Preisach fit ((d) 4.05 nm) this went 1.21 × → 1.00 × with the
// pivot and form rules of docs/closing-the-loop.md ("What limited (a)").
TEST(ResidualGain, StrokeGainDrivenByALaggedTemperatureColumn) {
  expect_gain(Gain::kTemperature, "(a) temperature gain", "aux_gain", "temperature_c", clean().after_test_truth.mae_nm, 1.10);
}
TEST(ResidualGain, GainFromASignalNotInTheFileIsNotExplained) {
  const pa::ResidualResult r = trace(Gain::kHiddenTemperature);
  print("hidden temperature gain", r);
  EXPECT_FALSE(r.remainder.explained);
  EXPECT_GT(r.remainder.structure_nm, 2.0);
  ASSERT_FALSE(r.remainder.correlates.empty());
}
