// Sanity gates (one test per gate) and `--model auto` (issue 11 items 3 and 4; the choice rule of issue 26 item 2).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <random>

#include "piezo_compensation/analysis/model_selection.h"
#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/start_state.h"
#include "piezo_compensation/sim/stage.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/training/lasso.h"
#include "test_models_data.h"

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

TEST(ModelSelection, AutoChoosesByTheSlowErrorOnAnotherStage) {
  // A short piece of the low-voltage Preisach + creep stage: physics none of the candidates is written from.
  const auto stage = sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/lowvolt_preisach_creep.yaml");
  const io::Dataset all = sim::simulate_stage(stage, 11, 25.0);
  const std::size_t cut = all.size() * 4 / 5;
  const io::Dataset train = all.slice(0, cut), val = all.slice(cut, all.size());
  analysis::SelectionRequest rq = analysis::selection_request(train, &val, all, cut, "c");
  const analysis::Selection sel = analysis::select_model(rq);
  ASSERT_TRUE(sel.model);
  const auto cands = analysis::default_candidates();
  // Every default candidate, then the first choice again with its output map when it is a PI or Preisach kind.
  ASSERT_GE(sel.table.size(), cands.size());
  ASSERT_LE(sel.table.size(), cands.size() + 1);
  if (sel.table.size() > cands.size()) EXPECT_TRUE(has(sel.table.back().candidate.label, " + output map"));
  EXPECT_EQ(sel.table[0].candidate.kind, "linear");
  double best = INFINITY, best_mae = INFINITY;
  for (const auto& r : sel.table)
    if (r.refused.empty()) best = std::min(best, r.slow.overall_nm), best_mae = std::min(best_mae, r.score.free_run.mae_nm);
  // The 5-s tail (no holds) is scored in 32 blocks (min_blocks), moves and cold fold only.
  EXPECT_NEAR(sel.table[sel.best].slow.block_s, 5.0 / 32.0, 0.01);
  EXPECT_EQ(sel.table[sel.best_overall].slow.overall_nm, best);
  const auto& chosen = sel.table[sel.best];
  if (sel.best != sel.best_overall) {
    EXPECT_LT(chosen.parameters, sel.table[sel.best_overall].parameters);
    EXPECT_TRUE(analysis::within_noise(sel.table[sel.best_overall].slow, chosen.slow));
  }
  EXPECT_EQ(sel.model->kind(), chosen.candidate.kind);
  EXPECT_NEAR(sel.model->meta.validation.at("free_run_mae_nm"), chosen.score.free_run.mae_nm, 1e-9);
  EXPECT_LT(chosen.score.free_run.mae_nm, 0.10 * sel.scale.position_range_nm);
  EXPECT_LT(chosen.score.free_run.mae_nm, 2.0 * best_mae);
  const YAML::Node y = sel.model->meta.selection;
  ASSERT_TRUE(y && y["candidates"]);
  EXPECT_EQ(y["candidates"].size(), sel.table.size());
  EXPECT_EQ(y["chosen_kind"].as<std::string>(), sel.model->kind());
  EXPECT_FALSE(y["reason"].as<std::string>().empty());
  EXPECT_TRUE(y["candidates"][sel.best]["overall_nm"]);
  const std::string table = analysis::selection_table(sel);
  EXPECT_TRUE(has(table, "**chosen**")) << table;
  EXPECT_TRUE(has(table, "| kind | parameters | moves [nm] | holds [nm] | hold ends [nm] | cold fold [nm] | carry-over [nm] | "
                        "overall [nm] |"))
      << table;
  // The carry-over fold ran for every candidate that passed (10 s of training at 200 Hz: 1000 rows per half).
  for (std::size_t k = 0; k < sel.table.size(); ++k)
    if (sel.table[k].refused.empty()) {
      EXPECT_EQ(sel.table[k].slow.blocks.carry.size(), 32u) << sel.table[k].candidate.label;
      EXPECT_TRUE(std::isfinite(sel.table[k].slow.carry_nm)) << sel.table[k].candidate.label;
      EXPECT_TRUE(y["candidates"][k]["carry_over_nm"]) << sel.table[k].candidate.label;
    }
  EXPECT_TRUE(has(table, "Choice: " + sel.reason)) << table;
  std::printf("%s\n", table.c_str());
}

// ---- the choice rule on hand-made block errors (issue 26 item 2) ----

namespace {

analysis::SlowScore slow(std::vector<double> moves, std::vector<double> holds, std::vector<double> ends,
                         std::vector<double> cold = {}) {
  analysis::SlowErrors e;
  e.moves = std::move(moves);
  e.holds = std::move(holds);
  e.hold_ends = std::move(ends);
  e.cold = std::move(cold);
  analysis::SlowScoreOptions o;
  o.noise_nm = 1.0;
  return analysis::summarise_slow(e, o);
}

}  // namespace

