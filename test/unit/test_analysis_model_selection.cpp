// Sanity gates (one test per gate), the errors `--model auto` scores and its choice rule (one test per rule), and
// `--model auto` end to end on simulated stages.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <functional>
#include <random>

#include "piezo_compensation/analysis/selection/model_selection.h"
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
  // A bias of −3.2e8 nm cancelled by other terms.
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

// ---- the candidates ----

namespace {
bool listed(const std::vector<analysis::ModelCandidate>& c, const std::string& label) {
  return std::any_of(c.begin(), c.end(), [&](const analysis::ModelCandidate& x) { return x.label == label; });
}
}  // namespace

// The candidates come from the registry's auto_candidacy: the invertible physical kinds by default, each as fitted
// and with the output map; kinds that may read other columns only when named; a kind marked never, not even then.
TEST(AutoCandidates, TheRegistryDecidesAndOtherColumnsAreOptIn) {
  const auto c = analysis::default_candidates();
  for (const auto& x : c) EXPECT_EQ(models::model_kind(x.kind).auto_candidacy, models::AutoCandidacy::kDefault) << x.label;
  for (const char* k : {"pi", "pi_creep_lti", "preisach", "preisach_creep_prony"}) {
    EXPECT_TRUE(listed(c, k)) << k;
    EXPECT_TRUE(listed(c, std::string(k) + " + output map")) << k;
  }
  for (const char* k : {"linear", "dense", "lstm", "kan", "augmented"})
    EXPECT_FALSE(std::any_of(c.begin(), c.end(), [&](const analysis::ModelCandidate& x) { return x.kind == k; })) << k;
  // A kind joins by its flag, whatever its name.
  models::ModelKind probe{"zz_probe", "a probe kind", nullptr, nullptr, models::AutoCandidacy::kDefault};
  models::register_model_kind(probe);
  EXPECT_TRUE(listed(analysis::default_candidates(), "zz_probe"));
  probe.auto_candidacy = models::AutoCandidacy::kExtra;
  models::register_model_kind(probe);
  EXPECT_FALSE(listed(analysis::default_candidates(), "zz_probe"));
  EXPECT_TRUE(listed(analysis::default_candidates({"zz_probe"}), "zz_probe"));
  probe.auto_candidacy = models::AutoCandidacy::kNever;
  models::register_model_kind(probe);
  EXPECT_THROW(analysis::default_candidates({"zz_probe"}), std::invalid_argument);
  const auto extra = analysis::default_candidates({"linear", "kan"});
  EXPECT_TRUE(listed(extra, "linear (lasso features)"));
  EXPECT_TRUE(listed(extra, "kan"));
  EXPECT_THROW(analysis::default_candidates({"augmented"}), std::invalid_argument);
}

// ---- the errors the use cares about ----

namespace {
// 10 Hz; voltage v(i), position y(i); `hold` rows [hold_from, end) hold the voltage (no noise: the figures are exact).
io::Dataset series(int rows, const std::function<double(int)>& v, const std::function<double(int)>& y,
                   const std::string& source = "rec") {
  io::Dataset d;
  auto& c = d.add_axis("c");
  for (int i = 0; i < rows; ++i) {
    d.time_s.push_back(0.1 * i);
    c.voltage_v.push_back(v(i));
    c.position_nm.push_back(y(i));
  }
  d.source = source;
  return d;
}
double moving_v(int i) { return 10.0 * std::sin(i / 300.0); }
}  // namespace

// Moves: the predicted change over 10 s and over 60 s against the measured one, between 5-s means. A prediction off
// by a constant and drifting 1 nm/s is off by exactly 10 and 60 nm on them.
TEST(UseErrors, MovesAreTheErrorOfTheChangeOver10And60Seconds) {
  const io::Dataset d = series(6000, moving_v, [](int i) { return 100.0 * moving_v(i); });
  std::vector<double> p = d.axis("c").position_nm;
  for (std::size_t i = 0; i < p.size(); ++i) p[i] += 500.0 + 0.1 * double(i);
  const analysis::SlowErrors e = analysis::use_errors(p, d.axis("c").position_nm, d, "c", 0);
  ASSERT_EQ(e.move_short.size(), 118u);  // 120 windows of 5 s, pairs 2 windows apart
  ASSERT_EQ(e.move_long.size(), 108u);   // 12 windows apart
  for (double x : e.move_short) EXPECT_NEAR(x, 10.0, 1e-6);
  for (double x : e.move_long) EXPECT_NEAR(x, 60.0, 1e-6);
  EXPECT_TRUE(e.hold_creep.empty());
  // Scored from row 3000 on: only the windows from there.
  EXPECT_EQ(analysis::use_errors(p, d.axis("c").position_nm, d, "c", 3000).move_short.size(), 58u);
}

