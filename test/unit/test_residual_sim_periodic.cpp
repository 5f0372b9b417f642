// The residual loop on simulator data (periodic effects): the encoder's interpolation error, periodic in
// position, and a periodic disturbance in time (test_residual_sim_cases.h). The other effects:
// test_residual_sim.cpp, test_residual_sim_coupling.cpp.
#include "test_residual_sim_cases.h"

using namespace residual_sim;

TEST(ResidualSim, EncoderInterpolationErrorIsPeriodicInPosition) { expect_found("encoder_periodic", "position_periodic"); }
TEST(ResidualSim, PeriodicDisturbance) { expect_found("periodic_disturbance", "periodic_disturbance"); }