TEST(SlowScore, HoldsAreFoundFromTheVoltage) {
  io::Dataset d;
  auto& a = d.add_axis("c");
  // 10 Hz: 100 moving samples, a 70-s hold, 20 moving, a 5-s dwell (too short), 20 moving, a 61-s hold to the end.
  std::vector<double> v;
  for (int i = 0; i < 100; ++i) v.push_back(0.1 * i);
  v.insert(v.end(), 700, 5.0);
  for (int i = 0; i < 20; ++i) v.push_back(4.9 - 0.1 * i);
  v.insert(v.end(), 50, 1.0);
  for (int i = 0; i < 20; ++i) v.push_back(1.1 + 0.1 * i);
  v.insert(v.end(), 610, -2.0);
  for (std::size_t i = 0; i < v.size(); ++i) d.time_s.push_back(0.1 * double(i)), a.voltage_v.push_back(v[i]), a.position_nm.push_back(0);
  const auto h = analysis::voltage_holds(d, "c", 0);
  ASSERT_EQ(h.size(), 2u);
  EXPECT_EQ(h[0].begin, 100u);
  EXPECT_EQ(h[0].end, 800u);
  EXPECT_EQ(h[1].begin, 890u);
  EXPECT_EQ(h[1].end, v.size());
  // From row 850 on only the last hold is left.
  EXPECT_EQ(analysis::voltage_holds(d, "c", 850).size(), 1u);
}

TEST(SlowScore, BlockMeansTakeTheWhiteNoiseOutAndHoldEndsAreTheirLastPart) {
  // Reference: alternating ±20 nm noise about 0; prediction 0 (a perfect model), then 0 with a 10 nm offset in
  // the last 30 samples of the hold.
  const std::size_t n = 300;
  std::vector<double> ref(n), pred(n, 0.0);
  for (std::size_t i = 0; i < n; ++i) ref[i] = (i % 2 ? 20.0 : -20.0);
  const std::vector<analysis::VoltageHold> holds{{100, 200}};
  auto e = analysis::slow_errors(pred, ref, holds, 0, 50, 30);
  ASSERT_EQ(e.moves.size(), 4u);  // 0-50, 50-100, 200-250, 250-300
  ASSERT_EQ(e.holds.size(), 2u);
  ASSERT_EQ(e.hold_ends.size(), 1u);
  for (double x : e.moves) EXPECT_NEAR(x, 0.0, 1e-12);  // the noise averaged away (per-sample MAE: 20 nm)
  EXPECT_NEAR(e.hold_ends[0], 0.0, 1e-12);
  for (std::size_t i = 170; i < 200; ++i) pred[i] = 10.0;
  e = analysis::slow_errors(pred, ref, holds, 0, 50, 30);
  EXPECT_NEAR(e.hold_ends[0], 10.0, 1e-12);
  EXPECT_NEAR(e.holds[1], 6.0, 1e-12);  // 30 of its 50 samples off by 10
  // Scored from row 120: the hold is clipped, the moves before it dropped.
  e = analysis::slow_errors(pred, ref, holds, 120, 50, 30);
  EXPECT_EQ(e.moves.size(), 2u);
  EXPECT_EQ(e.holds.size(), 2u);  // 120-170 and 170-200 (30 ≥ half a block)
  analysis::SlowScoreOptions o;
  o.noise_nm = 1.0;
  const auto s = analysis::summarise_slow(e, o);
  EXPECT_NEAR(s.hold_ends_nm, 10.0, 1e-12);
  EXPECT_NEAR(s.worst_hold_end_nm, 10.0, 1e-12);
  // overall: moves 0, holds 5, hold ends 10 (weight 3.25), no cold fold, noise 1 nm:
  // ((0+1)(5+1)(10+1)^3.25)^(1/5.25) − 1.
  EXPECT_NEAR(s.overall_nm, std::pow(6.0 * std::pow(11.0, 3.25), 1.0 / 5.25) - 1.0, 1e-12);
  // By ratio, not by scale: a column 1000× larger for everyone does not change the order of two candidates.
  analysis::SlowErrors a{{2.0}, {}, {}, {500.0}, {}}, b{{4.0}, {}, {}, {450.0}, {}};
  EXPECT_LT(analysis::summarise_slow(a, o).overall_nm, analysis::summarise_slow(b, o).overall_nm);
  EXPECT_TRUE(std::isnan(s.cold_nm));
}

TEST(SlowScore, HoldEndsDecideOverNoiseOnTheMoves) {
  // The case: linear 0.1 nm better on the moves (noise), but 20 nm off at the hold ends vs 10.
  const auto lin = slow({5.0, 5.1, 4.9, 5.0, 5.2, 4.8}, {8, 9, 7}, {20.0, 19.0, 21.0}, {6, 6, 6, 6});
  const auto prony = slow({5.1, 5.2, 5.0, 5.1, 5.3, 4.9}, {4, 5, 4}, {10.0, 9.0, 11.0}, {6, 6, 6, 6});
  const auto c = analysis::choose_candidate({{"linear", 3, &lin}, {"pi_creep_prony", 25, &prony}});
  EXPECT_EQ(c.chosen, 1u);
  EXPECT_EQ(c.best_overall, 1u);
  EXPECT_TRUE(has(c.reason, "pi_creep_prony: lowest overall")) << c.reason;
  EXPECT_TRUE(has(c.reason, "linear (3 parameters) within noise on moves and cold fold but")) << c.reason;
  EXPECT_TRUE(has(c.reason, "20 nm on hold ends")) << c.reason;
  std::printf("%s\n", c.reason.c_str());
}

