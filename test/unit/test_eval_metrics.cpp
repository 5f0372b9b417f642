#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "piezo_compensation/analysis/evaluation/eval_report.h"
#include "piezo_compensation/analysis/evaluation/evaluation.h"
#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/linear_model.h"
#include "piezo_compensation/models/pi_model.h"
#include "test_models_data.h"

using namespace piezo;
using namespace piezo::analysis;

TEST(Metrics, ValuesAndNoiseFloor) {
  const ErrorStats s = error_stats({1, 2, 3, 4}, {1, 4, 3, 1}, {1, 1, 0, 1});
  EXPECT_EQ(s.n, 3u);
  EXPECT_DOUBLE_EQ(s.mae_nm, (0 + 2 + 3) / 3.0);
  EXPECT_DOUBLE_EQ(s.rms_nm, std::sqrt((0 + 4 + 9) / 3.0));
  EXPECT_DOUBLE_EQ(s.max_nm, 3);
  EXPECT_DOUBLE_EQ(s.mean_nm, (0 - 2 + 3) / 3.0);
  EXPECT_NEAR(noise_floor_mae_nm(20.79), 16.59, 0.01);
  EXPECT_FALSE(error_stats({1}, {1}, {0}).valid());
  EXPECT_THROW(error_stats({1, 2}, {1}), std::invalid_argument);
}

namespace {
// Random walk with holds of a PI + creep model, noise σ = 20.79 nm, phase and segment columns.
io::Dataset study_like(models::Model& truth, std::uint64_t seed) {
  std::vector<int> phase;
  const auto v = testdata::random_walk_v(60000, seed, 0.001, &phase);
  io::Dataset d = testdata::make_dataset(truth, v, 11.0, kStudyEncoderNoiseNm, seed + 1, &phase);
  int seg = 0;
  for (std::size_t i = 1; i < d.size(); ++i) {
    if (d.phase[i] == 1 && d.phase[i - 1] != 1) ++seg;
    d.segment[i] = seg;
  }
  return d;
}
models::PiCreepModel truth_model() {
  models::CreepParams cp;
  cp.kind = models::CreepKind::kLti;
  cp.taus_s = {40, 900};
  cp.gains_nm_per_v = {1.5, 1.0};
  return models::PiCreepModel({0, 10, 20, 30}, {8, 2, 1, 0.5}, 0, cp, 11.0);
}
}  // namespace

TEST(Evaluation, HoldsComeFromPhaseAndSegment) {
  io::Dataset d;
  d.add_axis("c");
  for (int i = 0; i < 20; ++i) {
    d.time_s.push_back(i * 0.5);
    d.axis("c").voltage_v.push_back(0);
    d.axis("c").position_nm.push_back(0);
  }
  d.phase = {0, 0, 1, 1, 1, 0, 0, 1, 1, 1, 1, 1, 0, 1, 1, 1, 1, 1, 1, 0};
  d.segment = {0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2, 2, 2, 2, 2, 2};
  const auto h = find_holds(d);
  ASSERT_EQ(h.size(), 4u);  // the hold 7..11 is split at the segment change
  EXPECT_EQ(h[0].begin, 2u);
  EXPECT_EQ(h[0].end, 5u);
  EXPECT_EQ(h[1].end, 10u);
  EXPECT_EQ(h[2].segment, 2);
  EXPECT_DOUBLE_EQ(h[3].duration_s, 3.0);
  EXPECT_EQ(find_holds(d, 1.5).size(), 3u);  // 1.5, 1.5, 1.0 and 3.0 s long
}

TEST(Evaluation, PerfectModelScoresTheNoiseFloorAgainstMeasurementAndZeroAgainstTruth) {
  auto gen = truth_model();
  const io::Dataset d = study_like(gen, 3);
  auto model = truth_model();
  const ModelEvaluation ev = evaluate_model(model, "truth", d, nullptr, {});
  EXPECT_NEAR(ev.hysteresis.one_step.vs_truth.mae_nm, 0.0, 1e-9);
  EXPECT_NEAR(ev.creep.free_run.vs_truth.mae_nm, 0.0, 1e-9);
  EXPECT_NEAR(ev.hysteresis.one_step.vs_measured.mae_nm, noise_floor_mae_nm(kStudyEncoderNoiseNm), 0.5);
  ASSERT_FALSE(ev.finals.empty());
  for (const auto& f : ev.finals) EXPECT_NEAR(f.free_run_nm, f.truth_nm, 1e-9);
  EXPECT_GT(ev.creep.one_step.vs_measured.n, 1000u);
  EXPECT_GT(ev.hysteresis.one_step.vs_measured.n, 1000u);
}

TEST(Evaluation, FreeRunFeedsBackPredictionsOneStepFeedsMeasurements) {
  auto gen = truth_model();
  const io::Dataset d = study_like(gen, 5);
  // A model that is only the last measured position: D_{t-1}.
  features::FeatureSpec spec;
  features::FeatureDef lag;
  lag.type = "lagged_position";
  lag.lag_s = 1 / 11.0;
  spec.features.push_back(lag);
  models::LinearModel last(spec, 11.0, Eigen::VectorXd::Ones(1), 0.0);
  const SeriesPrediction p = predict_series(last, d, "c");
  const auto& m = d.axis("c").position_nm;
  for (std::size_t i = 1; i < 100; ++i) {
    EXPECT_DOUBLE_EQ(p.one_step[i], m[i - 1]);
    EXPECT_DOUBLE_EQ(p.free_run[i], m[0]);  // its own predictions: stuck at the first position
  }
}

