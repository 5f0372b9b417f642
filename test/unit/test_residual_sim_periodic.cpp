// The residual loop on simulator data (test_residual_sim_cases.h): the encoder's interpolation error, periodic in
// position. The other effects: test_residual_sim.cpp, test_residual_sim_coupling.cpp,
// test_residual_sim_disturbance.cpp.
#include "test_residual_sim_cases.h"

using namespace residual_sim;

TEST(ResidualSim, EncoderInterpolationErrorIsPeriodicInPosition) { expect_found("encoder_periodic", "position_periodic"); }