TEST(SlowScore, WithinTheNoiseTheFewerParametersWin) {
  // Two candidates whose block errors differ by ±0.5 nm either way: no column separates them.
  const auto big = slow({3.0, 3.5, 2.5, 3.0, 3.6, 2.4}, {2.0, 2.5, 1.5, 2.0}, {2.0, 3.0, 2.5, 2.2}, {4, 4, 4, 4});
  const auto small = slow({3.4, 3.1, 2.9, 2.6, 4.0, 2.2}, {2.5, 2.0, 2.0, 1.6}, {2.4, 2.6, 2.9, 1.9}, {4.2, 3.8, 4.3, 3.9});
  ASSERT_LT(big.overall_nm, small.overall_nm);
  EXPECT_TRUE(analysis::within_noise(big, small));
  const auto c = analysis::choose_candidate({{"preisach_creep_prony", 120, &big}, {"pi", 12, &small}, {"refused", 1, nullptr}});
  EXPECT_EQ(c.best_overall, 0u);
  EXPECT_EQ(c.chosen, 1u);
  EXPECT_TRUE(has(c.reason, "pi: within the noise of preisach_creep_prony on every column")) << c.reason;
  EXPECT_TRUE(has(c.reason, "with 12 instead of 120 parameters")) << c.reason;
  // Clearly better on the moves (6 paired blocks, all 1 nm lower): the bigger model stays.
  const auto worse_moves = slow({4.0, 4.5, 3.5, 4.0, 4.6, 3.4}, {2.0, 2.5, 1.5, 2.0}, {2.0, 3.0, 2.5, 2.2}, {4, 4, 4, 4});
  std::vector<std::string> why;
  EXPECT_FALSE(analysis::within_noise(big, worse_moves, &why));
  EXPECT_EQ(why, std::vector<std::string>{"moves"});
  EXPECT_EQ(analysis::choose_candidate({{"preisach_creep_prony", 120, &big}, {"pi", 12, &worse_moves}}).chosen, 0u);
  // Only refused candidates: no choice.
  EXPECT_EQ(analysis::choose_candidate({{"a", 1, nullptr}}).chosen, SIZE_MAX);
}

namespace {
// Predicts (seconds since its reset)² in nm at 10 Hz: its error shows where the run started.
class ResetModel : public models::Model {
 public:
  std::string kind() const override { return "reset_probe"; }
  void reset(double, double) override { k_ = 0; }
  double predict(const models::ModelInput&) const override { return 0.01 * double(k_) * double(k_); }
  void commit(const models::ModelInput&, double) override { ++k_; }
  std::unique_ptr<models::Model> clone() const override { return std::make_unique<ResetModel>(*this); }
  bool uses_position_history() const override { return false; }
  YAML::Node to_yaml() const override { return YAML::Node(); }
  std::size_t num_parameters() const override { return 1; }

 private:
  long k_ = 0;
};

// 10 Hz, 600 s; the voltage keeps moving (no holds); the position of row i is position(i).
template <class F>
io::Dataset probe_recording(F position) {
  io::Dataset d;
  auto& a = d.add_axis("c");
  for (int i = 0; i < 6000; ++i) {
    d.time_s.push_back(0.1 * i);
    a.voltage_v.push_back(std::sin(0.01 * i));
    a.position_nm.push_back(position(i));
  }
  return d;
}
}  // namespace

TEST(SlowScore, TheColdFoldStartsFromRestAtTheHeldOutPartAndIsScoredAfterAWindow) {
  // The position is what the probe predicts when reset at row 3000: 0 before, (t − 300 s)² after.
  const io::Dataset d =
      probe_recording([](int i) { return i < 3000 ? 0.0 : 0.01 * double(i - 3000) * double(i - 3000); });
  const ResetModel m;
  // Warm: reset at row 0, far off in every scored block; cold (one start): reset at row 3000, exact; its blocks
  // start after the 30-s window (cold_window_s).
  analysis::SlowScoreOptions eighths;  // 300 s in 30-s blocks (the default, 32 blocks, would cut 9.4-s ones)
  eighths.min_blocks = 8;
  analysis::SlowScoreOptions one = eighths;
  one.cold_starts = 1;
  const auto s = analysis::slow_score(m, d, 3000, "c", one);
  EXPECT_EQ(s.blocks.moves.size(), 10u);  // 300 s in 30-s blocks
  EXPECT_TRUE(s.blocks.holds.empty());
  EXPECT_GT(s.moves_nm, 1e5);
  EXPECT_EQ(s.blocks.cold.size(), 9u);
  EXPECT_NEAR(s.cold_nm, 0.0, 1e-6);
  EXPECT_NEAR(s.block_s, 30.0, 1e-9);
  // A separate file (score_from 0): the cold fold is the warm run after the 30-s window; with the start estimate
  // shifted by it, the mean error of that window (the probe's 0.01·k² over rows 0…299 against 0).
  const auto t = analysis::slow_score(m, d, 0, "c", one);
  ASSERT_EQ(t.blocks.cold.size(), t.blocks.moves.size() - 1);
  for (std::size_t i = 0; i < t.blocks.cold.size(); ++i) EXPECT_NEAR(t.blocks.cold[i], t.blocks.moves[i + 1], 1e-6);
  analysis::SlowScoreOptions estimated = one;
  estimated.cold_start_estimate = true;
  const auto u = analysis::slow_score(m, d, 0, "c", estimated);
  // The start estimate's offset (rest kept: the probe's other histories only add to its error), weighted by the
  // candidates' spread, so near the plain mean of 0.01·k² over rows 0…299 (298.5 nm) but not equal to it.
  models::StartOptions so;
  so.window_s = 30.0;
  const models::StartEstimate e = models::estimate_start(m, d, "c", so);
  EXPECT_TRUE(e.history.rest) << e.describe();
  const double offset = -e.offset_nm;
  EXPECT_NEAR(offset, 298.5, 0.05 * 298.5);
  ASSERT_EQ(u.blocks.cold.size(), u.blocks.moves.size() - 1);
  for (std::size_t i = 0; i < u.blocks.cold.size(); ++i) EXPECT_NEAR(u.blocks.cold[i], u.blocks.moves[i + 1] - offset, 1e-6);
  // Four starts (the default) at rows 3000, 3375, 3750, 4125, each scored after its 30-s window: 9 + 8 + 7 + 5
  // blocks (a last part of at least half a block counts); the first start's exact, the later ones off (the probe
  // restarted later than the position did).
  const auto f = analysis::slow_score(m, d, 3000, "c", eighths);
  ASSERT_EQ(f.blocks.cold.size(), 29u);
  for (std::size_t i = 0; i < f.blocks.cold.size(); ++i)
    if (i < 9) EXPECT_NEAR(f.blocks.cold[i], 0.0, 1e-6);
    else EXPECT_GT(f.blocks.cold[i], 1.0);
  // A short validation part (100 s, under 8 or 32 blocks) is cut into eighths or 32 blocks (3.1 s: 31 rows).
  EXPECT_NEAR(analysis::slow_score(m, d, 5000, "c", eighths).block_s, 12.5, 1e-9);
  EXPECT_NEAR(analysis::slow_score(m, d, 5000, "c").block_s, 3.1, 1e-9);
}