namespace {
// Writes the report of `evs` on `d` into `dir` (created); returns its report.md.
std::string write_report(const std::string& dir, const EvalContext& ctx, const std::vector<ModelEvaluation>& evs,
                         const io::Dataset& d) {
  std::filesystem::create_directories(dir);
  write_eval_report(dir, ctx, evs, d, nullptr);
  std::ifstream md(dir + "/report.md");
  return std::string((std::istreambuf_iterator<char>(md)), {});
}
}  // namespace

TEST(EvalReport, WritesMarkdownJsonAndTraces) {
  auto gen = truth_model();
  const io::Dataset d = study_like(gen, 7);
  auto model = truth_model();
  std::vector<ModelEvaluation> evs = {evaluate_model(model, "pi_lti", d, nullptr, {})};
  const std::string dir = ::testing::TempDir() + "piezo_eval_report";
  EvalContext ctx;
  ctx.test_path = "test.csv";
  const std::string text = write_report(dir, ctx, evs, d);
  EXPECT_NE(text.find("Table 3"), std::string::npos);
  EXPECT_NE(text.find("16.6 nm"), std::string::npos);
  const YAML::Node js = YAML::LoadFile(dir + "/report.json");  // JSON is valid YAML
  EXPECT_EQ(js["models"][0]["name"].as<std::string>(), "pi_lti");
  EXPECT_NEAR(js["models"][0]["hysteresis"]["one_step"]["vs_truth"]["mae_nm"].as<double>(), 0.0, 1e-6);
  EXPECT_TRUE(std::filesystem::exists(dir + "/traces_test.csv"));
  EXPECT_TRUE(std::filesystem::exists(dir + "/traces_creep.csv"));
  // With an anchor the report says what the start estimate chose and fitted: here both creep modes' states.
  EvalOptions anchored;
  anchored.anchor_s = 30.0;
  evs = {evaluate_model(model, "pi_lti", d, nullptr, anchored)};
  ctx.anchor_s = anchored.anchor_s;
  write_eval_report(dir, ctx, evs, d, nullptr);
  const YAML::Node st = YAML::LoadFile(dir + "/report.json")["models"][0]["start_estimate"];
  ASSERT_TRUE(st.IsMap());
  EXPECT_EQ(st["creep_states_fitted"].as<int>(), 2);
  EXPECT_EQ(st["creep_state_shifts_nm"].size(), 2u);
  EXPECT_GT(st["candidates"].as<int>(), 1);
  EXPECT_GT(st["window_swept_fraction"].as<double>(), 0.0);
  EXPECT_NEAR(st["window_swept_fraction"].as<double>(),
              st["window_swept_v"].as<double>() / st["voltage_range_v"].as<double>(), 1e-8);  // JSON: 10 digits
}

TEST(Evaluation, SegmentListsAndSegmentScoring) {
  EXPECT_EQ(parse_segments("2"), std::vector<int>{2});
  EXPECT_EQ(parse_segments("3-5,8"), (std::vector<int>{3, 4, 5, 8}));
  EXPECT_THROW(parse_segments("3-x"), std::invalid_argument);
  EXPECT_THROW(parse_segments("5-3"), std::invalid_argument);
  io::Dataset d;
  d.add_axis("c");
  for (int i = 0; i < 8; ++i) {
    d.time_s.push_back(i);
    d.axis("c").voltage_v.push_back(0);
    d.axis("c").position_nm.push_back(0);
  }
  d.phase = {0, 1, 1, 0, 0, 1, 1, 0};
  d.segment = {0, 0, 0, 1, 1, 1, 1, 2};
  EXPECT_EQ(hold_mask(d, {1}), (std::vector<char>{0, 0, 0, 0, 0, 1, 1, 0}));
  EXPECT_EQ(hysteresis_mask(d, 0, {1, 2}), (std::vector<char>{0, 0, 0, 1, 1, 0, 0, 1}));
  EXPECT_EQ(hysteresis_mask(d, 3.5, {}), (std::vector<char>{0, 0, 0, 0, 1, 0, 0, 1}));
}

// The model file's identification check (`piezo fit`: validation carry_over_ratio) is carried into the report: the
// figure in report.json (null without it), and a line in report.md that says, over 2, what it means.
TEST(EvalReport, SaysWhetherTheModelsTrainingRecordingIdentifiedIt) {
  auto gen = truth_model();
  const io::Dataset d = study_like(gen, 7);
  auto plain = truth_model(), flagged = truth_model(), fine = truth_model();
  flagged.meta.validation["carry_over_ratio"] = 4.6;
  fine.meta.validation["carry_over_ratio"] = 1.2;
  const std::vector<ModelEvaluation> evs = {evaluate_model(plain, "plain", d, nullptr, {}),
                                            evaluate_model(flagged, "short_recording", d, nullptr, {}),
                                            evaluate_model(fine, "long_recording", d, nullptr, {})};
  const std::string dir = ::testing::TempDir() + "piezo_eval_identification";
  EvalContext ctx;
  ctx.test_path = "test.csv";
  const std::string text = write_report(dir, ctx, evs, d);
  EXPECT_NE(text.find("- short_recording: identification at fit 4.60x (over 2.0: its training recording did not "
                      "identify it"),
            std::string::npos)
      << text;
  EXPECT_NE(text.find("- long_recording: identification at fit 1.20x\n"), std::string::npos) << text;
  EXPECT_EQ(text.find("- plain: identification"), std::string::npos);
  const YAML::Node js = YAML::LoadFile(dir + "/report.json");
  EXPECT_TRUE(js["models"][0]["carry_over_ratio"].IsNull());
  EXPECT_DOUBLE_EQ(js["models"][1]["carry_over_ratio"].as<double>(), 4.6);
}
