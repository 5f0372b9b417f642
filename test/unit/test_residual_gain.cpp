// Gain effects on the Preisach/independent-creep stage of test_residual_gain_cases.h: (d) the stage
// without an effect gets nothing added; a gain driven by a signal that is not in the file ends in "not
// explained" with the size of what is left. (a) temperature: test_residual_gain_temperature.cpp; (b) time:
// test_residual_gain_drift.cpp; (c) other axis: test_residual_gain_other_axis.cpp.
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
TEST(ResidualGain, GainFromASignalNotInTheFileIsNotExplained) {
  const pa::ResidualResult r = trace(Gain::kHiddenTemperature);
  print("hidden temperature gain", r);
  EXPECT_FALSE(r.remainder.explained);
  EXPECT_GT(r.remainder.structure_nm, 2.0);
  ASSERT_FALSE(r.remainder.correlates.empty());
}