// The carry-over fold (SlowScoreOptions::carry_fold): the half-fit model runs free from rest over the whole training
// part and is scored in blocks over its second half only. The probe predicts (t since reset)²: against a position
// of 0 everywhere its block means are known in closed form; in the overall the column counts carry_weight.
TEST(SlowScore, TheCarryOverFoldScoresTheSecondHalfOfTheTrainingPart) {
  const io::Dataset d = probe_recording([](int) { return 0.0; });
  const ResetModel m;
  analysis::SlowScoreOptions o;
  o.min_blocks = 8;
  const std::vector<double> e = analysis::carry_over_errors(m, d, 3000, "c", o);
  ASSERT_EQ(e.size(), 10u);  // rows 3000…5999 in 30-s blocks of 300 rows
  for (std::size_t b = 0; b < e.size(); ++b) {
    double mean = 0;  // mean of 0.01·k² over the block's rows k
    for (std::size_t k = 3000 + 300 * b; k < 3300 + 300 * b; ++k) mean += 0.01 * double(k) * double(k) / 300.0;
    EXPECT_NEAR(e[b], mean, 1e-6 * mean);
  }
  EXPECT_TRUE(analysis::carry_over_errors(m, d, 6000, "c", o).empty());
  // The column in the overall: moves of 1 nm and a carry-over of 100 nm at weight 1 → √((1 + ε)(100 + ε)) − ε,
  // ε the 1e-3-nm floor of the noise.
  analysis::SlowErrors b;
  b.moves = {1.0, 1.0};
  b.carry = {100.0, 100.0};
  analysis::SlowScoreOptions w;
  w.noise_nm = 1e-9;
  const analysis::SlowScore s = analysis::summarise_slow(b, w);
  EXPECT_NEAR(s.carry_nm, 100.0, 1e-9);
  EXPECT_NEAR(s.overall_nm, std::sqrt(1.001 * 100.001) - 0.001, 1e-9);
  // A candidate clearly worse on the carry-over alone is not within the noise of one that carries over.
  analysis::SlowErrors good = b, bad = b;
  good.carry = {1, 1.2, 0.9, 1.1, 1, 1.05, 0.95, 1};
  bad.carry = {30, 31, 29, 30, 32, 28, 30, 31};
  good.moves = bad.moves = {1, 1, 1, 1, 1, 1, 1, 1};
  std::vector<std::string> worse;
  EXPECT_FALSE(analysis::within_noise(analysis::summarise_slow(good, w), analysis::summarise_slow(bad, w), &worse));
  EXPECT_EQ(worse, std::vector<std::string>{"carry-over"});
}

// align_carry_over: while every scored candidate has the carry-over column it stays; once one lacks it (its half
// fit failed), every candidate is summarised without it, so the one without cannot win on fewer columns. A refused
// candidate does not count.
TEST(SlowScore, TheCarryOverColumnCountsOnlyWhenEveryCandidateHasIt) {
  analysis::SlowScoreOptions o;
  o.noise_nm = 1e-9;
  auto candidate = [&](std::vector<double> moves, std::vector<double> carry, const char* refused = "") {
    analysis::CandidateResult r;
    r.slow = analysis::summarise_slow({std::move(moves), {}, {}, {}, std::move(carry)}, o);
    r.refused = refused;
    return r;
  };
  std::vector<analysis::CandidateResult> t = {candidate({2, 2}, {100, 100}), candidate({3, 3}, {10, 10}),
                                              candidate({1, 1}, {}, "refused: a gate")};
  const double with_carry = t[0].slow.overall_nm;
  analysis::align_carry_over(t, o);
  EXPECT_EQ(t[0].slow.overall_nm, with_carry);  // the refused one does not count: the column stays
  EXPECT_EQ(t[0].slow.blocks.carry.size(), 2u);
  EXPECT_GT(t[0].slow.overall_nm, t[1].slow.overall_nm);  // the second carries over: it leads
  t.push_back(candidate({1, 1}, {}));  // scored, no carry-over: compared on moves alone, it would lead by far
  analysis::align_carry_over(t, o);
  for (const auto& r : t) {
    EXPECT_TRUE(r.slow.blocks.carry.empty());
    EXPECT_TRUE(std::isnan(r.slow.carry_nm));
  }
  EXPECT_NEAR(t[0].slow.overall_nm, 2.0, 1e-6);
  EXPECT_NEAR(t[1].slow.overall_nm, 3.0, 1e-6);
}

