// Sanity gates (one test per gate) and `--model auto` (issue 11 items 3 and 4).
#include <gtest/gtest.h>

#include <cmath>

#include "piezo_compensation/analysis/model_selection.h"
#include "piezo_compensation/sim/stage.h"

using namespace piezo;

namespace {

// A model that predicts a fixed function of the voltage, with parameters chosen by the test.
class FakeModel : public models::Model {
 public:
  FakeModel(double gain_nm_per_v, double offset_nm, YAML::Node params) : gain_(gain_nm_per_v), offset_(offset_nm), params_(params) {}
  std::string kind() const override { return "fake"; }
  void reset(double, double) override {}
  double predict(const models::ModelInput& in) const override { return offset_ + gain_ * in.voltage_v; }
  void commit(const models::ModelInput&, double) override {}
  std::unique_ptr<models::Model> clone() const override { return std::make_unique<FakeModel>(*this); }
  bool uses_position_history() const override { return false; }
  YAML::Node to_yaml() const override { return params_; }
  std::size_t num_parameters() const override { return 2; }

 private:
  double gain_, offset_;
  YAML::Node params_;
};

// 0–10 V ramp up and down, position 100 nm/V plus a little noise: range 1000 nm, 200 s at 10 Hz.
io::Dataset ramp_data() {
  io::Dataset d;
  auto& a = d.add_axis("c");
  for (int i = 0; i < 2000; ++i) {
    d.time_s.push_back(0.1 * i);
    const double v = 10.0 * std::fabs(std::fmod(i / 500.0, 2.0) - 1.0);
    a.voltage_v.push_back(v);
    a.position_nm.push_back(100.0 * v + ((i * 7919) % 13 - 6));
  }
  return d;
}

std::string gate_message(const FakeModel& m) {
  const auto d = ramp_data();
  const auto score = analysis::score_validation(m, d, 1500, "c");
  return analysis::sanity_problem(m, &score, analysis::data_scale(d.slice(0, 1500), "c"));
}

YAML::Node params(const std::string& yaml) { return YAML::Load(yaml); }

bool has(const std::string& s, const std::string& part) { return s.find(part) != std::string::npos; }

}  // namespace

TEST(FitGates, AGoodFitPasses) {
  EXPECT_EQ(gate_message(FakeModel(100.0, 0.0, params("{weights_nm_per_v: [100], bias_nm: 0, tau_s: [1, 100]}"))), "");
}

TEST(FitGates, NonFiniteValidationErrorIsRefused) {
  const std::string m = gate_message(FakeModel(NAN, 0.0, params("{}")));
  EXPECT_TRUE(has(m, "kind fake")) << m;
  EXPECT_TRUE(has(m, "not finite")) << m;
  EXPECT_TRUE(has(m, "likely cause")) << m;
}

TEST(FitGates, FreeRunErrorAboveQuarterOfRangeIsRefused) {
  // 300 nm off on a 1000 nm range: 30 % > 25 %.
  const std::string m = gate_message(FakeModel(100.0, 300.0, params("{}")));
  EXPECT_TRUE(has(m, "kind fake")) << m;
  EXPECT_TRUE(has(m, "% of the data's position range")) << m;
  EXPECT_TRUE(has(m, "units")) << m;
  // 200 nm off (20 %) passes this gate.
  EXPECT_EQ(gate_message(FakeModel(100.0, 200.0, params("{}"))), "");
}

TEST(FitGates, HugeOffsetParameterIsRefused) {
  // The case: a bias of −3.2e8 nm cancelled by other terms.
  const std::string m = gate_message(FakeModel(100.0, 0.0, params("{bias_nm: -3.2e8, weights_nm_per_v: [100]}")));
  EXPECT_TRUE(has(m, "model.bias_nm")) << m;
  EXPECT_TRUE(has(m, "times the data's position range")) << m;
}

TEST(FitGates, CancellingWeightsAreRefused) {
  const std::string m = gate_message(FakeModel(100.0, 0.0, params("{weights_nm_per_v: [11588, -11488]}")));
  EXPECT_TRUE(has(m, "model.weights_nm_per_v[0]")) << m;
  EXPECT_TRUE(has(m, "cancelling weights")) << m;
}

TEST(FitGates, TimeConstantTheDataCannotSeeIsRefused) {
  // 150 s of training data, a creep mode at 1e5 s.
  const std::string m = gate_message(FakeModel(100.0, 0.0, params("{creep: {tau_max_s: 100000}}")));
  EXPECT_TRUE(has(m, "model.creep.tau_max_s")) << m;
  EXPECT_TRUE(has(m, "training data lasts 150 s")) << m;
  EXPECT_THROW(analysis::check_fit_sanity(FakeModel(100.0, 0.0, params("{creep: {tau_max_s: 100000}}")), nullptr,
                                          analysis::data_scale(ramp_data(), "c")),
               analysis::FitRejected);
}

TEST(ModelSelection, AutoKeepsTheBestCandidateOnAnotherStage) {
  // A short piece of the low-voltage Preisach + creep stage: physics none of the candidates is written from.
  const auto stage = sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/lowvolt_preisach_creep.yaml");
  const io::Dataset all = sim::simulate_stage(stage, 11, 25.0);
  const std::size_t cut = all.size() * 4 / 5;
  const io::Dataset train = all.slice(0, cut), val = all.slice(cut, all.size());
  analysis::SelectionRequest rq = analysis::selection_request(train, &val, all, cut, "c");
  const analysis::Selection sel = analysis::select_model(rq);
  ASSERT_TRUE(sel.model);
  const auto cands = analysis::default_candidates();
  ASSERT_EQ(sel.table.size(), cands.size());
  EXPECT_EQ(sel.table[0].candidate.kind, "linear");
  double best = INFINITY;
  for (const auto& r : sel.table)
    if (r.refused.empty()) best = std::min(best, r.score.free_run.mae_nm);
  EXPECT_EQ(sel.table[sel.best].score.free_run.mae_nm, best);
  EXPECT_EQ(sel.model->kind(), sel.table[sel.best].candidate.kind);
  EXPECT_NEAR(sel.model->meta.validation.at("free_run_mae_nm"), best, 1e-9);
  EXPECT_LT(best, 0.10 * sel.scale.position_range_nm);
  const YAML::Node y = sel.model->meta.selection;
  ASSERT_TRUE(y && y["candidates"]);
  EXPECT_EQ(y["candidates"].size(), cands.size());
  EXPECT_EQ(y["chosen_kind"].as<std::string>(), sel.model->kind());
  const std::string table = analysis::selection_table(sel);
  EXPECT_TRUE(has(table, "**chosen**")) << table;
  std::printf("%s\n", table.c_str());
}
