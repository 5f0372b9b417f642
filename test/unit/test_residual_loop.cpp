// The residual loop on synthetic data with one planted effect each (none declared to the tool): the right family
// is found, the TEST error comes back to what the model reaches without the effect, and nothing is added when
// there is no effect. The signal-driven cases (temperature column, cross-axis coupling) are in
// test_residual_loop_signals.cpp and test_residual_loop_coupling.cpp, split so each binary stays under 60 s.
// (The simulator-driven version of these checks is test_residual_sim.cpp.)
#include "test_residual_loop_cases.h"

using namespace residual_loop;

TEST(ResidualLoop, FindsPositionPeriodicError) {
  const Outcome o = run(Planted::kPositionPeriodic, 21);
  ASSERT_NO_FATAL_FAILURE(expect_found(o, "position_periodic"));
  EXPECT_NEAR(o.res.effects.front().parameters.at("period_nm"), 400.0, 4.0);
  EXPECT_NEAR(o.res.effects.front().parameters.at("amplitude_nm"), 30.0, 6.0);
}

TEST(ResidualLoop, FindsPeriodicDisturbance) {
  const Outcome o = run(Planted::kPeriodicDisturbance, 24);
  ASSERT_NO_FATAL_FAILURE(expect_found(o, "periodic_disturbance"));
  EXPECT_NEAR(o.res.effects.front().parameters.at("frequency_hz"), 0.0123, 0.0123 * 1e-3);
  EXPECT_NEAR(o.res.effects.front().parameters.at("amplitude_nm"), 35.0, 5.0);
}

TEST(ResidualLoop, NoFalseDiscoveries) {
  const Outcome o = run(Planted::kNone, 25);
  double prev = o.res.before_test.mae_nm;
  for (const auto& e : o.res.effects) {
    EXPECT_GE(1.0 - e.test_after.mae_nm / prev, 0.02) << "added " << e.family << " for less than 2 % TEST MAE";
    prev = e.test_after.mae_nm;
  }
  EXPECT_TRUE(o.res.effects.empty()) << "added " << (o.res.effects.empty() ? "" : o.res.effects.front().family);
}