// select_model's carry-over fold sees only the training part's first half: a stage whose gain doubles halfway
// through the training part. The column equals the half fit made here by hand (rows [0, 4/5 of the half) fitted,
// the rest of the half its validation), run over the whole training part and scored on its second half; a fit that
// had seen the second half would follow the doubled gain there.
TEST(SlowScore, TheCarryOverFoldFitsTheFirstHalfOnly) {
  io::Dataset all;
  auto& a = all.add_axis("c");
  for (int i = 0; i < 5000; ++i) {
    const double t = 0.1 * i, v = 5.0 * std::sin(2 * M_PI * t / 40.0);
    all.time_s.push_back(t);
    a.voltage_v.push_back(v);
    a.position_nm.push_back((i < 2000 ? 10.0 : 20.0) * v);
  }
  const io::Dataset train = all.slice(0, 4000), val = all.slice(4000, 5000);
  analysis::SelectionRequest rq = analysis::selection_request(train, &val, all, 4000, "c");
  rq.candidates = {{"pi", "pi", YAML::Node(), false}};
  const analysis::Selection sel = analysis::select_model(rq);
  ASSERT_GE(sel.table.size(), 1u);  // then pi with its output map
  ASSERT_EQ(sel.table[0].candidate.label, "pi");
  const auto& got = sel.table[0].slow.blocks.carry;
  ASSERT_FALSE(got.empty());
  const io::Dataset fit_part = train.slice(0, 1600), half_val = train.slice(1600, 2000);
  training::FitRequest fr;
  fr.train = &fit_part;
  fr.validation = &half_val;
  fr.options = YAML::Node(YAML::NodeType::Map);
  fr.seed = rq.seed;
  const models::ModelPtr half_fit = training::fit_model("pi", fr);
  const std::vector<double> want = analysis::carry_over_errors(*half_fit, train, 2000, "c", sel.slow_options);
  ASSERT_EQ(got.size(), want.size());
  for (std::size_t b = 0; b < got.size(); ++b) EXPECT_NEAR(got[b], want[b], 1e-9 * (1 + want[b]));
  // The half fit keeps the first half's 10 nm/V: its blocks are those of 10·V against 20·V (2000 rows in 32nds).
  std::vector<double> p10, y;
  for (std::size_t i = 2000; i < 4000; ++i) p10.push_back(10.0 * a.voltage_v[i]), y.push_back(a.position_nm[i]);
  const std::vector<double> first_gain = analysis::block_errors(p10, y, 2000 / 32);
  ASSERT_EQ(first_gain.size(), got.size());
  double mean = 0;
  for (double e : first_gain) mean += e / static_cast<double>(first_gain.size());
  EXPECT_NEAR(sel.table[0].slow.carry_nm, mean, 0.02 * mean);
}

// The identification check's figure: (carry-over + block noise) / (moves + block noise); over 2 the line says the
// recording does not identify the kind and what to do; without a carry-over column it is not checked.
TEST(Identification, TheRatioAndWhatTheLineSays) {
  analysis::SlowScore s;
  s.blocks.carry = {38.0, 42.0};
  s.carry_nm = 40.0;
  s.moves_nm = 10.0;
  const analysis::Identification bad = analysis::identification(s, 2.0);
  EXPECT_NEAR(bad.ratio(), 42.0 / 12.0, 1e-12);
  EXPECT_TRUE(bad.flagged());
  const std::string line = bad.describe("pi", 40.0);
  EXPECT_NE(line.find("3.5x"), std::string::npos) << line;
  EXPECT_NE(line.find("40-s training recording does not identify it"), std::string::npos) << line;
  EXPECT_NE(line.find("Record longer"), std::string::npos) << line;
  s.carry_nm = 16.0;  // (16 + 2) / 12 = 1.5
  const analysis::Identification good = analysis::identification(s, 2.0);
  EXPECT_FALSE(good.flagged());
  EXPECT_NE(good.describe("pi", 40.0).find("the recording identifies it"), std::string::npos);
  s.blocks.carry.clear();  // the fold did not run
  const analysis::Identification none = analysis::identification(s, 2.0);
  EXPECT_FALSE(none.checked());
  EXPECT_FALSE(none.flagged());
  EXPECT_NE(none.describe("pi", 40.0).find("not checked: no carry-over figure"), std::string::npos);
  s.blocks.carry = {38.0};  // a carry-over figure, but no moves in the validation part
  s.moves_nm = NAN;
  const analysis::Identification no_moves = analysis::identification(s, 2.0);
  EXPECT_FALSE(no_moves.checked());
  EXPECT_NE(no_moves.describe("pi", 40.0).find("no moves"), std::string::npos);
}

// The loader's warning (the predictor logs it): over 2 it names the file and the ratio; within, or without the
// figure, nothing.
TEST(Identification, ALoaderWarnsOnlyForAFlaggedModelFile) {
  io::Dataset all;
  auto& a = all.add_axis("c");
  for (int i = 0; i < 400; ++i) {
    all.time_s.push_back(0.1 * i);
    a.voltage_v.push_back(std::sin(0.05 * i));
    a.position_nm.push_back(10.0 * a.voltage_v.back());
  }
  training::FitRequest fr;
  fr.train = &all;
  fr.options = YAML::Node(YAML::NodeType::Map);
  const models::ModelPtr m = training::fit_model("pi", fr);
  EXPECT_EQ(analysis::unidentified_model_warning(*m, "m.yaml"), "");
  m->meta.validation["carry_over_ratio"] = 1.9;
  EXPECT_EQ(analysis::unidentified_model_warning(*m, "m.yaml"), "");
  m->meta.validation["carry_over_ratio"] = 4.6;
  const std::string w = analysis::unidentified_model_warning(*m, "m.yaml");
  EXPECT_NE(w.find("model file m.yaml: its training recording did not identify it"), std::string::npos) << w;
  EXPECT_NE(w.find("4.6x worse"), std::string::npos) << w;
}