// No zero: each recording's unknown encoder zero cancels in every change, and no pair spans two recordings.
TEST(UseErrors, NoZeroIsNeededAndNoPairSpansTwoRecordings) {
  std::vector<io::Dataset> parts;
  for (int k = 0; k < 2; ++k)
    parts.push_back(series(3000, moving_v, [k](int i) { return 100.0 * moving_v(i) + 800.0 * k; }, "rec" + std::to_string(k)));
  const io::Dataset joined = io::join_recordings(parts);
  std::vector<double> p(joined.size());
  for (std::size_t i = 0; i < p.size(); ++i) p[i] = 100.0 * joined.axis("c").voltage_v[i];
  const analysis::SlowScore s = analysis::summarise_slow(analysis::use_errors(p, joined.axis("c").position_nm, joined, "c", 0));
  EXPECT_NEAR(s.move_short_nm, 0.0, 1e-9);
  EXPECT_NEAR(s.move_long_nm, 0.0, 1e-9);
  io::Dataset one = joined;
  one.recordings.clear();  // the same rows as one recording: the pairs across the join see the 800-nm step
  const analysis::SlowErrors e = analysis::use_errors(p, one.axis("c").position_nm, one, "c", 0);
  EXPECT_NEAR(*std::max_element(e.move_long.begin(), e.move_long.end()), 800.0, 1e-6);
}

// Hold creep: from each hold's first 5-s window, so where the hold's level sits does not count; the creep after it
// does. Moves leave the holds out.
TEST(UseErrors, HoldCreepIsScoredFromEachHoldsStart) {
  auto creep = [](int i) { return i >= 6000 ? 30.0 * (1.0 - std::exp(-(i - 6000) / 1000.0)) : 0.0; };
  auto v = [](int i) { return i >= 6000 ? moving_v(6000) : moving_v(i); };
  const io::Dataset d = series(9000, v, [&](int i) { return 100.0 * v(i) + (i >= 6000 ? 150.0 : 0.0) + creep(i); });
  std::vector<double> p(d.size());
  for (std::size_t i = 0; i < p.size(); ++i) p[i] = 100.0 * d.axis("c").voltage_v[i];  // no level, no creep
  const analysis::SlowErrors e = analysis::use_errors(p, d.axis("c").position_nm, d, "c", 0);
  ASSERT_EQ(e.hold_end_creep.size(), 1u);
  double first = 0, last = 0;  // the measured creep's means over the hold's first and last windows
  for (int i = 6000; i < 6050; ++i) first += creep(i) / 50.0;
  for (int i = 8950; i < 9000; ++i) last += creep(i) / 50.0;
  EXPECT_NEAR(e.hold_end_creep[0], -(last - first), 1e-6);  // predicted − measured
  EXPECT_EQ(e.hold_creep.size(), 59u);                     // every later window of the 300-s hold
  EXPECT_NEAR(e.hold_creep.back(), last - first, 1e-6);
  for (double x : e.move_short) EXPECT_NEAR(x, 0.0, 1e-9);  // the level step at the hold is not a move
}

// A held-out part shorter than four long moves is scored at its own time scale: windows, moves and blocks scaled by
// span / (4 · 60 s); a long one keeps the defaults. Scored so, the drifting prediction is off by its drift over the
// scaled moves.
TEST(UseErrors, AShortHeldOutPartIsScoredAtItsOwnTimeScale) {
  const io::Dataset d = series(1201, moving_v, [](int i) { return 100.0 * moving_v(i); });  // 120 s at 10 Hz
  const analysis::SlowScoreOptions o = analysis::fitted_to_part({}, d, 600);                 // the last 60 s
  EXPECT_NEAR(o.time_scale, 0.25, 1e-9);
  EXPECT_NEAR(o.mean_s, 1.25, 1e-9);
  EXPECT_NEAR(o.move_short_s, 2.5, 1e-9);
  EXPECT_NEAR(o.move_long_s, 15.0, 1e-9);
  EXPECT_EQ(analysis::fitted_to_part({}, d, 0).time_scale, 0.5);
  const io::Dataset long_part = series(6000, moving_v, [](int i) { return 100.0 * moving_v(i); });
  EXPECT_EQ(analysis::fitted_to_part({}, long_part, 0).time_scale, 1.0);
  std::vector<double> p = d.axis("c").position_nm;
  for (std::size_t i = 0; i < p.size(); ++i) p[i] += 0.1 * double(i);  // 1 nm/s
  const analysis::SlowScore s = analysis::summarise_slow(analysis::use_errors(p, d.axis("c").position_nm, d, "c", 600, o), o);
  EXPECT_NEAR(s.move_short_nm, 2.5, 1e-6);
  EXPECT_NEAR(s.move_long_nm, 15.0, 1e-6);
}

