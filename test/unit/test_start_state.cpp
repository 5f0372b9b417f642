// The start-up state estimate (models/start_state.h; docs/models.md, "Start-up state estimate"): a model started on
// a recording whose history it has not seen, the first seconds choosing its hysteresis and creep state, against
// the offset-only anchor. Models run on physics they were not built from (Preisach stages, other seeds).
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <functional>
#include <iomanip>
#include <iostream>
#include <limits>

#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/track.h"
#include "piezo_compensation/estimation/error_filter.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/models/start_state.h"
#include "piezo_compensation/sim/stage.h"
#include "piezo_compensation/training/fitters.h"

using namespace piezo;

namespace {

const std::string kSrc = PIEZO_SOURCE_DIR;

struct Score {
  double mae_meas = 0, max_meas = 0, mae_true = 0, max_true = 0;
};

Score score_after(const std::vector<double>& pred, const io::Dataset& d, std::size_t first) {
  const io::AxisSeries& ax = d.axis("c");
  Score s;
  std::size_t n = 0;
  for (std::size_t i = first; i < d.size(); ++i, ++n) {
    const double em = std::abs(pred[i] - ax.position_nm[i]), et = std::abs(pred[i] - ax.true_position_nm[i]);
    s.mae_meas += em, s.mae_true += et;
    s.max_meas = std::max(s.max_meas, em), s.max_true = std::max(s.max_true, et);
  }
  s.mae_meas /= static_cast<double>(n), s.mae_true /= static_cast<double>(n);
  return s;
}

struct AnchoredRun {
  Score score;
  models::StartEstimate start;
  double seconds = 0;
};

AnchoredRun run_anchored(const models::Model& m, const io::Dataset& d, double window_s, bool history) {
  models::ModelPtr c = m.clone();
  models::StreamOptions so;
  so.anchor_s = window_s;
  so.anchor_history = history;
  const auto t0 = std::chrono::steady_clock::now();
  const models::StreamResult r = models::stream_model(*c, d, "c", so);
  AnchoredRun out;
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  out.score = score_after(r.prediction, d, r.first_scored);
  out.start = r.start;
  return out;
}

// The first row after `after_s` where the voltage has fallen over the last `fall_s` by at least `min_drop_v`, in
// both halves of it: a recording sliced there starts mid-motion on a descending branch, its history unknown to the
// model.
std::size_t descending_row(const io::Dataset& d, double after_s, double fall_s, double min_drop_v) {
  const std::vector<double>& v = d.axis("c").voltage_v;
  const std::size_t back = static_cast<std::size_t>(std::lround(fall_s * d.sample_rate_hz()));
  for (std::size_t i = back; i < d.size(); ++i) {
    if (d.time_s[i] - d.time_s[0] < after_s) continue;
    const double mid = v[i - back / 2];
    if (v[i - back] - v[i] >= min_drop_v && mid < v[i - back] && v[i] < mid && v[i] < v[i - 1]) return i;
  }
  return d.size();
}

void print(const char* what, const AnchoredRun& r) {
  std::cout << std::fixed << std::setprecision(2) << what << ": MAE " << r.score.mae_meas << " / " << r.score.mae_true
            << " nm (measured / truth), max " << r.score.max_meas << " / " << r.score.max_true << " nm; "
            << r.start.describe() << " [" << r.seconds << " s]\n";
}

// The hold-trim stage's model (fitted on seed 101, config/models/mm3e_foreign_c.yaml) on seed 202's recording.
io::Dataset foreign_recording(std::uint64_t seed, double duration_s) {
  const sim::StageConfig stage = sim::load_stage(kSrc + "/config/stages/mm3e_foreign_hold_stage.yaml");
  return sim::simulate_stage(stage, seed, duration_s);
}

// The mid-motion recording of tests (a) and the compensator's, simulated once.
const io::Dataset& seed202() {
  static const io::Dataset d = foreign_recording(202, 3600.0);
  return d;
}

}  // namespace

// (a) Mid-motion on a descending branch after 20 min of history: the estimate chooses a history that arrives from
// above and ends up clearly closer than the offset-only anchor, against measurement and truth.
TEST(StartState, MidMotionOnADescendingBranchBeatsOffsetOnly) {
  const models::ModelPtr m = models::load_model(kSrc + "/config/models/mm3e_foreign_c.yaml");
  const io::Dataset& all = seed202();
  const std::size_t cut = descending_row(all, 1200.0, 3.0, 5.0);
  ASSERT_LT(cut + 11 * 600, all.size());
  const io::Dataset rec = all.slice(cut, all.size());
  const AnchoredRun plain = run_anchored(*m, rec, 30.0, false);
  const AnchoredRun est = run_anchored(*m, rec, 30.0, true);
  std::cout << "cut at " << all.time_s[cut] << " s, " << all.axis("c").voltage_v[cut] << " V\n";
  {  // the bound: the model that saw the whole history, its offset fixed on the same window
    models::ModelPtr c = m->clone();
    std::vector<double> p = models::stream_model(*c, all, "c").prediction;
    p.erase(p.begin(), p.begin() + static_cast<long>(cut));
    const models::WindowFit f = models::window_offset(rec.axis("c").position_nm.data(), p.data(), plain.start.window_rows);
    for (double& x : p) x += f.offset_nm;
    const Score full = score_after(p, rec, plain.start.window_rows);
    std::cout << "whole history: MAE " << full.mae_meas << " / " << full.mae_true << " nm, max " << full.max_meas << " / "
              << full.max_true << " nm, window RMS " << f.rms_nm << " nm\n";
  }
  print("offset only", plain);
  print("start estimate", est);
  EXPECT_EQ(plain.start.candidates, 1u);
  EXPECT_GT(est.start.candidates, 10u);
  EXPECT_LE(est.start.rms_nm, est.start.rms_rest_nm);
  EXPECT_NE(est.start.candidate.find("down"), std::string::npos) << est.start.candidate;
  // The estimate must cut the offset-only error to under 0.4 × against the truth and 0.5 × against the
  // measurement (both printed above), and its worst error too.
  EXPECT_LT(est.score.mae_true, 0.4 * plain.score.mae_true);
  EXPECT_LT(est.score.mae_meas, 0.5 * plain.score.mae_meas);
  EXPECT_LT(est.score.max_true, plain.score.max_true);
  EXPECT_LT(est.seconds, 1.0);
}