namespace {
// 500 s at 10 Hz of a 40-s sine on a Prandtl–Ishlinskii stage, y = 10·V + 4·play₁(V) + 6·play₃(V) nm (plays of
// half-width 1 and 3 V): ±5 V throughout, or ±1.5 V in the first 200 s (the recording's first half never moves the
// 3-V play: it cannot identify that weight) and ±5 V after.
io::Dataset play_recording(bool narrow_first_half) {
  io::Dataset all;
  auto& a = all.add_axis("c");
  double p1 = 0.0, p3 = 0.0;
  for (int i = 0; i < 5000; ++i) {
    const double t = 0.1 * i, v = (narrow_first_half && i < 2000 ? 1.5 : 5.0) * std::sin(2 * M_PI * t / 40.0);
    p1 = std::clamp(p1, v - 1.0, v + 1.0);
    p3 = std::clamp(p3, v - 3.0, v + 3.0);
    all.time_s.push_back(t);
    a.voltage_v.push_back(v);
    a.position_nm.push_back(10.0 * v + 4.0 * p1 + 6.0 * p3 + 0.5 * std::sin(1.7 * i));
  }
  return all;
}
}  // namespace

// check_identification (`piezo fit --model KIND`) and select_model (`--model auto`, stored as carry_over_ratio)
// agree: a recording that sweeps ±5 V throughout identifies the PI kind; one whose first half sweeps ±1.5 V does
// not (the half fit has no weight on the 3-V play, and the second half swings through it).
TEST(Identification, ARecordingWhoseFirstHalfSweepsLessIsFlagged) {
  for (bool narrow : {false, true}) {
    const io::Dataset all = play_recording(narrow);
    const io::Dataset train = all.slice(0, 4000), val = all.slice(4000, 5000);
    analysis::SelectionRequest rq = analysis::selection_request(train, &val, all, 4000, "c");
    rq.candidates = {{"pi", "pi", YAML::Node(), false}};
    const analysis::Selection sel = analysis::select_model(rq);
    ASSERT_TRUE(sel.identification.checked());
    ASSERT_EQ(sel.model->meta.validation.count("carry_over_ratio"), 1u);
    EXPECT_DOUBLE_EQ(sel.model->meta.validation.at("carry_over_ratio"), sel.identification.ratio());
    const analysis::Identification id = analysis::check_identification(rq, rq.candidates[0], *sel.table[0].model);
    ASSERT_TRUE(id.checked());
    EXPECT_NEAR(id.ratio(), sel.identification.ratio(), 1e-9 * sel.identification.ratio());
    std::cout << (narrow ? "narrow first half: " : "full sweep: ") << id.describe("pi", 400.0) << "\n";
    if (narrow) {
      EXPECT_GT(id.ratio(), 4.0);
      EXPECT_TRUE(id.flagged());
    } else {
      EXPECT_LT(id.ratio(), 1.5);
      EXPECT_FALSE(id.flagged());
    }
  }
}

// End to end on creep-protocol data with settings no other test uses (issue 26's done-when "auto's worst hold end
// within 10 % of the best kind's, on a stage the tests were not tuned on"): Preisach hysteresis with 100 switching
// voltages, a weak six-mode creep spectrum (4 s … 2 h, weights 0.01–0.025), 21 nm readings, seed 2626, 8 × (300-s history, 300-s hold);
// scenarios 1–5 train, 6–8 are held out (the model runs through 1–5 first; the cold fold starts at 6).
TEST(ModelSelection, OnACreepProtocolStageTheChoiceIsByHoldEnds) {
  sim::StageConfig stage =
      sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/mm3e_preisach_creep_protocol.yaml");
  auto& axis = stage.simulator.axes[2];
  axis.creep_spectrum_tau_s = {4.0, 20.0, 120.0, 600.0, 2000.0, 7000.0};
  axis.creep_spectrum_weights = {0.01, 0.01, 0.015, 0.015, 0.02, 0.025};
  axis.preisach_grid_count = 100;
  stage.protocol_parameters = YAML::Load("{scenarios: 8, history_s: 300, hold_s: 300}");
  const io::Dataset all = sim::simulate_stage(stage, 2626);
  const std::size_t per = all.size() / 8, cut = 5 * per;
  const io::Dataset train = all.slice(0, cut), val = all.slice(cut, all.size());
  analysis::SelectionRequest rq = analysis::selection_request(train, &val, all, cut, "c");
  rq.candidates = {{"linear (lasso features)", "linear", YAML::Node(), true},
                   {"pi", "pi", YAML::Node(), false},
                   {"preisach", "preisach", YAML::Node(), false},
                   {"pi_creep_prony", "pi_creep_prony", YAML::Node(), false},
                   {"preisach_creep_prony", "preisach_creep_prony", YAML::Node(), false}};
  const analysis::Selection sel = analysis::select_model(rq);
  ASSERT_TRUE(sel.model);
  std::printf("%s\n", analysis::selection_table(sel).c_str());
  double best_end = INFINITY;
  std::size_t by_mae = 0;
  for (std::size_t k = 0; k < sel.table.size(); ++k) {
    const auto& r = sel.table[k];
    std::printf("%s: hold ends vs truth mean %.2f nm, worst %.2f nm; free-run MAE vs measured %.2f nm\n",
                r.candidate.label.c_str(), r.slow.hold_ends_truth_nm, r.slow.worst_hold_end_truth_nm,
                r.score.free_run.mae_nm);
    if (!r.refused.empty()) continue;
    best_end = std::min(best_end, r.slow.worst_hold_end_truth_nm);
    if (r.score.free_run.mae_nm < sel.table[by_mae].score.free_run.mae_nm) by_mae = k;
  }
  const auto& chosen = sel.table[sel.best];
  // The three held-out holds and the dwells before their approaches (the voltage unchanged ≥ 60 s).
  EXPECT_GE(chosen.slow.blocks.hold_ends.size(), 3u);
  EXPECT_LE(chosen.slow.worst_hold_end_truth_nm, 1.1 * best_end);
  std::printf("chosen %s; by the old rule (free-run MAE vs measured) %s\n", chosen.candidate.label.c_str(),
              sel.table[by_mae].candidate.label.c_str());
}

