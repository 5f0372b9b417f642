// The fit plan (training/fit_plan.h): how the validation part is held out, the options, the origin stamp.
#include <gtest/gtest.h>

#include <fstream>
#include <stdexcept>
#include <string>

#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/training/fit_plan.h"

using namespace piezo;

namespace {

// `n` rows at 1 Hz on axis c; recordings beginning at `begins` (besides row 0).
io::Dataset rows(std::size_t n, const std::vector<std::size_t>& begins = {}) {
  io::Dataset d;
  for (std::size_t i = 0; i < n; ++i) d.time_s.push_back(static_cast<double>(i));
  auto& c = d.add_axis("c");
  c.voltage_v.assign(n, 1.0);
  c.position_nm.assign(n, 0.0);
  if (!begins.empty()) {
    d.recordings.push_back({"r0", 0, 0.0});
    for (std::size_t k = 0; k < begins.size(); ++k) d.recordings.push_back({"r" + std::to_string(k + 1), begins[k], 0.0});
  }
  d.source = "src.csv";
  return d;
}

}  // namespace

TEST(FitPlan, OneRecordingIsCutByRowsAndScoredAfterTheTrainingPart) {
  training::FitPlan plan;
  training::split_by_fraction(plan, rows(100), 0.8);
  EXPECT_EQ(plan.train.size(), 80u);
  EXPECT_EQ(plan.validation.size(), 20u);
  EXPECT_EQ(plan.split_at, 80u);
  EXPECT_EQ(&plan.score_data(), &plan.all);  // the validation continues the training part's history
  EXPECT_EQ(plan.validation.source, "src.csv");
  const training::FitRequest r = plan.request();
  EXPECT_EQ(r.train, &plan.train);
  EXPECT_EQ(r.validation, &plan.validation);
  training::split_by_fraction(plan, rows(100), 1.0);
  EXPECT_FALSE(plan.has_validation());
  EXPECT_EQ(plan.request().validation, nullptr);
  EXPECT_THROW(training::split_by_fraction(plan, rows(100), 0.1), std::invalid_argument);  // 10 rows: too few
  EXPECT_THROW(training::split_by_fraction(plan, rows(100), 1.5), std::invalid_argument);
}

TEST(FitPlan, SeveralRecordingsAreHeldOutWhole) {
  training::FitPlan plan;
  training::split_by_fraction(plan, rows(90, {30, 60}), 0.67);  // 2 of 3 recordings train
  EXPECT_EQ(plan.train.size(), 60u);
  EXPECT_EQ(plan.train.recording_count(), 2u);
  EXPECT_EQ(plan.validation.size(), 30u);
  EXPECT_EQ(plan.split_at, 0u);  // scored from its own start
  EXPECT_EQ(&plan.score_data(), &plan.validation);
  EXPECT_THROW(training::split_by_fraction(plan, rows(90, {30, 60}), 0.1), std::invalid_argument);
}

TEST(FitPlan, OptionsFromAFileThenSettings) {
  const std::string path = ::testing::TempDir() + "fit_plan_options.yaml";
  std::ofstream(path) << "n_play: 8\ncreep_input: voltage\n";
  const YAML::Node o = training::plan_options(path, {"n_play=12", "thresholds_v=[0, 1]"});
  EXPECT_EQ(o["n_play"].as<int>(), 12);
  EXPECT_EQ(o["creep_input"].as<std::string>(), "voltage");
  EXPECT_EQ(o["thresholds_v"].size(), 2u);
  EXPECT_THROW(training::plan_options("", {"no_value"}), std::invalid_argument);
  std::ofstream(path) << "- a list\n";
  EXPECT_THROW(training::plan_options(path, {}), std::invalid_argument);
  EXPECT_THROW(training::plan_options(path + ".missing", {}), std::invalid_argument);
}

TEST(FitPlan, TheOriginStampKeepsAFitsOwnSource) {
  models::PiCreepModel m({0, 1}, {1.0, 0.5}, 0.0, models::CreepParams{}, 1.0);
  io::Dataset train = rows(10);
  train.time_clock = "ros";
  training::stamp_origin(m, train, "a.csv b.csv");
  EXPECT_EQ(m.meta.time_clock, "ros");
  EXPECT_EQ(m.meta.training_source, "a.csv b.csv");
  m.meta.training_source = "fit's own";
  training::stamp_origin(m, train, "other.csv");
  EXPECT_EQ(m.meta.training_source, "fit's own");
  EXPECT_NE(m.meta.fitted_on, models::kFittedOnSimulated);
  train.origin = "simulated";
  training::stamp_origin(m, train, "");
  EXPECT_EQ(m.meta.fitted_on, models::kFittedOnSimulated);
}
