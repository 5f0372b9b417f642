// The prony creep kind (pi_creep_prony) and the scale-free PI fits, checked on simulated stages whose physics the
// models were not written from (config/stages: Preisach hysteresis, creep spectra of first-order modes).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/sim/stage.h"
#include "test_hold_scoring.h"

using namespace piezo;
using models::PiCreepModel;


// Creep within 5 nm on the creep-protocol stage (config/stages/mm3e_preisach_creep_protocol.yaml: each scenario a
// 30-min random history ending in a fast approach, then a 30-min hold; a creep spectrum of five first-order modes
// between 3 s and 3 h, 11 Hz, 20.8 nm encoder noise), with its hysteresis switched to Prandtl–Ishlinskii: on the
// stage's asymmetric Preisach hysteresis no PI kind gets near 5 nm (docs/validation/models.md), so this asserts the
// creep part where the hysteresis is representable. 12 scenarios instead of 15 (fast test): 7 train, 2 validation,
// 3 test; the model runs free over all of them and is scored in the test holds against the true position.
TEST(PronyCreep, HoldsWithinFiveNanometresWithAnIndependentCreepSpectrum) {
  sim::StageConfig stage = sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/mm3e_preisach_creep_protocol.yaml");
  stage.simulator.axes[2].hysteresis_model = "prandtl_ishlinskii";
  stage.protocol_parameters["scenarios"] = 12;
  const double rate = stage.simulator.sample_rate_hz;
  const io::Dataset d = sim::simulate_stage(stage, 20261124);
  const std::size_t per = d.time_s.size() / 12, n_train = 7 * per, n_val = 9 * per;
  const io::Dataset train = slice(d, 0, n_train), val = slice(d, n_train, n_val);

  training::FitRequest req;
  req.train = &train;
  req.validation = &val;
  // The final model of a user who has chosen the kind: weights refitted on training + validation.
  req.options = YAML::Load("{refit_with_validation: true}");
  auto prony = training::fit_model("pi_creep_prony", req);
  const HoldScore s = score_holds(*prony, d, n_val, rate);
  std::cout << "pi_creep_prony: test-hold MAE vs truth " << s.mae_nm << " nm, worst end-of-hold " << s.worst_end_nm
            << " nm over " << s.holds << " holds\n";
  EXPECT_EQ(s.holds, 3);
  EXPECT_LE(s.mae_nm, 5.0);
  // Requirement: ≤ 5 nm at every end of hold, for the final model a user gets (refitted on train + validation);
  // figures: docs/validation/models.md, "Creep on physics no kind was written from".
  EXPECT_LE(s.worst_end_nm, 5.0);
  // PI hysteresis is a special case of the preisach kind: it must do no worse here (5 % slack on the worst end).
  auto pre = training::fit_model("preisach_creep_prony", req);
  const HoldScore sp = score_holds(*pre, d, n_val, rate);
  std::cout << "preisach_creep_prony: test-hold MAE vs truth " << sp.mae_nm << " nm, worst end-of-hold "
            << sp.worst_end_nm << " nm\n";
  EXPECT_LE(sp.mae_nm, s.mae_nm);
  EXPECT_LE(sp.worst_end_nm, std::min(5.0, 1.05 * s.worst_end_nm));
  // Identifiable modes only: none faster than two samples, none slower than the training record.
  const auto& pm = dynamic_cast<const PiCreepModel&>(*prony);
  for (double tau : pm.mode_taus_s()) {
    EXPECT_GE(tau, 2.0 / rate * 0.999);
    EXPECT_LE(tau, n_train / rate * 1.001);
  }
  for (double g : pm.mode_gains()) EXPECT_GE(g, 0.0);
}