// The lasso's candidates include play hinges max(play_r(V) − c, 0) placed on the training data's voltage span
// (features::candidate_features(&span)): weighted sums of them are any piecewise-linear map of a play output, so a
// linear model can follow loops that are not congruent. Without them, the lasso on the MM3E Preisach stage leaned on
// its past positions to follow the training loops and doubled its error on the next recording (docs/models.md).
// Here on that stage's relay Preisach (Gaussian relay density; the hinges are ramp hysterons of play outputs):
// fitted on 48 min, its error on another 30-min recording (from the simulator's known start) against its error
// on the 12-min continuation, with and without the hinges.
TEST(LassoLinear, PlayHingesCarryAPreisachLoopToTheNextRecording) {
  const auto stage = sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/mm3e_preisach.yaml");
  const io::Dataset rec = sim::simulate_stage(stage, 31, 3600.0), next = sim::simulate_stage(stage, 32, 2400.0);
  const std::size_t split = rec.size() * 4 / 5;
  const io::Dataset train = rec.slice(0, split);
  const features::DataSpan span = io::data_span(train, "c");
  auto fit_on = [&](const features::FeatureSpec& candidates) {
    const auto sel = training::run_lasso(candidates, train, "c");
    features::FeatureSpec chosen = training::select_features(sel.spec, sel.path.coefs[sel.path.index_1se]);
    chosen.mean.clear(), chosen.scale.clear();
    training::FitRequest req;
    req.train = &train;
    req.options["features"] = chosen.to_yaml();
    return training::fit_model("linear", req);
  };
  const features::FeatureSpec with = features::candidate_features(&span);
  const features::FeatureSpec without = features::identifiable_on(features::candidate_features(), span);
  ASSERT_EQ(with.size(), without.size() + 13);
  struct Result {
    double continuation, next;
  };
  auto measure = [&](const features::FeatureSpec& candidates) {
    const auto m = fit_on(candidates);
    return Result{analysis::score_validation(*m, rec, split, "c").free_run_truth.mae_nm,
                  analysis::score_validation(*m, next, next.size() / 4, "c").free_run_truth.mae_nm};
  };
  const Result h = measure(with), p = measure(without);
  std::cout << "lasso linear vs the truth, continuation / next recording: with hinges " << h.continuation << " / "
            << h.next << " nm, without " << p.continuation << " / " << p.next << " nm\n";
  EXPECT_LT(h.next, 1.5 * h.continuation);
  EXPECT_LT(h.next, 0.5 * p.next);
}

// Hold ends weigh as much as the other four columns together (hold_end_weight 3.25 = 1 + 1 + 0.25 + 1): the
// parked tip the choice is for. The shape of docs/models.md's (a′), a creep-protocol stage no test is tuned on: a
// kind better on moves, holds and hold ends whose half fit carries over worse keeps the choice; at weight 2 the
// carry-over column outvotes the hold ends and the other kind is chosen.
TEST(SlowScore, HoldEndsWeighAsMuchAsTheOtherColumnsTogether) {
  auto score = [](double moves, double holds, std::vector<double> ends, double cold, double carry, double weight) {
    analysis::SlowErrors e;
    for (int k = 0; k < 8; ++k) {
      const double wiggle = 0.1 * ((k * 7) % 5 - 2);
      e.moves.push_back(moves + wiggle), e.holds.push_back(holds + wiggle), e.cold.push_back(cold + wiggle);
      e.carry.push_back(carry + wiggle);
    }
    e.hold_ends = std::move(ends);
    analysis::SlowScoreOptions o;
    o.noise_nm = 1.1;
    o.hold_end_weight = weight;
    return analysis::summarise_slow(e, o);
  };
  const double w = analysis::SlowScoreOptions{}.hold_end_weight;
  EXPECT_EQ(w, 1.0 + 1.0 + analysis::SlowScoreOptions{}.cold_weight + analysis::SlowScoreOptions{}.carry_weight);
  for (const double weight : {w, 2.0}) {
    const auto prony = score(1.68, 1.70, {2.3, 2.8}, 12.2, 18.6, weight);
    const auto linear = score(3.27, 2.49, {3.0, 3.96}, 13.3, 4.0, weight);
    const auto c = analysis::choose_candidate({{"linear (lasso features)", 21, &linear}, {"preisach_creep_prony", 32, &prony}});
    std::printf("hold ends x%g: %s\n", weight, c.reason.c_str());
    EXPECT_EQ(c.chosen, weight == w ? 1u : 0u) << c.reason;
  }
}