// (b) A recording that starts at rest (the simulator's own start): the estimate is no worse than offset-only.
TEST(StartState, AtRestNoWorseThanOffsetOnly) {
  const models::ModelPtr m = models::load_model(kSrc + "/config/models/mm3e_foreign_c.yaml");
  const io::Dataset rec = foreign_recording(303, 1800.0);
  const AnchoredRun plain = run_anchored(*m, rec, 30.0, false);
  const AnchoredRun est = run_anchored(*m, rec, 30.0, true);
  print("offset only", plain);
  print("start estimate", est);
  // Not asserted: the window RMS. The learned state prior (training-like operation) pulls the slow states away from
  // the reset equilibrium this recording starts in, so the window fits a little worse than rest (20.9 vs 20.2 nm,
  // weighted); what counts is after the window.
  EXPECT_LE(est.score.mae_true, 1.05 * plain.score.mae_true + 0.5);
  EXPECT_LE(est.score.mae_meas, 1.05 * plain.score.mae_meas + 0.5);
}

// (b2) One estimate, one offset, in either prediction mode: the one-step stream of a model that reads no position is
// the free run (`piezo eval --anchor-s` reports it as such), so it keeps the estimate's offset, not the plain window
// mean, which the rows the estimate weights little pull away (the case: the low-voltage PI stage's 12-play fit on
// seed 21, run on seed 22 from its start with a 2-s window; docs/models.md, "Start-up state estimate").
TEST(StartState, OneStepAndFreeRunShareTheEstimatesOffset) {
  const sim::StageConfig stage = sim::load_stage(kSrc + "/config/stages/lowvolt_pi.yaml");
  const io::Dataset all = sim::simulate_stage(stage, 21, 0.0);
  const std::size_t n_train = all.size() * 4 / 5;
  const io::Dataset train = all.slice(0, n_train), val = all.slice(n_train, all.size());
  training::FitRequest req;
  req.train = &train;
  req.validation = &val;
  req.options = YAML::Load("{n_play: 12, input_map: 'off'}");
  const models::ModelPtr m = training::fit_model("pi", req);
  ASSERT_FALSE(m->uses_position_history());
  const io::Dataset rec = sim::simulate_stage(stage, 22, 20.0);
  models::StreamOptions so;
  so.anchor_s = 2.0;
  models::ModelPtr a = m->clone(), b = m->clone();
  const models::StreamResult free = models::stream_model(*a, rec, "c", so);
  so.mode = models::PredictionMode::kOneStep;
  const models::StreamResult one = models::stream_model(*b, rec, "c", so);
  ASSERT_GT(free.start.candidates, 10u);
  ASSERT_EQ(free.start.window_weight.size(), free.first_scored);
  EXPECT_EQ(one.anchor_offset_nm, free.anchor_offset_nm);
  for (std::size_t i = 0; i < rec.size(); i += 97) ASSERT_EQ(one.prediction[i], free.prediction[i]) << "row " << i;
  // The plain mean would differ here by far more than the noise (the case this test keeps fixed).
  const models::WindowFit plain = models::window_offset(rec.axis("c").position_nm.data(),
                                                        [&] {
                                                          std::vector<double> p = free.prediction;
                                                          for (double& x : p) x -= free.anchor_offset_nm;
                                                          return p;
                                                        }().data(),
                                                        free.first_scored);
  std::cout << "estimate's offset " << free.anchor_offset_nm << " nm, plain window mean " << plain.offset_nm << " nm\n";
  EXPECT_GT(std::abs(plain.offset_nm - free.anchor_offset_nm), 200.0);
  EXPECT_LT(score_after(one.prediction, rec, one.first_scored).mae_true, 300.0);
}

// (d) The creep modes' states are fitted on the window (Model::linear_state_count), not only chosen among the
// synthetic histories: a stage that rested 2000 s at 12 V (a voltage no candidate rests at) and then moved for
// 5 min before the recording starts. The truth is the model itself (σ 5 nm readings), so only the state is unknown;
// the stage matrix runs the fit on physics the models were not built from.
models::PiCreepModel creep_truth() {
  models::CreepParams cp;
  cp.kind = models::CreepKind::kLti;
  cp.taus_s = {3.0, 60.0, 900.0};
  cp.gains_nm_per_v = {1.0, 1.5, 2.5};
  return models::PiCreepModel({0, 8, 16, 32}, {8, 2, 1, 0.5}, 0, cp, 11.0);
}

// The creep stage's motion about 12 V, at time t_s.
double creep_motion_v(double t_s) {
  return 12.0 + 50.0 * std::sin(2 * M_PI * t_s / 97.0) * std::sin(2 * M_PI * t_s / 431.0);
}

// MAE against the truth after the window of `e`, `m` run as stream_model runs it (prepare_start, then the offset).
double mae_vs_truth_after(models::PiCreepModel m, const io::Dataset& rec, const models::StartEstimate& e) {
  models::prepare_start(m, rec, "c", e.history);
  double sum = 0;
  std::size_t n = 0;
  for (std::size_t i = 0; i < rec.size(); ++i) {
    const models::ModelInput in{rec.axis("c").voltage_v[i], nullptr};
    const double y = m.predict(in) + e.offset_nm;
    m.commit(in, y);
    if (i >= e.window_rows) sum += std::abs(y - rec.axis("c").true_position_nm[i]), ++n;
  }
  return sum / static_cast<double>(n);
}

