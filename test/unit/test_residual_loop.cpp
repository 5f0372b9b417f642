// The residual loop on synthetic data with one planted effect each (none declared to the tool): the right family
// is found, the TEST error comes back to what the model reaches without the effect, and nothing is added when
// there is no effect. (The simulator-driven version of these checks is test_residual_sim.cpp.)
#include <gtest/gtest.h>

#include <cstdlib>
#include <iostream>

#include "piezo_compensation/analysis/residual.h"
#include "test_residual_common.h"

namespace pa = piezo::analysis;
using piezo::test::Planted;

namespace {
struct Outcome {
  pa::ResidualResult res;
  double clean_mae_nm = 0;
};

Outcome run(Planted p, std::uint64_t seed) {
  const double hours = 3.0;
  const piezo::io::Dataset d = piezo::test::synthetic(p, hours, seed);
  const std::size_t n_train = d.size() * 2 / 3;
  const piezo::io::Dataset train = d.slice(0, n_train), test = d.slice(n_train, d.size());
  pa::ResidualOptions o;
  o.axis = "c";
  if (std::getenv("PIEZO_RESIDUAL_VERBOSE")) o.log = [](const std::string& s) { std::cerr << s << "\n"; };
  const std::size_t n_fit = static_cast<std::size_t>(static_cast<double>(n_train) * (1.0 - o.validation_fraction));
  auto base = piezo::test::LowpassLinearModel::fit(train, "c", n_fit);
  Outcome out;
  out.res = pa::trace_residual(*base, train, test, o);
  // The same model on the same data without the effect.
  const piezo::io::Dataset clean = piezo::test::synthetic(Planted::kNone, hours, seed);
  const piezo::io::Dataset ctrain = clean.slice(0, n_train), ctest = clean.slice(n_train, clean.size());
  auto cbase = piezo::test::LowpassLinearModel::fit(ctrain, "c", n_fit);
  const auto pred = piezo::models::stream_model(*cbase, ctest, "c").prediction;
  out.clean_mae_nm = pa::error_stats(pred, ctest.axis("c").position_nm).mae_nm;
  return out;
}

void expect_found(const Outcome& o, const std::string& family) {
  ASSERT_FALSE(o.res.effects.empty()) << "nothing found, expected " << family;
  EXPECT_EQ(o.res.effects.front().family, family);
  EXPECT_LT(o.res.effects.front().p_value, 0.01);
  EXPECT_LT(o.res.after_test.mae_nm, 1.15 * o.clean_mae_nm)
      << "before " << o.res.before_test.mae_nm << " nm, after " << o.res.after_test.mae_nm << " nm, clean "
      << o.clean_mae_nm << " nm";
  EXPECT_LT(o.res.after_test.mae_nm, o.res.before_test.mae_nm);
}
}  // namespace

TEST(ResidualLoop, FindsPositionPeriodicError) {
  const Outcome o = run(Planted::kPositionPeriodic, 21);
  ASSERT_NO_FATAL_FAILURE(expect_found(o, "position_periodic"));
  EXPECT_NEAR(o.res.effects.front().parameters.at("period_nm"), 400.0, 4.0);
  EXPECT_NEAR(o.res.effects.front().parameters.at("amplitude_nm"), 30.0, 6.0);
}

TEST(ResidualLoop, FindsTemperatureColumn) {
  const Outcome o = run(Planted::kAuxTemperature, 22);
  ASSERT_NO_FATAL_FAILURE(expect_found(o, "aux_signal"));
  EXPECT_EQ(o.res.effects.front().labels.at("signal"), "temperature_c");
}

TEST(ResidualLoop, FindsCrossAxisCoupling) {
  const Outcome o = run(Planted::kCrossAxis, 23);
  ASSERT_NO_FATAL_FAILURE(expect_found(o, "cross_axis"));
  EXPECT_EQ(o.res.effects.front().labels.at("signal"), "a_voltage_v");
  EXPECT_NEAR(o.res.effects.front().parameters.at("lag_s"), 1.0, 0.51);
  EXPECT_NEAR(o.res.effects.front().parameters.at("gain_nm_per_v"), 1.5, 0.2);
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
