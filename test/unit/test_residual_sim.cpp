// The residual loop on simulator data (test_residual_sim_cases.h): thermal drift traced to the temperature
// column, and no false discoveries without an extra effect (nothing may be added that gains < 2 % TEST MAE).
// Cross-axis and rate-dependent effects: test_residual_sim_coupling.cpp; periodic ones: test_residual_sim_periodic.cpp
// and test_residual_sim_disturbance.cpp (split so each file stays under the unit-test time rule).
#include "test_residual_sim_cases.h"

using namespace residual_sim;

TEST(ResidualSim, ThermalDriftIsTracedToTheTemperatureColumn) { expect_found("thermal_drift", "aux_signal"); }
TEST(ResidualSim, NoFalseDiscoveriesWithoutAnExtraEffect) {
  const pa::ResidualResult r = trace("");
  double prev = r.before_test.mae_nm;
  for (const auto& e : r.effects) {
    EXPECT_GE(1.0 - e.test_after.mae_nm / prev, 0.02) << "added " << e.family << " for less than 2 % TEST MAE";
    prev = e.test_after.mae_nm;
  }
}