// `m`'s start estimate on `rec` with options `o`, and with `option` switched off; each one's MAE against the truth
// after its window, printed under `what`.
struct OptionEffect {
  models::StartEstimate with, without;
  double with_nm, without_nm;
};
OptionEffect with_and_without(const models::PiCreepModel& m, const io::Dataset& rec, models::StartOptions o,
                              bool models::StartOptions::*option, const char* what) {
  OptionEffect r;
  o.*option = true;
  r.with = models::estimate_start(m, rec, "c", o);
  o.*option = false;
  r.without = models::estimate_start(m, rec, "c", o);
  r.with_nm = mae_vs_truth_after(m, rec, r.with);
  r.without_nm = mae_vs_truth_after(m, rec, r.without);
  std::printf("with %s: %s\nwithout: %s\nMAE vs truth after the window: %.2f nm with, %.2f nm without\n", what,
              r.with.describe().c_str(), r.without.describe().c_str(), r.with_nm, r.without_nm);
  return r;
}

// A recording of `truth` (in its state as given) driven by voltage(i) for pre + n samples at 11 Hz: the first pre
// unseen (its history), the rest recorded from t = 0 s with the true position and readings of σ 5 nm (xorshift:
// deterministic).
io::Dataset record_after(models::PiCreepModel truth, std::size_t pre, std::size_t n,
                         const std::function<double(std::size_t)>& voltage) {
  io::Dataset d;
  auto& a = d.add_axis("c");
  std::uint64_t x = 88172645463325252ull;
  for (std::size_t i = 0; i < pre + n; ++i) {
    const double v = voltage(i);
    const double y = truth.predict({v, nullptr});
    truth.commit({v, nullptr}, y);
    if (i < pre) continue;
    x ^= x << 13, x ^= x >> 7, x ^= x << 17;
    const double u1 = (static_cast<double>(x >> 11) + 0.5) / 9007199254740992.0;
    x ^= x << 13, x ^= x >> 7, x ^= x << 17;
    const double u2 = (static_cast<double>(x >> 11) + 0.5) / 9007199254740992.0;
    d.time_s.push_back(static_cast<double>(i - pre) / 11.0);
    a.voltage_v.push_back(v);
    a.true_position_nm.push_back(y);
    a.position_nm.push_back(y + 5.0 * std::sqrt(-2 * std::log(u1)) * std::cos(2 * M_PI * u2));
  }
  return d;
}

io::Dataset creep_recording() {
  models::PiCreepModel truth = creep_truth();
  truth.reset(12.0, 0.0);
  for (int i = 0; i < 22000; ++i) truth.commit({12.0, nullptr}, 0.0);  // 2000 s at 12 V
  // 5 min unseen, then 10 min recorded
  return record_after(truth, 3300, 6600, [](std::size_t i) { return creep_motion_v(static_cast<double>(i) / 11.0); });
}

TEST(StartState, CreepStatesAreFittedOnTheWindow) {
  const models::PiCreepModel m = creep_truth();
  EXPECT_EQ(m.linear_state_count(), 3u);
  {  // a shift moves the next prediction by itself, then decays with the mode
    models::PiCreepModel c = m;
    c.reset(5.0, 0.0);
    const double y0 = c.predict({5.0, nullptr}), s0 = c.linear_state_nm(1);
    c.shift_linear_state(1, 7.0);
    EXPECT_NEAR(c.predict({5.0, nullptr}) - y0, 7.0, 1e-9);
    EXPECT_NEAR(c.linear_state_nm(1) - s0, 7.0, 1e-9);
  }
  const io::Dataset rec = creep_recording();
  models::StartOptions o;
  o.window_s = 30.0;
  const OptionEffect e = with_and_without(m, rec, o, &models::StartOptions::fit_linear_states, "the creep states");
  EXPECT_EQ(e.with.linear_states, 3u);
  EXPECT_EQ(e.with.history.linear_shift_nm.size(), 3u);
  EXPECT_EQ(e.without.linear_states, 0u);
  EXPECT_TRUE(e.without.history.linear_shift_nm.empty());
  EXPECT_LT(e.with_nm, 0.7 * e.without_nm);
  EXPECT_TRUE(std::isfinite(e.with.offset_sigma_nm) && e.with.offset_sigma_nm > 0);
  // A fitted model knows its training data's voltage range: the synthetic histories stay in it (above, without
  // it, they span the window's voltage span on both sides of the first voltage: "rested at 85.69 V").
  models::PiCreepModel ranged = m;
  ranged.meta.train_voltage_min_v = -20.0;
  ranged.meta.train_voltage_max_v = 62.0;
  o.fit_linear_states = false;
  const models::StartEstimate r = models::estimate_start(ranged, rec, "c", o);
  ASSERT_FALSE(r.history.rest) << r.describe();
  for (double v : {r.history.reset_v, r.history.turn_v}) {
    EXPECT_GE(v, -20.0) << r.describe();
    EXPECT_LE(v, 62.0) << r.describe();
  }
}

// The hysteresis memory a real history leaves is nested: turning points of shrinking amplitude (the wiping-out
// property), which a single turning point cannot leave. A PI truth (the model itself, σ 5 nm readings) whose wide
// plays weigh most, and whose unseen history swung 100 → 20 → 68 → 39.2 → 56.5 → 46.1 → 50 V (each swing 0.6 of the
// last: not a ratio the candidates try);
// the recording's first minute (the window) wanders ±3 V about 50 V, then the voltage sweeps down to 0 V and up to
// 100 V over 10 min, through the memory the window could not see. With the decaying staircases
// (StartOptions::staircases) the estimate reaches that memory; with single turning points it cannot, and the
// error shows once the sweep reaches the plays the window left untouched.
models::PiCreepModel nested_truth() {
  return models::PiCreepModel({0, 5, 10, 15, 20, 25, 30, 35, 40, 45}, {2, 1, 1, 1, 1.5, 2, 2.5, 3, 3.5, 4}, 0,
                              models::CreepParams{}, 11.0);
}

