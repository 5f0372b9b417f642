// The demo's scenarios and scoring (compensation/demo_scenario.h), driven by a lock-step fake device.
#include <gtest/gtest.h>
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <algorithm>
#include <functional>
#include <sstream>

#include "piezo_compensation/compensation/demo_scenario.h"

namespace {

using piezo::compensation::CreepDemoOptions;
using piezo::compensation::DemoRun;
using piezo::compensation::IdealLine;

const IdealLine kLine{10.0, 5.0};  // 10 nm/V, 5 nm at 0 V

// A device that applies each intent at the next sample. `true_nm(mode, phase index in hold, v)` is its physics.
// Reports arrive in a rotating order (the three topics are not ordered). Lock-step: the predictor's output of the
// sample comes before or after the reports, also rotating. Returns the JSON metrics.
// `estimate(mode, hold_k)`: the predictor's fused estimate and trim it reports with the sample (hold_trim).
YAML::Node drive(DemoRun& run, const std::function<double(int mode, int hold_k, double v)>& true_nm,
                 int* mode_switches = nullptr, std::vector<bool>* modes = nullptr,
                 const std::function<DemoRun::Estimate(int mode, int hold_k)>& estimate = nullptr) {
  double v = 0.0;
  int mode = 0, hold_k = 0;
  double last_intent = NAN, intent = 0.0;
  for (std::uint32_t seq = 100; !run.done(); ++seq) {
    const double x = true_nm(mode, hold_k, v), t = seq / 11.0;
    std::optional<DemoRun::Next> n;
    const auto keep = [&](std::optional<DemoRun::Next> r) { if (r) n = r; };
    const auto predicted = [&] {
      keep(run.on_prediction(t, intent, intent, false, estimate ? estimate(mode, hold_k) : DemoRun::Estimate{}));
    };
    if (run.lockstep() && seq % 2) predicted();
    switch (seq % 3) {
      case 0: keep(run.on_truth(seq, x, t)); keep(run.on_encoder(seq, std::round(x / 20) * 20, t)); keep(run.on_voltage(seq, v, t)); break;
      case 1: keep(run.on_voltage(seq, v, t)); keep(run.on_truth(seq, x, t)); keep(run.on_encoder(seq, std::round(x / 20) * 20, t)); break;
      default: keep(run.on_encoder(seq, std::round(x / 20) * 20, t)); keep(run.on_voltage(seq, v, t)); keep(run.on_truth(seq, x, t));
    }
    if (run.lockstep() && !(seq % 2)) {
      EXPECT_FALSE(n) << "lock-step: an intent before the predictor has the sample (seq " << seq << ")";
      predicted();
    }
    if (!n) continue;
    if (n->set_mode) {
      const bool on = run.switches_tracking_trim() ? n->tracking_trim
                      : run.switches_hold_trim()   ? n->hold_trim
                                                   : n->compensated;
      if (run.switches_hold_trim()) {
        EXPECT_TRUE(n->compensated) << "hold_trim: compensation stays on";
      }
      mode = on ? 1 : 0;
      if (mode_switches) ++*mode_switches;
      if (modes) modes->push_back(on);
    }
    hold_k = n->intent_v == last_intent ? hold_k + 1 : 0;
    last_intent = n->intent_v;
    intent = n->intent_v;
    if (!run.lockstep()) run.on_prediction(t, n->intent_v, n->intent_v, false);  // the predictor sends the intent as it is
    v = n->intent_v;
    if (seq > 10'000'000) ADD_FAILURE() << "demo never ends";
  }
  std::ostringstream js;
  run.write_json(js);
  return YAML::Load(js.str());
}

TEST(DemoScenario, SawtoothScoresTheDeviationFromTheIdealLine) {
  DemoRun run("sawtooth", CreepDemoOptions{}, kLine, 11.0);
  int switches = 0;
  std::vector<bool> modes;
  // Uncompensated: 2 % too much gain; compensated: on the line.
  const auto j = drive(run, [](int mode, int, double v) { return kLine.position_nm(v) + (mode ? 0.0 : 0.2 * v); },
                       &switches, &modes);
  EXPECT_EQ(modes, (std::vector<bool>{false, true}));
  EXPECT_NEAR(j["stroke_nm"].as<double>(), 1400.0, 1e-6);           // ±70 V × 10 nm/V
  EXPECT_NEAR(j["uncompensated_max_pct"].as<double>(), 1.0, 1e-3);  // 0.2 × 70 / 1400
  EXPECT_NEAR(j["compensated_max_pct"].as<double>(), 0.0, 1e-9);
  EXPECT_EQ(run.rows().size(), run.steps());
  std::ostringstream csv;
  run.write_csv(csv);
  const std::string text = csv.str();
  EXPECT_EQ(std::count(text.begin(), text.end(), '\n'), static_cast<long>(run.steps()) + 1);
}

TEST(DemoScenario, CreepMeasuresTheDriftOfEachHold) {
  CreepDemoOptions co;
  co.history_s = 300.0;
  co.hold_s = 20.0;
  co.scenarios = {2, 1};
  DemoRun run("creep", co, kLine, 11.0);
  // Uncompensated: the tip creeps 0.5 nm per sample while holding; compensated: it stays.
  const auto j = drive(run, [](int mode, int k, double v) { return kLine.position_nm(v) + (mode ? 0.0 : 0.5 * k); });
  const auto unc = j["uncompensated_drift_nm"], comp = j["compensated_drift_nm"];
  ASSERT_EQ(unc.size(), 2u);
  ASSERT_EQ(comp.size(), 2u);
  for (std::size_t i = 0; i < 2; ++i) {
    // The hold's first scored sample has the hold voltage applied (k = 1), the last k = 220 samples later.
    EXPECT_NEAR(unc[i].as<double>(), 0.5 * (co.hold_s * 11 - 1), 1.0) << i;
    EXPECT_NEAR(comp[i].as<double>(), 0.0, 1e-9) << i;
    EXPECT_EQ(j["hold_start_forced"][i].as<int>(), 0);
  }
  EXPECT_EQ(j["uncompensated_late_samples"].as<int>(), 0);
  EXPECT_EQ(j["creep_scenarios"].size(), 2u);
}

TEST(DemoScenario, LockStepWaitsForThePredictionAndStartsHoldsAtOnce) {
  CreepDemoOptions co;
  co.history_s = 300.0;
  co.hold_s = 20.0;
  co.scenarios = {2, 1};
  DemoRun run("creep", co, kLine, 11.0, true);
  const auto j = drive(run, [](int mode, int k, double v) { return kLine.position_nm(v) + (mode ? 0.0 : 0.5 * k); });
  EXPECT_TRUE(j["lockstep"].as<bool>());
  for (std::size_t i = 0; i < 2; ++i) {
    EXPECT_NEAR(j["uncompensated_drift_nm"][i].as<double>(), 0.5 * (co.hold_s * 11 - 1), 1.0) << i;
    EXPECT_EQ(j["hold_start_delay_samples"][i].as<int>(), 0) << i;
  }
  EXPECT_EQ(j["uncompensated_late_samples"].as<int>(), 0);
  EXPECT_EQ(run.rows().size(), run.steps());

  DemoRun saw("sawtooth", CreepDemoOptions{}, kLine, 11.0, true);
  const auto js = drive(saw, [](int mode, int, double v) { return kLine.position_nm(v) + (mode ? 0.0 : 0.2 * v); });
  EXPECT_NEAR(js["uncompensated_max_pct"].as<double>(), 1.0, 1e-3);
  EXPECT_EQ(js["uncompensated_late_samples"].as<int>(), 0);
  EXPECT_GT(js["uncompensated_saw_samples"].as<int>(), 1000);
}

// Pairing goes through io/sequence_pairer.h: a lost voltage report takes the held value, a lost encoder reading is
// a sample without a measurement, and each keeps the scenario on the device's sample clock.
TEST(DemoScenario, LostReportsKeepOneStepPerSample) {
  DemoRun run("sawtooth", CreepDemoOptions{}, kLine, 11.0);
  double v = 0.0;
  std::size_t given = 0;
  for (std::uint32_t seq = 7; !run.done() && seq < 100000; ++seq) {
    std::optional<DemoRun::Next> n;
    const auto keep = [&](std::optional<DemoRun::Next> r) { if (r) n = r; };
    keep(run.on_truth(seq, kLine.position_nm(v)));
    if (seq % 50 != 0) keep(run.on_voltage(seq, v));   // lost voltage: pairs when the next report shows it lost
    if (seq % 70 != 3) keep(run.on_encoder(seq, std::round(kLine.position_nm(v) / 20) * 20));
    if (n) v = n->intent_v, ++given;
  }
  EXPECT_TRUE(run.done());
  EXPECT_GT(run.pairing().lost_voltages, 0u);
  EXPECT_GT(run.pairing().lost_readings, 0u);
  std::size_t unmeasured = 0;
  for (const auto& r : run.rows()) unmeasured += std::isnan(r.encoder_nm);
  EXPECT_EQ(unmeasured, run.pairing().lost_readings);
  EXPECT_EQ(run.rows().size(), run.steps());
}

// hold_trim: a short history, then the hold, feedforward only and then trimmed; the hold is scored over its last
// score_last_s against the intended position, and the predictor's estimate goes into the CSV.
TEST(DemoScenario, HoldTrimScoresTheEndOfEachHold) {
  CreepDemoOptions co = piezo::compensation::hold_trim_demo_defaults();
  EXPECT_EQ(co.history_s, 120.0);
  EXPECT_EQ(co.hold_s, 1800.0);
  EXPECT_EQ(co.score_last_s, 1680.0);
  co.hold_s = 60.0;        // 660 samples,
  co.score_last_s = 40.0;  // the last 440 scored (hold_k 221 … 660)
  DemoRun run("hold_trim", co, kLine, 11.0, true);
  EXPECT_TRUE(run.switches_hold_trim());
  std::vector<bool> modes;
  // Feedforward only: 8 nm off and creeping 0.01 nm per sample; trimmed: 0.5 nm + a settling 3 nm.
  const auto physics = [](int mode, int k, double v) {
    return kLine.position_nm(v) + (mode ? 0.5 + 3.0 * std::exp(-k / 50.0) : 8.0 + 0.01 * k);
  };
  const auto estimate = [](int mode, int k) {
    DemoRun::Estimate e;
    e.fused_nm = 100.0 + k, e.fused_sigma_nm = 0.75, e.hold_trim_nm = mode ? -0.25 : 0.0;
    e.hold_trim_state = mode == 0 ? "off" : k > 55 ? "active" : "settling";
    return e;
  };
  const auto j = drive(run, physics, nullptr, &modes, estimate);
  EXPECT_EQ(modes, (std::vector<bool>{false, true}));
  EXPECT_EQ(j["scenario"].as<std::string>(), "hold_trim");
  ASSERT_EQ(j["ff_worst_nm"].size(), 1u);
  ASSERT_EQ(j["trimmed_worst_nm"].size(), 1u);
  EXPECT_NEAR(j["hold_trim_ff_worst_nm"].as<double>(), 8.0 + 0.01 * 660, 0.011);
  EXPECT_NEAR(j["hold_trim_ff_mae_nm"].as<double>(), 8.0 + 0.01 * (221 + 660) / 2.0, 0.011);
  EXPECT_NEAR(j["hold_trim_trimmed_worst_nm"].as<double>(), 0.5 + 3.0 * std::exp(-221 / 50.0), 0.002);
  EXPECT_LT(j["hold_trim_trimmed_mae_nm"].as<double>(), 0.51);
  EXPECT_EQ(j["ff_scored_samples"][0].as<int>(), 440);
  EXPECT_EQ(j["trimmed_scored_samples"][0].as<int>(), 440);
  EXPECT_EQ(j["ff_active_samples"][0].as<int>(), 0);
  EXPECT_EQ(j["trimmed_active_samples"][0].as<int>(), 440);
  EXPECT_NEAR(j["intended_nm"][0].as<double>(), kLine.position_nm(j["hold_v"][0].as<double>()), 1e-9);
  EXPECT_EQ(run.rows().size(), run.steps());
  std::ostringstream csv;
  run.write_csv(csv);
  const std::string text = csv.str();
  EXPECT_EQ(text.substr(0, text.find('\n')),
            "mode,segment,phase,time_s,intent_v,applied_v,ideal_nm,true_nm,encoder_nm,fused_nm,fused_sigma_nm,"
            "hold_trim_nm,hold_trim_state");
  EXPECT_NE(text.find(",0.75,-0.25,active\n"), std::string::npos);
  EXPECT_EQ(text.find(",none\n"), std::string::npos) << "every sample has its prediction";

  // The defaults: one 120-s history and a 30-min hold per pass.
  DemoRun full("hold_trim", piezo::compensation::hold_trim_demo_defaults(), kLine, 11.0, true);
  EXPECT_GT(full.steps(), 2u * 1920u * 11u);
  EXPECT_LT(full.steps(), 2u * 1945u * 11u + 200u);
}

// tracking_trim: a warm-up pass, then the same moves with the tracking trim off and on, the hold trim on in both;
// |true − intended| scored during the moves (ramps and each hold's first settle_s) and in the holds from
// hold_score_from_s, the warm-up not at all.
TEST(DemoScenario, TrackingTrimScoresMovesAndHoldsOfTheScoredPasses) {
  piezo::compensation::MovesDemoOptions mo;
  mo.moves = 2, mo.hold_s = 20.0, mo.hold_score_from_s = 10.0, mo.rest_s = 5.0;
  DemoRun run("tracking_trim", CreepDemoOptions{}, kLine, 11.0, true, mo);
  EXPECT_TRUE(run.switches_tracking_trim());
  EXPECT_FALSE(run.switches_hold_trim());
  // Moving and the first 30 samples of a hold: 4 nm off without the tracking trim, 1 nm with it; then 0.3 / 0.2 nm.
  const auto physics = [](int mode, int k, double v) {
    return kLine.position_nm(v) + (k < 30 ? (mode ? 1.0 : 4.0) : (mode ? 0.2 : 0.3));
  };
  const auto estimate = [](int mode, int k) {
    DemoRun::Estimate e;
    e.tracking_trim_nm = mode ? 2.0 : 0.0;
    e.tracking_trim_state = mode == 0 ? "off" : k == 0 ? "active" : "handed_over";
    e.hold_trim_state = "active";
    return e;
  };
  std::vector<bool> modes;
  const auto j = drive(run, physics, nullptr, &modes, estimate);
  EXPECT_EQ(modes, (std::vector<bool>{false, true}));  // the warm-up and the first pass alike
  EXPECT_EQ(j["scenario"].as<std::string>(), "tracking_trim");
  EXPECT_NEAR(j["tracking_off_move_mean_nm"].as<double>(), 4.0, 1e-9);
  EXPECT_NEAR(j["tracking_on_move_mean_nm"].as<double>(), 1.0, 1e-9);
  EXPECT_NEAR(j["tracking_off_move_max_nm"].as<double>(), 4.0, 1e-9);
  EXPECT_NEAR(j["tracking_off_hold_max_nm"].as<double>(), 0.3, 1e-9);
  EXPECT_NEAR(j["tracking_on_hold_mean_nm"].as<double>(), 0.2, 1e-9);
  // per pass: 2 holds × (220 − 110 + 1) samples from 10 s on; the moves' count equal in both passes
  EXPECT_EQ(j["tracking_off_hold_samples"].as<int>(), 2 * 111);
  EXPECT_EQ(j["tracking_on_hold_samples"].as<int>(), 2 * 111);
  EXPECT_EQ(j["tracking_on_move_samples"].as<int>(), j["tracking_off_move_samples"].as<int>());
  EXPECT_GT(j["tracking_off_move_samples"].as<int>(), 3 * 11);
  EXPECT_EQ(j["tracking_off_active_samples"].as<int>(), 0);
  EXPECT_GT(j["tracking_on_active_samples"].as<int>(), 0);
  EXPECT_GE(j["tracking_off_applied_min_v"].as<double>(), mo.target_min_v);
  EXPECT_LE(j["tracking_on_applied_max_v"].as<double>(), mo.target_max_v);
  std::ostringstream csv;
  run.write_csv(csv);
  const std::string text = csv.str();
  EXPECT_NE(text.substr(0, text.find('\n')).find(",hold_trim_state,tracking_trim_nm,tracking_trim_state"), std::string::npos);
  EXPECT_NE(text.find(",2,active\n"), std::string::npos);
  // the three passes run the same intents
  const auto steps = piezo::compensation::moves_demo_steps(mo, 11.0);
  ASSERT_EQ(steps.size() % 3, 0u);
  const std::size_t n = steps.size() / 3;
  for (std::size_t i = 0; i < n; ++i) {
    ASSERT_EQ(steps[i].intent_v, steps[n + i].intent_v) << i;
    ASSERT_EQ(steps[i].intent_v, steps[2 * n + i].intent_v) << i;
  }
  EXPECT_EQ(steps[n - 1].intent_v, 0.0);
  mo.hold_score_from_s = 30.0;
  EXPECT_THROW(DemoRun("tracking_trim", CreepDemoOptions{}, kLine, 11.0, true, mo), std::invalid_argument);
}

TEST(DemoScenario, BadSettingsNameTheParameter) {
  const auto msg = [](auto f) {
    try {
      f();
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(msg([] { DemoRun("zigzag", CreepDemoOptions{}, kLine, 11.0); }).find("~scenario"), std::string::npos);
  CreepDemoOptions co;
  co.scenarios = {999};
  EXPECT_NE(msg([&] { DemoRun("creep", co, kLine, 11.0); }).find("~creep_scenarios"), std::string::npos);
}

}  // namespace
