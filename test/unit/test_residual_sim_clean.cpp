// The residual loop on simulator data (test_residual_sim_cases.h) without an extra effect: nothing may be added
// that gains < 2 % TEST MAE.
#include "test_residual_sim_cases.h"

using namespace residual_sim;

TEST(ResidualSim, NoFalseDiscoveriesWithoutAnExtraEffect) {
  const pa::ResidualResult r = trace("");
  double prev = r.before_test.mae_nm;
  for (const auto& e : r.effects) {
    EXPECT_GE(1.0 - e.test_after.mae_nm / prev, 0.02) << "added " << e.family << " for less than 2 % TEST MAE";
    prev = e.test_after.mae_nm;
  }
}
