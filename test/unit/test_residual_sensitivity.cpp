// The residual loop's sensitivity harness (analysis/residual_sensitivity.h), small: a periodic encoder error of
// 1.5 σ (RMS over the reading noise) must be named on every stage, and nothing may be added to a stage without an
// effect (the bound of 5 % false positives, on a handful of stages: none). The full table: docs/closing-the-loop.md,
// "Sensitivity", `piezo residual-sensitivity`. Seeds other than the table's.
#include <gtest/gtest.h>

#include <iostream>

#include "piezo_compensation/analysis/residual_sensitivity.h"

namespace pa = piezo::analysis;

TEST(ResidualSensitivity, PeriodicErrorOfOneAndAHalfSigmaFoundAndCleanStagesLeftAlone) {
  pa::SensitivityOptions o;
  o.families = {pa::SensitivityFamily::kPeriodic};
  o.sizes_sigma = {1.5};
  o.trials = 2;
  o.clean_trials = 3;
  o.hours = 6.0;  // as the table: shorter stages leave the base too much slow misfit to judge by
  o.seed = 3100;
  o.progress = [](const std::string& s) { std::cerr << s << "\n"; };
  const pa::SensitivityResult r = pa::run_sensitivity(o);
  std::cerr << pa::sensitivity_table(r, o);
  ASSERT_EQ(r.cells.size(), 1u);
  EXPECT_EQ(r.cells[0].detected, r.cells[0].trials) << "a 1.5 σ periodic encoder error was missed";
  EXPECT_EQ(r.clean_trials, 3);
  EXPECT_LE(r.clean_false, static_cast<int>(0.05 * r.clean_trials)) << "effects added to clean stages";
  EXPECT_NEAR(r.noise_sigma_nm, 20.8, 0.1);
}

TEST(ResidualSensitivity, UnknownFamilyIsNamed) {
  EXPECT_THROW(pa::parse_sensitivity_family("thermal"), std::invalid_argument);
  EXPECT_EQ(pa::parse_sensitivity_family("gain"), pa::SensitivityFamily::kGain);
}