// ---- the choice rule ----

namespace {
analysis::SlowScore scored(double short_nm, double long_nm, double creep_nm, std::size_t n = 120, double spread = 1.0,
                           double noise_nm = 0.0) {
  analysis::SlowErrors e;
  for (std::size_t i = 0; i < n; ++i) {
    const double w = spread * std::sin(1.3 * double(i));  // block-to-block scatter, the same for every candidate
    e.move_short.push_back(short_nm + w);
    e.move_long.push_back(long_nm + w);
    e.hold_creep.push_back(creep_nm + w);
  }
  analysis::SlowScoreOptions o;
  o.noise_nm = noise_nm;
  return analysis::summarise_slow(e, o);
}
}  // namespace

// The best: the lowest overall, the geometric mean of the three columns.
TEST(ModelChoice, TheBestIsTheLowestGeometricMeanOfTheColumns) {
  const analysis::SlowScore a = scored(10, 40, 8), b = scored(20, 20, 20), c = scored(5, 80, 30);
  EXPECT_NEAR(a.overall_nm, std::cbrt(a.move_short_nm * a.move_long_nm * a.hold_creep_nm), 1e-3);
  const auto ch = analysis::choose_candidate({{"b", 10, &b}, {"a", 10, &a}, {"c", 10, &c}});
  EXPECT_EQ(ch.best_overall, 1u);
  EXPECT_EQ(ch.chosen, 1u);
  EXPECT_TRUE(has(ch.reason, "a: lowest overall")) << ch.reason;
}

// Within the noise of the best on every column, the fewest parameters win.
TEST(ModelChoice, WithinTheNoiseTheFewestParametersWin) {
  const analysis::SlowScore big = scored(10.0, 30.0, 8.0), small = scored(10.05, 30.1, 8.05, 120, 5.0);
  EXPECT_TRUE(analysis::within_noise(big, small));
  const auto ch = analysis::choose_candidate({{"preisach_creep_prony", 120, &big}, {"pi", 12, &small}});
  EXPECT_EQ(ch.best_overall, 0u);
  EXPECT_EQ(ch.chosen, 1u);
  EXPECT_TRUE(has(ch.reason, "pi: within the noise of preisach_creep_prony")) << ch.reason;
  EXPECT_TRUE(has(ch.reason, "with 12 instead of 120 parameters")) << ch.reason;
  // A difference the paired test finds consistent but under the noise of one entry is within the noise too.
  const analysis::SlowScore quiet = scored(10.0, 30.0, 8.0, 120, 1.0, 0.5), close = scored(10.2, 30.2, 8.2, 120, 1.0, 0.5);
  EXPECT_TRUE(analysis::within_noise(quiet, close));
  EXPECT_FALSE(analysis::within_noise(scored(10.0, 30.0, 8.0), close));  // without a noise figure it is worse
}

// Clearly worse on one column (the paired test over blocks) is not within the noise, however good the others; the
// reason names the column.
TEST(ModelChoice, ClearlyWorseOnOneColumnIsNotChosen) {
  const analysis::SlowScore best = scored(10, 30, 8), creepy = scored(9, 29, 20);
  std::vector<std::string> worse;
  EXPECT_FALSE(analysis::within_noise(best, creepy, &worse));
  ASSERT_EQ(worse, std::vector<std::string>{"hold creep"});
  const auto ch = analysis::choose_candidate({{"pi_creep_lti", 9, &best}, {"pi", 5, &creepy}});
  EXPECT_EQ(ch.chosen, 0u);
  EXPECT_TRUE(has(ch.reason, "pi (5 parameters) is clearly worse on hold creep")) << ch.reason;
}