io::Dataset nested_memory_recording() {
  models::PiCreepModel truth = nested_truth();
  std::vector<double> v;
  for (int j = 1; j <= 550; ++j) v.push_back(100.0 * j / 550.0);  // rested at 0 V, up to 100 V
  double from = 100.0;
  for (double to : {20.0, 68.0, 39.2, 56.48, 46.11, 50.0}) {  // 2 V/s ramps
    const int n = static_cast<int>(std::ceil(std::abs(to - from) / 2.0 * 11.0));
    for (int j = 1; j <= n; ++j) v.push_back(from + (to - from) * j / n);
    from = to;
  }
  const std::size_t pre = v.size();
  for (int i = 0; i < 660; ++i) v.push_back(50.0 + 3.0 * std::sin(2 * M_PI * i / 11.0 / 17.0));  // the window
  for (int i = 0; i < 3300; ++i) v.push_back(50.0 - 50.0 * std::sin(M_PI * i / 3300.0));          // down to 0 V
  for (int i = 0; i < 3300; ++i) v.push_back(50.0 * std::sin(M_PI * i / 3300.0 - M_PI / 2) + 50.0);  // up to 100 V
  truth.reset(0.0, 0.0);
  return record_after(truth, pre, v.size() - pre, [&v](std::size_t i) { return v[i]; });
}

TEST(StartState, ANestedMemoryIsReachedByADecayingStaircase) {
  models::PiCreepModel m = nested_truth();
  m.meta.train_voltage_min_v = 0.0;
  m.meta.train_voltage_max_v = 100.0;
  const io::Dataset rec = nested_memory_recording();
  models::StartOptions o;
  o.window_s = 60.0;
  const OptionEffect e = with_and_without(m, rec, o, &models::StartOptions::staircases, "the staircases");
  EXPECT_GT(e.with.candidates, e.without.candidates);
  EXPECT_GT(e.with.history.shrink, 0.0) << e.with.describe();
  EXPECT_NE(e.with.describe().find("in swings around 50 V"), std::string::npos) << e.with.describe();
  EXPECT_LT(e.with_nm, 0.5 * e.without_nm);
}

// A slow creep state sits where operation keeps it — near its gain × the mean voltage — which a long rest at an end
// of the range or at the first voltage does not reproduce. The creep stage below (modes 3, 60 and 900 s) after 3 h of
// motion about 50 V in a 0–100 V range, its recording continuing that motion; the estimate without the learned prior
// and without the state fit, so that only the candidate histories place the 900-s mode. With the rest at the
// range's middle (StartOptions::rest_at_middle) one of them puts it there.
TEST(StartState, ARestAtTheRangesMiddlePlacesASlowState) {
  models::PiCreepModel m = creep_truth();
  m.meta.train_voltage_min_v = 0.0;
  m.meta.train_voltage_max_v = 100.0;
  models::PiCreepModel truth = m;
  auto motion = [](double t) { return 50.0 + 40.0 * std::sin(2 * M_PI * t / 97.0) * std::sin(2 * M_PI * t / 431.0); };
  truth.reset(motion(0.0), 0.0);
  // 3 h unseen, then 10 min recorded
  const io::Dataset rec =
      record_after(truth, 118800, 6600, [&motion](std::size_t i) { return motion(static_cast<double>(i) / 11.0); });
  models::StartOptions o;
  o.window_s = 30.0;
  o.fit_linear_states = false;
  const OptionEffect e = with_and_without(m, rec, o, &models::StartOptions::rest_at_middle, "the middle rest");
  EXPECT_DOUBLE_EQ(e.with.history.reset_v, 50.0) << e.with.describe();
  EXPECT_GT(e.with.candidates, e.without.candidates);
  EXPECT_LT(e.with_nm, 0.5 * e.without_nm);
}

// The estimate says how much of the voltage range its window swept: the hysteresis memory of wider swings is not in
// the window (docs/models.md, "The stage matrix": MM3E 30-s windows 2.7x the continuation, 300-s ones 1.07x), and
// below half the range the line advises a longer window. Without a training range the data's span is the range.
TEST(StartState, TheReportSaysHowMuchOfTheRangeTheWindowSwept) {
  const io::Dataset rec = creep_recording();
  models::PiCreepModel m = creep_truth();
  m.meta.train_voltage_min_v = -40.0;
  m.meta.train_voltage_max_v = 64.0;
  models::StartOptions o;
  const auto& v = rec.axis("c").voltage_v;
  for (double window_s : {30.0, 300.0}) {
    o.window_s = window_s;
    const models::StartEstimate e = models::estimate_start(m, rec, "c", o);
    const auto [lo, hi] = std::minmax_element(v.begin(), v.begin() + static_cast<long>(e.window_rows));
    std::printf("%.0f-s window: %s\n", window_s, e.describe().c_str());
    EXPECT_DOUBLE_EQ(e.window_swept_v, *hi - *lo);
    EXPECT_DOUBLE_EQ(e.range_v, 104.0);
    const bool advised = e.describe().find("longer window") != std::string::npos;
    EXPECT_EQ(advised, e.swept_fraction() < models::kWindowSweepAdvised) << e.describe();
    if (window_s == 30.0) EXPECT_LT(e.swept_fraction(), models::kWindowSweepAdvised);
    else EXPECT_GT(e.swept_fraction(), models::kWindowSweepAdvised);
  }
  const models::StartEstimate data_range = models::estimate_start(creep_truth(), rec, "c", o);
  const auto [dlo, dhi] = std::minmax_element(v.begin(), v.end());
  EXPECT_DOUBLE_EQ(data_range.range_v, *dhi - *dlo);
}

