// The residual loop on simulator data (test_residual_sim_cases.h): thermal drift traced to the temperature
// column. No false discoveries without an extra effect: test_residual_sim_clean.cpp.
// Cross-axis and rate-dependent effects: test_residual_sim_coupling.cpp; periodic ones: test_residual_sim_periodic.cpp
// and test_residual_sim_disturbance.cpp (split so each file stays under the unit-test time rule).
#include "test_residual_sim_cases.h"

using namespace residual_sim;

TEST(ResidualSim, ThermalDriftIsTracedToTheTemperatureColumn) { expect_found("thermal_drift", "aux_signal"); }