// A candidate whose cold start is off by more than a tenth of the position range is left out when another's is not
// (a 94-µm cold fold on a 45-µm stage chose a model 18.6 % off on the next recording).
TEST(ModelChoice, AColdStartFarOffIsNotChosenWhenAnotherIsWithinRange) {
  analysis::SlowScore far, near, unscored_cold;
  far.cold_nm = 94000, near.cold_nm = 3000, unscored_cold.cold_nm = NAN;
  const auto out = analysis::cold_start_exclusions({&far, &near, nullptr, &unscored_cold}, 45000);
  ASSERT_EQ(out.size(), 4u);
  EXPECT_NE(out[0].find("cold start off: cold fold 94000 nm > 10 % of the position range (45000 nm)"), std::string::npos)
      << out[0];
  EXPECT_EQ(out[1], "");
  EXPECT_EQ(out[2], "");
  EXPECT_EQ(out[3], "");
  // when every candidate is far off, none is left out (the choice stays the usual one; the report says how far)
  near.cold_nm = 50000;
  for (const auto& s : analysis::cold_start_exclusions({&far, &near}, 45000)) EXPECT_EQ(s, "");
}

// Several validation recordings: each one's zero is no model's to know, so the slow score leaves it out; a model
// exact up to each recording's zero scores its noise, not the zeros.
TEST(ModelChoice, EachRecordingsZeroIsNotScored) {
  std::vector<io::Dataset> parts;
  std::mt19937 rng(3);
  std::normal_distribution<double> noise(0.0, 2.0);
  for (int k = 0; k < 3; ++k) {
    io::Dataset d;
    io::AxisSeries& c = d.add_axis("c");
    for (int i = 0; i < 6000; ++i) {
      const double v = 10.0 * std::sin(i / 300.0 + k);
      d.time_s.push_back(i / 10.0);
      c.voltage_v.push_back(v);
      c.position_nm.push_back(100.0 * v + 500.0 * (k - 1) + noise(rng));
    }
    d.source = "rec" + std::to_string(k);
    parts.push_back(d);
  }
  const io::Dataset joined = io::join_recordings(parts);
  const FakeModel exact(100.0, 0.0, YAML::Node());
  const analysis::SlowScore s = analysis::slow_score(exact, joined, 0, "c");
  std::cout << "[zeros] moves " << s.moves_nm << " nm\n";
  EXPECT_LT(s.moves_nm, 2.0);  // block means of 2-nm noise, not the ±500-nm zeros
  io::Dataset one = joined;
  one.recordings.clear();  // the same rows as one recording: its zero is one, the others' differences are scored
  EXPECT_GT(analysis::slow_score(exact, one, 0, "c").moves_nm, 200.0);
}

// Several recordings: each hold is scored from the zero of its own first hold_zero_s. A model exact on the moves
// whose only error in the holds is their level (the tip parks 100 or 200 nm off the voltage's line) scores that
// level as nothing; the creep that follows (30 nm over 300 s, τ 100 s) is what is left. With hold_zero_s = 0 the
// levels count again, less what each recording's zero takes of them.
TEST(ModelChoice, EachHoldIsScoredFromItsOwnStartWhenZerosAreUnknown) {
  std::vector<io::Dataset> parts;
  for (int k = 0; k < 2; ++k) {
    io::Dataset d;
    io::AxisSeries& c = d.add_axis("c");
    for (int i = 0; i < 9000; ++i) {  // 600 s of moves, then a 300-s hold at 10 V, at 10 Hz
      const bool hold = i >= 6000;
      const double v = hold ? 10.0 : 10.0 * std::sin(i / 300.0);
      const double th = hold ? (i - 6000) / 10.0 : 0.0;
      const double level = hold ? 100.0 * (k + 1) : 0.0, creep = hold ? 30.0 * (1.0 - std::exp(-th / 100.0)) : 0.0;
      d.time_s.push_back(i / 10.0);
      c.voltage_v.push_back(v);
      c.position_nm.push_back(100.0 * v + 300.0 * k + level + creep);
    }
    d.source = "rec" + std::to_string(k);
    parts.push_back(d);
  }
  const io::Dataset joined = io::join_recordings(parts);
  const FakeModel exact_moves(100.0, 0.0, YAML::Node());
  analysis::SlowScoreOptions o;
  o.cold_starts = 1;
  const analysis::SlowScore s = analysis::slow_score(exact_moves, joined, 0, "c", o);
  o.hold_zero_s = 0.0;
  const analysis::SlowScore level = analysis::slow_score(exact_moves, joined, 0, "c", o);
  std::printf("[hold zeros] holds %.1f nm, hold ends %.1f nm; scored against the recording's zero: %.1f, %.1f nm\n",
              s.holds_nm, s.hold_ends_nm, level.holds_nm, level.hold_ends_nm);
  // the creep from the hold's first 5 s (mean 0.7 nm) to its last 30 s (mean 28.3 nm)
  EXPECT_NEAR(s.hold_ends_nm, 27.5, 1.5);
  EXPECT_LT(s.holds_nm, 27.5);
  EXPECT_GT(level.hold_ends_nm, s.hold_ends_nm + 50.0);  // two thirds of 100 and 200 nm, with the creep
}