// The learned prior (ModelMeta::state_prior, what training::fit_model stores): where an hour of the same kind of
// operation kept each creep state. A fast mode follows the voltage (its line's slope is its gain), a slow one sits
// near its mean whatever the voltage (the warm-up pass: not where a reset at the first voltage put it); with it the
// slow states start where such operation leaves them instead of where the candidates' extreme histories put them.
TEST(StartState, LearnedStatePriorPlacesTheSlowStates) {
  const models::PiCreepModel truth = creep_truth();
  io::Dataset train;
  {
    models::PiCreepModel t = truth;
    t.reset(12.0, 0.0);
    auto& a = train.add_axis("c");
    for (int i = 0; i < 39600; ++i) {  // 1 h of the recording's kind of motion, another stretch of it
      const double v = creep_motion_v((i + 20000) / 11.0);
      train.time_s.push_back(i / 11.0);
      a.voltage_v.push_back(v);
      a.position_nm.push_back(t.predict({v, nullptr}));
      t.commit({v, nullptr}, a.position_nm.back());
    }
  }
  const std::vector<models::LinearStatePrior> prior = models::learn_state_prior(truth, train, "c");
  ASSERT_EQ(prior.size(), 3u);
  for (const auto& p : prior) std::printf("state prior: %.3f nm + %.4f nm/V, sigma %.3f nm\n", p.intercept_nm, p.slope_nm_per_v, p.sigma_nm);
  EXPECT_NEAR(prior[0].slope_nm_per_v, 1.0, 0.1);   // 3 s: follows the voltage with its gain
  EXPECT_LT(std::abs(prior[2].slope_nm_per_v), 0.05);  // 900 s: barely sees the present voltage, sits near its
  EXPECT_NEAR(prior[2].intercept_nm, 2.5 * 12.0, 3.0);    // gain × the mean voltage (12 V)
  EXPECT_LT(prior[2].sigma_nm, 5.0);
  const io::Dataset rec = creep_recording();
  models::StartOptions o;
  o.window_s = 30.0;
  models::PiCreepModel learned = truth;
  learned.meta.state_prior = prior;
  auto mae_after = [&](const models::PiCreepModel& m) {
    const models::StartEstimate e = models::estimate_start(m, rec, "c", o);
    std::printf("%s\n", e.describe().c_str());
    return mae_vs_truth_after(m, rec, e);
  };
  const double with = mae_after(learned), without = mae_after(truth);
  std::printf("MAE vs truth after the window: %.2f nm with the learned prior, %.2f nm with the candidates' range\n", with, without);
  EXPECT_LT(with, 0.7 * without);
  // 40 s of training (the lowvolt stages' length) cannot settle the 60-s and 900-s modes: two warm-ups from either
  // end of the range leave them apart, and that gap widens their prior instead of pinning them where the reset put them.
  models::PiCreepModel brief = truth;
  brief.meta.state_prior = models::learn_state_prior(truth, train.slice(0, 440), "c");
  ASSERT_EQ(brief.meta.state_prior.size(), 3u);
  for (const auto& p : brief.meta.state_prior) std::printf("40-s prior: %.3f nm + %.4f nm/V, sigma %.3f nm\n", p.intercept_nm, p.slope_nm_per_v, p.sigma_nm);
  EXPECT_GT(brief.meta.state_prior[2].sigma_nm, 10.0 * prior[2].sigma_nm);
  const double short_training = mae_after(brief);
  std::printf("MAE vs truth after the window with the prior of 40 s of training: %.2f nm\n", short_training);
  EXPECT_LT(short_training, 1.2 * without);
  EXPECT_TRUE(models::learn_state_prior(models::PiCreepModel({0, 8}, {8, 2}, 0, {}, 11.0), train, "c").empty());
  io::Dataset holed = train;  // a non-finite voltage (possible in a data set built in code) leaves no prior
  holed.axis("c").voltage_v[20000] = NAN;
  EXPECT_TRUE(models::learn_state_prior(truth, holed, "c").empty());
  // A prior without scatter puts its states on its line at the first voltage (the window cannot move them).
  models::PiCreepModel exact = truth;
  exact.meta.state_prior = {{10.0, 0.0, 0.0}, {20.0, 0.0, 0.0}, {30.0, 0.5, 0.0}};
  const models::StartEstimate e = models::estimate_start(exact, rec, "c", o);
  models::prepare_start(exact, rec, "c", e.history);
  const double v0 = rec.axis("c").voltage_v[0];
  EXPECT_NEAR(exact.linear_state_nm(0), 10.0, 1e-3);
  EXPECT_NEAR(exact.linear_state_nm(1), 20.0, 1e-3);
  EXPECT_NEAR(exact.linear_state_nm(2), 30.0 + 0.5 * v0, 1e-3);
}