// A short, fast, low-voltage recording (config/stages/lowvolt_preisach_creep.yaml: 0–3.6 V,
// ~50 µm, 200 Hz; 32 s train, 8 s validation) and a test recording of another seed that starts 5 s into its motion
// (unknown state). Every PI kind must give a bias and weights of the data's own scale (no cancelling pair), no mode
// the data cannot see, and a free-run error far below the travel.
TEST(PronyCreep, ShortLowVoltageRecordingGivesSaneParametersForEveryPiKind) {
  const sim::StageConfig stage = sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/lowvolt_preisach_creep.yaml");
  const double rate = stage.simulator.sample_rate_hz;
  const io::Dataset all = sim::simulate_stage(stage, 5, 40.0);
  const io::Dataset test_full = sim::simulate_stage(stage, 9, 75.0);
  const std::size_t cut = static_cast<std::size_t>(5 * rate);
  const io::Dataset test = slice(test_full, cut, test_full.time_s.size());
  const io::AxisSeries& tx = test.axis("c");
  const auto [mn, mx] = std::minmax_element(tx.true_position_nm.begin(), tx.true_position_nm.end());
  const double range = *mx - *mn;
  const std::size_t n_train = static_cast<std::size_t>(32 * rate);
  const io::Dataset train = slice(all, 0, n_train), val = slice(all, n_train, all.time_s.size());
  const io::AxisSeries& ax = all.axis("c");
  const auto [pmn, pmx] = std::minmax_element(ax.position_nm.begin(), ax.position_nm.end());
  const auto [vmn, vmx] = std::minmax_element(ax.voltage_v.begin(), ax.voltage_v.end());
  for (const char* kind :
       {"pi", "pi_creep_log", "pi_creep_lti", "pi_creep_fractional", "pi_creep_prony", "preisach", "preisach_creep_prony"}) {
    training::FitRequest req;
    req.train = &train;
    req.validation = &val;
    auto m = training::fit_model(kind, req);
    const auto& pm = dynamic_cast<const PiCreepModel&>(*m);
    EXPECT_LT(std::abs(pm.bias_nm()), 2 * (std::abs(*pmn) + std::abs(*pmx))) << kind;
    // The hysteretic travel (PI: Σw·span; preisach: its output over a full sweep) within a few times the measured one.
    auto sweep = m->clone();
    sweep->reset(*vmn, 0.0);
    const double y_lo = sweep->predict({*vmn, nullptr});
    EXPECT_LT(std::abs(sweep->predict({*vmx, nullptr}) - y_lo), 3 * (*pmx - *pmn)) << kind;
    for (double w : pm.weights()) EXPECT_GE(w, 0.0) << kind;
    for (double tau : pm.mode_taus_s()) {
      EXPECT_GE(tau, 2.0 / rate * 0.999) << kind;
      EXPECT_LE(tau, 32.0 * 1.001) << kind;
    }
    auto run = m->clone();
    run->reset(tx.voltage_v[0], tx.position_nm[0]);
    double sum = 0, worst = 0;
    std::size_t n = 0;
    for (std::size_t t = 0; t < tx.voltage_v.size(); ++t) {
      models::ModelInput in{tx.voltage_v[t], nullptr};
      const double y = run->predict(in);
      run->commit(in, y);
      if (t < static_cast<std::size_t>(rate)) continue;  // the first second belongs to the unknown state
      const double e = std::abs(y - tx.true_position_nm[t]);
      sum += e, ++n, worst = std::max(worst, e);
    }
    std::cout << kind << ": free-run MAE " << 100 * sum / n / range << " % of range, max " << 100 * worst / range
              << " %\n";
    EXPECT_LT(sum / n, 0.05 * range) << kind;
  }
}

TEST(PronyCreep, ModelFileRoundTripsAndBoundsItsSizes) {
  models::CreepParams cp;
  cp.kind = models::CreepKind::kProny;
  cp.tau_min_s = 0.2, cp.tau_max_s = 2000, cp.modes_per_decade = 2;
  cp.gains_nm_per_v.assign(cp.num_coefficients(), 0.0);
  for (std::size_t j = 0; j < cp.gains_nm_per_v.size(); ++j) cp.gains_nm_per_v[j] = 0.01 * (j + 1);
  PiCreepModel m({0, 10, 20}, {5, 1, 0.5}, 3.0, cp, 11.0);
  const std::string text = model_file_text(m);
  auto back = model_from_text(text);
  ASSERT_EQ(back->kind(), "pi_creep_prony");
  const auto& b = dynamic_cast<const PiCreepModel&>(*back);
  EXPECT_EQ(b.mode_taus_s(), m.mode_taus_s());
  EXPECT_EQ(b.mode_gains(), m.mode_gains());
  EXPECT_NE(load_error_after(text, "modes_per_decade: 2", "modes_per_decade: 500").find("modes_per_decade"), std::string::npos);
  EXPECT_NE(load_error_after(text, "tau_max_s: 2000", "tau_max_s: 1e30").find("decades"), std::string::npos);
  EXPECT_NE(load_error_after(text, "tau_max_s: 2000", "tau_max_s: 20000").find("mode_gains"), std::string::npos);
}