// A refused candidate (no score) is never chosen; none scored: no choice.
TEST(ModelChoice, ARefusedCandidateIsNeverChosen) {
  const analysis::SlowScore s = scored(10, 30, 8);
  EXPECT_EQ(analysis::choose_candidate({{"refused", 1, nullptr}, {"pi", 12, &s}}).chosen, 1u);
  EXPECT_EQ(analysis::choose_candidate({{"a", 1, nullptr}}).chosen, SIZE_MAX);
}

// ---- `--model auto` end to end ----

// A stage none of the candidates is written from (relay Preisach, creep spectrum), 30 min with holds: the
// table, the stored selection and the rule: the chosen one has the lowest overall or is within the noise of it with
// fewer parameters.
TEST(ModelSelection, AutoChoosesByMovesAndHoldCreep) {
  const auto stage = sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/mm3e_preisach_creep.yaml");
  const io::Dataset all = sim::simulate_stage(stage, 11, 1800.0);
  const std::size_t cut = all.size() * 3 / 4;
  const io::Dataset train = all.slice(0, cut), val = all.slice(cut, all.size());
  analysis::SelectionRequest rq = analysis::selection_request(train, &val, all, cut, "c");
  const analysis::Selection sel = analysis::select_model(rq);
  ASSERT_TRUE(sel.model);
  const std::string table = analysis::selection_table(sel);
  std::printf("%s\n", table.c_str());
  ASSERT_EQ(sel.table.size(), analysis::default_candidates().size());
  double best = INFINITY;
  for (const auto& r : sel.table)
    if (r.refused.empty()) best = std::min(best, r.slow.overall_nm);
  EXPECT_EQ(sel.table[sel.best_overall].slow.overall_nm, best);
  const auto& chosen = sel.table[sel.best];
  EXPECT_GT(chosen.slow.blocks.move_long.size(), 20u);
  if (sel.best != sel.best_overall) {
    EXPECT_LT(chosen.parameters, sel.table[sel.best_overall].parameters);
    EXPECT_TRUE(analysis::within_noise(sel.table[sel.best_overall].slow, chosen.slow));
  }
  EXPECT_EQ(sel.model->kind(), chosen.candidate.kind);
  const YAML::Node y = sel.model->meta.selection;
  ASSERT_TRUE(y && y["candidates"]);
  EXPECT_EQ(y["candidates"].size(), sel.table.size());
  EXPECT_EQ(y["chosen"].as<std::string>(), chosen.candidate.label);
  EXPECT_TRUE(y["candidates"][sel.best]["move_60s_nm"]);
  EXPECT_TRUE(has(table, "| kind | parameters | 10-s moves [nm] | 60-s moves [nm] | hold creep [nm] |")) << table;
  EXPECT_TRUE(has(table, "Choice: " + sel.reason)) << table;
  EXPECT_TRUE(sel.identification.checked()) << sel.identification.unchecked;
}

// ---- identification ----

// The identification figure: (carry-over + noise) / (validation + noise); over 2 the line says the recording does
// not identify the kind and what to do; without a carry-over figure it is not checked.
TEST(Identification, TheRatioAndWhatTheLineSays) {
  const analysis::Identification bad = analysis::identification(40.0, 10.0, 2.0);
  EXPECT_NEAR(bad.ratio(), 42.0 / 12.0, 1e-12);
  EXPECT_TRUE(bad.flagged());
  const std::string line = bad.describe("pi", 40.0);
  EXPECT_TRUE(has(line, "3.5x")) << line;
  EXPECT_TRUE(has(line, "40-s training recording does not identify it")) << line;
  EXPECT_TRUE(has(line, "Record longer")) << line;
  const analysis::Identification good = analysis::identification(16.0, 10.0, 2.0);  // 18 / 12 = 1.5
  EXPECT_FALSE(good.flagged());
  EXPECT_TRUE(has(good.describe("pi", 40.0), "the recording identifies it"));
  const analysis::Identification none = analysis::identification(NAN, 10.0, 2.0);
  EXPECT_FALSE(none.checked());
  EXPECT_TRUE(has(none.describe("pi", 40.0), "not checked: no carry-over figure"));
  EXPECT_FALSE(analysis::identification(38.0, NAN, 2.0).checked());
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
