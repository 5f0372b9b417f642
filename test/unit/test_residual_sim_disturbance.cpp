// The residual loop on simulator data (test_residual_sim_cases.h): a periodic disturbance in time. The other
// effects: test_residual_sim.cpp, test_residual_sim_coupling.cpp, test_residual_sim_periodic.cpp.
#include "test_residual_sim_cases.h"

using namespace residual_sim;

TEST(ResidualSim, PeriodicDisturbance) { expect_found("periodic_disturbance", "periodic_disturbance"); }
