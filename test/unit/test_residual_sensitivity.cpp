// The residual loop's sensitivity harness (analysis/residual/residual_sensitivity.h), small: a periodic encoder error of
// 1.5 σ (RMS over the reading noise) must be named on every stage, and nothing may be added to a stage without an
// effect (the bound of 5 % false positives, on a handful of stages: none). The full table: docs/closing-the-loop.md,
// "Sensitivity", `piezo residual-sensitivity`. Seeds other than the table's.
#include <gtest/gtest.h>

#include <cmath>
#include <iostream>
#include <string>
#include <vector>

#include "piezo_compensation/analysis/residual/estimator_fit.h"
#include "piezo_compensation/analysis/residual/residual_sensitivity.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/stage.h"

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

// Another axis of the data enters the residual loop through its fused position; `piezo residual` fits its model on
// TRAIN when no --other-model is given (analysis::fit_axis_model). On the coarse stage's axis a (250-nm steps,
// Preisach and a seven-mode creep the fitted kind is not written from; 2 h of random walk), the model with its identified error filter
// knows the position far better than the readings do on the rows it was not fitted on.
TEST(ResidualSensitivity, AnotherAxisFittedOnTrainIsFusedThroughItsEncoder) {
  const std::string src = PIEZO_SOURCE_DIR;
  const piezo::sim::StageConfig stage = piezo::sim::load_stage(src + "/config/stages/mm3e_coarse_stage.yaml");
  YAML::Node walk;
  walk["duration_s"] = 2.0 * 3600.0;
  const auto proto = piezo::protocols::make_protocol("random_walk", walk, stage.simulator.sample_rate_hz, 77);
  piezo::sim::ManipulatorSimulator sim(stage.simulator, 77);
  const piezo::io::Dataset d = sim.run(proto->program());
  const std::size_t n_fit = d.size() * 3 / 4;
  const piezo::models::ModelPtr bare = pa::fit_axis_model(d, n_fit, "a", "pi_creep_lti", 77, false);
  EXPECT_FALSE(bare->meta.estimator && !bare->meta.estimator.IsNull());
  const piezo::models::ModelPtr m = pa::fit_axis_model(d, n_fit, "a", "pi_creep_lti", 77, true);
  ASSERT_TRUE(m->meta.estimator && !m->meta.estimator.IsNull());
  const std::vector<double> fused = pa::fused_position(*m, d, "a");
  const auto& a = d.axis("a");
  double e_fused = 0, e_read = 0;
  for (std::size_t i = n_fit; i < d.size(); ++i)
    e_fused += std::fabs(fused[i] - a.true_position_nm[i]), e_read += std::fabs(a.position_nm[i] - a.true_position_nm[i]);
  std::cerr << "axis a on the validation rows, MAE against the truth: fused " << e_fused / (d.size() - n_fit)
            << " nm, readings " << e_read / (d.size() - n_fit) << " nm\n";
  EXPECT_LT(e_fused, 0.5 * e_read);
  EXPECT_THROW(pa::fit_axis_model(d, d.size(), "a", "pi_creep_lti", 77, true), std::invalid_argument);
}
