// The clean reference figures of the residual tests, each written once per ctest run by a CTest fixture (one shard
// per figure, cmake/parts/residual.cmake) for the binaries that compare against it, instead of each computing it.
#include "test_residual_gain_cases.h"
#include "test_residual_sim_cases.h"

// test_residual_sim*: the base's TEST MAE on the simulator protocol without an effect.
TEST(ResidualRefs, SimClean) {
  const piezo::io::Dataset clean = residual_sim::simulate("");
  piezo::test::write_reference_figure(residual_sim::kCleanRefEnv, residual_sim::clean_key(clean),
                                      [&] { return residual_sim::clean_mae(clean); });
}

// test_residual_gain_* and test_residual_two_effects: (d)'s base alone, TEST MAE against the truth.
TEST(ResidualRefs, GainBase) {
  namespace gain = piezo::test::gain;
  const piezo::io::Dataset clean = gain::with_gain(gain::Gain::kNone);
  piezo::test::write_reference_figure(gain::kCleanRefEnv, gain::clean_key(clean),
                                      [&] { return gain::clean_base_truth_mae(clean); });
}