// (c) Bad input: one clear error naming what was wrong.
TEST(StartState, BadInputNamesTheProblem) {
  const models::ModelPtr m = models::load_model(kSrc + "/config/models/mm3e_foreign_c.yaml");
  io::Dataset d = foreign_recording(404, 60.0);
  models::StartOptions o;
  auto message = [&](const io::Dataset& data, double window_s) {
    o.window_s = window_s;
    try {
      models::estimate_start(*m, data, "c", o);
    } catch (const std::exception& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(message(d, 0.0).find("start window must be a finite time > 0 s"), std::string::npos) << message(d, 0.0);
  EXPECT_NE(message(d, -1.0).find("> 0 s"), std::string::npos);
  EXPECT_NE(message(d, std::nan("")).find("> 0 s"), std::string::npos);
  EXPECT_NE(message(d, 120.0).find("covers the whole data set"), std::string::npos) << message(d, 120.0);
  d.axis("c").position_nm[5] = std::nan("");
  EXPECT_NE(message(d, 10.0).find("non-finite measured position at row 6"), std::string::npos) << message(d, 10.0);
  d.axis("c").position_nm[5] = 0.0;
  d.axis("c").voltage_v[3] = std::nan("");
  EXPECT_NE(message(d, 10.0).find("non-finite voltage at row 4"), std::string::npos) << message(d, 10.0);
  // The same check guards the anchor of stream_model.
  models::StreamOptions so;
  so.anchor_s = 120.0;
  models::ModelPtr c = m->clone();
  EXPECT_THROW(models::stream_model(*c, foreign_recording(404, 60.0), "c", so), io::DataError);
}

// The estimator starts from the estimate's offset and σ (ONE start, not a separate constant).
TEST(StartState, ErrorFilterStartsFromTheEstimate) {
  estimation::NoiseModel nm;
  nm.reading_sigma_nm = 20.0;
  nm.initial_sigma_nm = 50.0;
  estimation::ErrorFilter f(nm, 1.0 / 11.0);
  EXPECT_NEAR(f.sigma_nm(), 50.0, 1e-9);
  f.reset(12.0, 3.0);
  EXPECT_NEAR(f.slow_error_nm(), 12.0, 1e-12);
  EXPECT_NEAR(f.sigma_nm(), 3.0, 1e-9);
  f.reset(0.0, std::nan(""));
  EXPECT_NEAR(f.sigma_nm(), 50.0, 1e-9);
  EXPECT_THROW(f.reset(std::nan(""), 1.0), std::invalid_argument);
  EXPECT_THROW(f.reset(0.0, -1.0), std::invalid_argument);
}

// The compensator (predictor, `piezo track`) runs the same estimate over its first seconds and starts the
// estimator from it: on the mid-motion recording its fused estimate is closer to the truth after the window.
TEST(StartState, TrackRecordingUsesTheEstimate) {
  const models::ModelPtr m = models::load_model(kSrc + "/config/models/mm3e_foreign_c.yaml");
  const io::Dataset& all = seed202();
  const std::size_t cut = descending_row(all, 1200.0, 3.0, 5.0);
  const io::Dataset rec = all.slice(cut, all.size());
  compensation::TrackOptions o;
  const compensation::TrackResult cold = compensation::track_recording(m->clone(), rec, "c", o);
  o.start_estimate_s = 30.0;
  const compensation::TrackResult warm = compensation::track_recording(m->clone(), rec, "c", o);
  EXPECT_NE(warm.start_estimate.find("start estimate over"), std::string::npos) << warm.start_estimate;
  std::cout << warm.start_estimate << "\n";
  auto mae = [&](const std::vector<double>& x, std::size_t from, std::size_t to) {
    double s = 0;
    for (std::size_t i = from; i < to; ++i) s += std::abs(x[i] - rec.axis("c").true_position_nm[i]);
    return s / static_cast<double>(to - from);
  };
  const std::size_t from = 11 * 31, to = std::min(rec.size(), from + 11 * 300);
  std::cout << std::fixed << std::setprecision(2) << "5 min after the window, MAE vs truth: model "
            << mae(cold.model_nm, from, to) << " → " << mae(warm.model_nm, from, to) << " nm, fused "
            << mae(cold.fused_nm, from, to) << " → " << mae(warm.fused_nm, from, to) << " nm\n";
  EXPECT_NE(warm.start_estimate.find("down"), std::string::npos);
  // The model alone (its offset is the filter's) must improve, and the fused estimate by at least 20 %.
  EXPECT_LT(mae(warm.model_nm, from, to), mae(cold.model_nm, from, to));
  EXPECT_LT(mae(warm.fused_nm, from, to), 0.8 * mae(cold.fused_nm, from, to));
}

// The start estimate against the offset-only anchor (docs/models.md, "Start-up state estimate"), slow: a model fitted on seed A of a stage, run on a
// recording of seed B sliced to start mid-motion on a descending branch; offset-only anchor against the estimate,
// scored after the window against measurement and truth.
namespace {
models::ModelPtr fit_seed11(const sim::StageConfig& stage, const std::string& kind, double fit_s) {
  const io::Dataset a = sim::simulate_stage(stage, 11, fit_s);
  const std::size_t n_train = a.size() * 4 / 5;
  const io::Dataset train = a.slice(0, n_train), val = a.slice(n_train, a.size());
  training::FitRequest req;
  req.train = &train;
  req.validation = &val;
  return training::fit_model(kind, req);
}

// kind "file:PATH": that model file instead of a fit on seed 11.
void measure_stage(const std::string& name, const std::string& kind, double fit_s, double cut_after_s,
                   double test_s, double window_s, double fall_s, std::uint64_t seed = 12) {
  const sim::StageConfig stage = sim::load_stage(kSrc + "/config/stages/" + name + ".yaml");
  const models::ModelPtr m = kind.rfind("file:", 0) == 0 ? models::load_model(kSrc + "/" + kind.substr(5))
                                                          : fit_seed11(stage, kind, fit_s);
  const io::Dataset b = sim::simulate_stage(stage, seed, cut_after_s + test_s);
  const double drop_v = 0.03 * (stage.simulator.axes[2].voltage_max_v - stage.simulator.axes[2].voltage_min_v);
  const std::size_t cut = descending_row(b, cut_after_s, fall_s, drop_v);
  ASSERT_LT(cut + 10, b.size());
  const io::Dataset rec = b.slice(cut, b.size());
  {  // the bound: the model that ran over seed B from its start, its offset fixed on the same window
    models::ModelPtr c = m->clone();
    std::vector<double> p = models::stream_model(*c, b, "c").prediction;
    p.erase(p.begin(), p.begin() + static_cast<long>(cut));
    const std::size_t k = models::start_window_rows(rec, "c", window_s);
    const double off = models::window_offset(rec.axis("c").position_nm.data(), p.data(), k).offset_nm;
    for (double& x : p) x += off;
    const Score s = score_after(p, rec, k);
    std::cout << std::fixed << std::setprecision(1) << "| " << name << " | " << kind << " | " << window_s
              << " s | whole history (bound) | " << s.mae_meas << " | " << s.max_meas << " | " << s.mae_true << " | "
              << s.max_true << " | cut at " << b.time_s[cut] << " s | |\n";
  }
  for (bool history : {false, true}) {
    const AnchoredRun r = run_anchored(*m, rec, window_s, history);
    std::cout << std::fixed << std::setprecision(1) << "| " << name << " | " << kind << " | " << window_s << " s | "
              << (history ? "start estimate" : "offset only") << " | " << r.score.mae_meas << " | " << r.score.max_meas
              << " | " << r.score.mae_true << " | " << r.score.max_true << " | " << r.start.candidate << " | "
              << std::setprecision(3) << r.seconds << " s |\n";
  }
}
}  // namespace

TEST(StartStateTable, FittedOnOneSeedStartedMidMotionOnAnother) {
  std::cout << "| stage | model | window | start | MAE meas [nm] | max meas [nm] | MAE truth [nm] | max truth [nm] | "
               "chosen | time |\n|---|---|---|---|---|---|---|---|---|---|\n";
  for (const char* kind : {"preisach_creep_prony", "pi_creep_prony"}) {
    measure_stage("lowvolt_preisach_creep", kind, 50.0, 15.0, 30.0, 3.0, 0.5);
    measure_stage("mm3e_preisach_creep", kind, 7200.0, 1800.0, 3600.0, 30.0, 3.0);
  }
  // The hold-trim stage's shipped model (fitted on seed 101) on other seeds: histories of 20–30 min, then a hold.
  for (std::uint64_t seed : {202, 505, 606})
    measure_stage("mm3e_foreign_hold_stage", "file:config/models/mm3e_foreign_c.yaml", 0, 1200.0, 2400.0, 30.0, 3.0, seed);
}

// A recurrent model's hidden state is reached by a synthetic pre-history, not by rest: an LSTM on the fixed
// voltage_history features (its hidden state carries the memory those 10 columns lack, so rest is far off) on the
// stage matrix's stack150_pi separate recording (seed 22, cut at 2 s, window 1 s); the window played backwards (StartOptions::replay_window) is one more candidate, which may not
// make the start worse (figures in docs/models.md, "Start-up state estimate").
TEST(StartStateTable, ALstmStartsFromASyntheticHistoryNotFromRest) {
  const sim::StageConfig stage = sim::load_stage(kSrc + "/config/stages/stack150_pi.yaml");
  const io::Dataset all = sim::simulate_stage(stage, 21, 0.0);
  const io::Dataset train = all.slice(0, all.size() * 4 / 5), val = all.slice(all.size() * 4 / 5, all.size());
  training::FitRequest req;
  req.train = &train;
  req.validation = &val;
  req.options = YAML::Load("{steps: 800, patience: 0, features: voltage_history}");
  req.seed = 3;
  const models::ModelPtr m = training::fit_model("lstm", req);
  const io::Dataset whole = sim::simulate_stage(stage, 22, 8.0);
  std::size_t cut = static_cast<std::size_t>(std::lround(2.0 * whole.sample_rate_hz()));
  const auto& v = whole.axis("c").voltage_v;
  while (cut + 1 < v.size() && (v[cut] == v[cut - 1] || v[cut + 1] == v[cut])) ++cut;
  const io::Dataset rec = whole.slice(cut, whole.size());
  auto mae_after = [&](bool replay, bool history = true) {
    models::StartOptions o;
    o.window_s = 1.0;
    o.replay_window = replay;
    o.search_history = history;
    const models::StartEstimate e = models::estimate_start(*m, rec, "c", o);
    models::ModelPtr c = m->clone();
    models::prepare_start(*c, rec, "c", e.history);
    models::StreamOptions so;
    so.reset = false;
    so.keep_diverging = true;
    const std::vector<double> p = models::stream_model(*c, rec, "c", so).prediction;
    double sum = 0;
    for (std::size_t i = e.window_rows; i < rec.size(); ++i) sum += std::abs(p[i] + e.offset_nm - rec.axis("c").position_nm[i]);
    std::printf("%s\n", e.describe().c_str());
    return sum / static_cast<double>(rec.size() - e.window_rows);
  };
  const double with = mae_after(true), without = mae_after(false), rest = mae_after(false, false);
  std::printf("lstm on stack150_pi's separate recording, MAE after the window: %.1f nm with the window played backwards, "
              "%.1f nm without, %.1f nm from rest (offset only)\n", with, without, rest);
  EXPECT_LT(with, 0.25 * rest);
  EXPECT_LE(with, without * 1.05);  // the played-back window is one more candidate: it may not make the start worse
}

// Is the start σ honest? The estimator starts from the estimate's offset and σ (ErrorFilter::reset), so σ should
// cover the model's mean error against the truth over the first 5 min after the window. Three creep kinds fitted on
// each MM3E stage (seed 21, 2 h), each started cold mid-motion on six other recordings (seeds 22–27, cut after
// 15 min, 30-s window): 72 starts. Requirement: at least 90 % within 2σ and 60 % within 1σ (nominal 95 % and 68 %);
// the misses expected are misspecified models (PI-creep kinds on Preisach loops), whose error after the window is
// the model's, which the window fits to the noise and so cannot see. Figures: docs/validation/models.md,
// "Start-up state estimate: is its σ honest?".
TEST(StartStateTable, TheStartSigmaCoversTheErrorAfterTheWindow) {
  int n = 0, in1 = 0, in2 = 0;
  for (const char* st : {"mm3e_pi", "mm3e_pi_creep", "mm3e_preisach", "mm3e_preisach_creep"}) {
    const sim::StageConfig stage = sim::load_stage(kSrc + "/config/stages/" + st + ".yaml");
    const io::Dataset all = sim::simulate_stage(stage, 21, 7200.0);
    const io::Dataset train = all.slice(0, all.size() * 4 / 5), val = all.slice(all.size() * 4 / 5, all.size());
    for (const char* kind : {"pi_creep_lti", "pi_creep_prony", "preisach_creep_prony"}) {
      training::FitRequest req;
      req.train = &train;
      req.validation = &val;
      req.seed = 3;
      const models::ModelPtr m = training::fit_model(kind, req);
      for (std::uint64_t seed = 22; seed < 28; ++seed) {
        const io::Dataset whole = sim::simulate_stage(stage, seed, 1800.0);
        const auto& v = whole.axis("c").voltage_v;
        std::size_t cut = static_cast<std::size_t>(std::lround(900.0 * whole.sample_rate_hz()));
        while (cut + 1 < v.size() && (v[cut] == v[cut - 1] || v[cut + 1] == v[cut])) ++cut;
        const io::Dataset rec = whole.slice(cut, whole.size());
        models::StreamOptions o;
        o.anchor_s = 30.0;
        o.keep_diverging = true;
        models::ModelPtr c = m->clone();
        const models::StreamResult r = models::stream_model(*c, rec, "c", o);
        const auto& truth = rec.axis("c").true_position_nm;
        const std::size_t end = std::min(rec.size(), r.first_scored + static_cast<std::size_t>(300.0 * rec.sample_rate_hz()));
        double bias = 0;
        for (std::size_t i = r.first_scored; i < end; ++i) bias += r.prediction[i] - truth[i];
        bias /= static_cast<double>(end - r.first_scored);
        const double z = bias / r.start.offset_sigma_nm;
        ++n, in1 += std::abs(z) <= 1.0, in2 += std::abs(z) <= 2.0;
        if (std::abs(z) > 2.0) std::printf("%s %s seed %llu: %.1f nm after the window, sigma %.1f nm (%.1f sigma)\n", st, kind,
                                           static_cast<unsigned long long>(seed), bias, r.start.offset_sigma_nm, z);
      }
    }
  }
  std::printf("start sigma: the mean error over 5 min after the window within 1 sigma on %d of %d starts, within 2 sigma on %d\n",
              in1, n, in2);
  EXPECT_GE(in2, 0.9 * n);  // nominal 95 %
  EXPECT_GE(in1, 0.6 * n);  // nominal 68 %
}

// Cost at kHz rates: the window streamed once per candidate (the synthetic histories capped at max_history_samples,
// so the long ages drop out). A 200 Hz preisach_creep_prony on 3 s of the 5 kHz stack150 stage's voltages (mapped
// into the model's 0–4 V; timing only, the per-sample cost does not depend on the rate).
TEST(StartStateTable, CostAtFiveKilohertz) {
  const sim::StageConfig low = sim::load_stage(kSrc + "/config/stages/lowvolt_preisach_creep.yaml");
  const io::Dataset a = sim::simulate_stage(low, 11, 50.0);
  const io::Dataset train = a.slice(0, a.size() * 4 / 5);
  training::FitRequest req;
  req.train = &train;
  const models::ModelPtr m = training::fit_model("preisach_creep_prony", req);
  const sim::StageConfig stack = sim::load_stage(kSrc + "/config/stages/stack150_preisach_creep.yaml");
  io::Dataset d = sim::simulate_stage(stack, 12, 6.0);
  for (double& v : d.axis("c").voltage_v) v = 2.0 + v * 4.0 / 300.0;
  models::StartOptions o;
  o.window_s = 3.0;
  const auto t0 = std::chrono::steady_clock::now();
  const models::StartEstimate e = models::estimate_start(*m, d, "c", o);
  const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::cout << d.sample_rate_hz() << " Hz, " << e.window_rows << " window rows, " << e.candidates << " candidates: "
            << s << " s\n";
  EXPECT_LT(s, 5.0);
}

// The compensator's side: a bad window length is refused by name; a lost reading in the window or a model replaced
// during it leaves the cold start and says why.
TEST(StartState, CompensatorWindowEdgeCases) {
  const models::ModelPtr m = models::load_model(kSrc + "/config/models/mm3e_foreign_c.yaml");
  const compensation::IdealLine line{12.5, 0.0};
  compensation::AxisCompensatorConfig cfg;
  cfg.start_estimate_s = -1.0;
  try {
    compensation::AxisCompensator c(m->clone(), line, cfg);
    ADD_FAILURE() << "a negative start_estimate_s was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("start_estimate_s"), std::string::npos) << e.what();
  }
  cfg.start_estimate_s = 1.0;
  compensation::AxisCompensator lost(m->clone(), line, cfg);
  for (int i = 0; i < 20; ++i) lost.on_sample(0.1 * i, i == 3 ? std::nan("") : 12.5 * 0.1 * i, i != 3);
  EXPECT_EQ(lost.start_estimate(), nullptr);
  EXPECT_NE(lost.start_estimate_status().find("non-finite measured position at row 4"), std::string::npos)
      << lost.start_estimate_status();
  compensation::AxisCompensator swapped(m->clone(), line, cfg);
  for (int i = 0; i < 5; ++i) swapped.on_sample(0.1 * i, 12.5 * 0.1 * i, true);
  swapped.replace_model(m->clone(), line);
  for (int i = 5; i < 20; ++i) swapped.on_sample(0.1 * i, 12.5 * 0.1 * i, true);
  EXPECT_NE(swapped.start_estimate_status().find("replaced"), std::string::npos) << swapped.start_estimate_status();
  compensation::AxisCompensator fine(m->clone(), line, cfg);
  for (int i = 0; i < 20; ++i) fine.on_sample(0.1 * i, 12.5 * 0.1 * i, true);
  ASSERT_NE(fine.start_estimate(), nullptr) << fine.start_estimate_status();
  EXPECT_EQ(fine.start_estimate()->window_rows, 11u);
}
