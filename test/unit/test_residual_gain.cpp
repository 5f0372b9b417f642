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
// Within the 1.10 × ((d)'s base is within 4.1 nm of the truth, noise σ 21 nm, so 10 % is 0.4 nm). Measured
// 20.1 → 4.03 nm = 1.00 × (3.8 %/°C against 4 %, lag 120 s + low-pass 100 s against the true 45 s + 240 s); it fails
// if the gain is not found (5.0 ×) or misplaced (lag chosen before the base is refitted: 3.1 ×). Before the pivot
// and form rules of docs/closing-the-loop.md: 1.21 × about the base's reset rest position, 1.58 × about the stage's
// position at 0 V with the form chosen on the first base's residual.
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
