// Two effects at once, on the Preisach/independent-creep stage of test_residual_gain_cases.h: an
// additive a → c coupling (0.4 nm/V of axis a, 1 s late) and a 2 %/°C stroke gain on a temperature the stage
// feels through 45 s + 240 s. Both must be named, one after the other with the base refitted between, and the
// TEST error against the truth must end within 15 % of the same stage without either effect (the base alone,
// which the (d) case of test_residual_gain shows gets nothing added).
#include "test_residual_gain_cases.h"

using namespace piezo::test::gain;

TEST(ResidualTwoEffects, CouplingAndATemperatureGainAreBothNamed) {
  const pa::ResidualResult r = trace(Gain::kTemperatureAndCoupling);
  print("two effects", r);
  bool coupling = false, gain = false;
  for (const auto& e : r.effects) {
    if (e.family == "cross_axis" && e.labels.at("signal").rfind("a_", 0) == 0) coupling = true;
    else if (e.family == "aux_gain" && e.labels.at("signal") == "temperature_c") gain = true;
    else ADD_FAILURE() << "added " << e.family << " besides the two effects";
  }
  EXPECT_TRUE(coupling) << "the a → c coupling was not named";
  EXPECT_TRUE(gain) << "the temperature gain was not named";
  const double clean = clean_base_truth_mae();
  std::cerr << "two effects: " << r.after_test_truth.mae_nm / clean << " × the clean stage's " << clean << " nm\n";
  EXPECT_LT(r.after_test_truth.mae_nm, 1.15 * clean) << "before " << r.before_test_truth.mae_nm << " nm";
}
