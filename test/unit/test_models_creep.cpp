#include <gtest/gtest.h>

#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/training/fitters.h"
#include "test_models_data.h"

using namespace piezo;
using models::CreepKind;
using models::CreepParams;
using models::PiCreepModel;

namespace {
const std::vector<double> kR = {0, 10, 20, 30, 40, 50};
const std::vector<double> kW = {8.0, 2.0, 1.5, 1.0, 0.6, 0.3};

// Data from the model itself: 6 h random walk with long holds, small encoder noise.
io::Dataset generate(const CreepParams& cp, double noise_nm) {
  PiCreepModel truth(kR, kW, 10.0, cp, 11.0);
  std::vector<int> phase;
  const auto v = testdata::random_walk_v(6 * 3600 * 11, 17, 0.0005, &phase);
  return testdata::make_dataset(truth, v, 11.0, noise_nm, 4, &phase);
}

const PiCreepModel& fit(const io::Dataset& d, const std::string& kind, models::ModelPtr& keep,
                       const std::string& input = "voltage") {
  training::FitRequest req;
  req.train = &d;
  req.options["thresholds_v"] = kR;
  req.options["creep_input"] = input;
  keep = training::fit_model(kind, req);
  EXPECT_EQ(keep->kind(), kind);
  return dynamic_cast<const PiCreepModel&>(*keep);
}
}  // namespace

TEST(CreepModels, LogarithmicRecoversGammaAndT1) {
  CreepParams cp;
  cp.kind = CreepKind::kLog;
  cp.gamma_nm_per_v = 0.4;
  cp.t1_s = 3.0;
  cp.decades = 3;  // 3 s … 3000 s: the fit keeps no mode slower than the 6-h record (3·10^4 s would be)
  models::ModelPtr keep;
  const auto& m = fit(generate(cp, 2.0), "pi_creep_log", keep);
  EXPECT_NEAR(m.creep().gamma_nm_per_v, 0.4, 0.02);
  EXPECT_NEAR(std::log10(m.creep().t1_s), std::log10(3.0), 0.1);
  EXPECT_NEAR(m.weights()[0], kW[0], 0.2);
}

TEST(CreepModels, LtiRecoversSpringDamperPairs) {
  CreepParams cp;
  cp.kind = CreepKind::kLti;
  cp.taus_s = {30.0, 1500.0};
  cp.gains_nm_per_v = {1.2, 0.8};
  models::ModelPtr keep;
  const auto& m = fit(generate(cp, 2.0), "pi_creep_lti", keep);
  ASSERT_EQ(m.creep().taus_s.size(), 2u);
  EXPECT_NEAR(std::log10(m.creep().taus_s[0]), std::log10(30.0), 0.05);
  EXPECT_NEAR(std::log10(m.creep().taus_s[1]), std::log10(1500.0), 0.05);
  EXPECT_NEAR(m.creep().gains_nm_per_v[0], 1.2, 0.05);
  EXPECT_NEAR(m.creep().gains_nm_per_v[1], 0.8, 0.05);
}

// A backfitting refit (training::refit_options) starts the law from the previous model's time constants and only
// refines near them, one round as the alternation does: from constants 0.1 decade off (a refit's data moved little)
// it comes back to the truth, like the full search.
TEST(CreepModels, LtiWarmStartRefinesFromThePreviousTimeConstants) {
  CreepParams cp;
  cp.kind = CreepKind::kLti;
  cp.taus_s = {30.0, 1500.0};
  cp.gains_nm_per_v = {1.2, 0.8};
  const io::Dataset d = generate(cp, 2.0);
  CreepParams off = cp;
  off.taus_s = {30.0 * 1.26, 1500.0 / 1.26};
  const PiCreepModel previous(kR, kW, 10.0, off, 11.0);
  YAML::Node given;
  given["thresholds_v"] = kR;
  given["creep_input"] = "voltage";
  const YAML::Node o = training::refit_options(previous, given);
  ASSERT_TRUE(o["warm_start"] && o["warm_start"].as<bool>());
  ASSERT_EQ(o["taus_s"].as<std::vector<double>>(), off.taus_s);
  EXPECT_EQ(o["creep_input"].as<std::string>(), "voltage");  // what the caller gave stays
  training::FitRequest req;
  req.train = &d;
  req.options = o;
  const auto fitted = training::fit_model("pi_creep_lti", req);
  const auto& m = dynamic_cast<const PiCreepModel&>(*fitted);
  ASSERT_EQ(m.creep().taus_s.size(), 2u);
  EXPECT_NEAR(std::log10(m.creep().taus_s[0]), std::log10(30.0), 0.05);
  EXPECT_NEAR(std::log10(m.creep().taus_s[1]), std::log10(1500.0), 0.05);
  // Only near: from a constant a decade off, the refit stays within half a decade of it (the full search would not).
  CreepParams far = cp;
  far.taus_s = {3.0, 1500.0};
  req.options = training::refit_options(PiCreepModel(kR, kW, 10.0, far, 11.0), given);
  const auto near = training::fit_model("pi_creep_lti", req);
  EXPECT_LE(dynamic_cast<const PiCreepModel&>(*near).creep().taus_s[0], 3.0 * std::pow(10.0, 0.5) + 1e-9);
  // Options given by the caller win; a warm start needs the law's start.
  given["taus_s"] = std::vector<double>{5.0, 50.0};
  EXPECT_EQ(training::refit_options(previous, given)["taus_s"].as<std::vector<double>>(), (std::vector<double>{5.0, 50.0}));
  YAML::Node bad;
  bad["warm_start"] = true;
  req.options = bad;
  try {
    training::fit_model("pi_creep_lti", req);
    ADD_FAILURE() << "warm_start without taus_s was accepted";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("warm_start"), std::string::npos) << e.what();
  }
}

// The refits of a lag profile are compared with each other, so they keep the previous model's structure
// (refit_options(previous, options, true)): its play thresholds, creep input and maps, even where a validation part
// would choose others. Without the flag they are chosen again.
TEST(CreepModels, SameStructureRefitKeepsThresholdsCreepInputAndMaps) {
  CreepParams cp;
  cp.kind = CreepKind::kLti;
  cp.on_hysteresis = true;
  cp.taus_s = {30.0, 1500.0};
  cp.gains_nm_per_v = {0.05, 0.05};
  const std::vector<double> coarse = {0.0, 25.0};
  const PiCreepModel previous(coarse, {8.0, 2.0}, 10.0, cp, 11.0);
  const YAML::Node again = training::refit_options(previous, YAML::Node(), false);
  EXPECT_FALSE(again["thresholds_v"] || again["creep_input"] || again["input_map"] || again["output_map"]);
  const YAML::Node same = training::refit_options(previous, YAML::Node(), true);
  EXPECT_EQ(same["thresholds_v"].as<std::vector<double>>(), coarse);
  EXPECT_EQ(same["creep_input"].as<std::string>(), "hysteresis");
  EXPECT_EQ(same["input_map"].as<std::string>(), "off");
  EXPECT_EQ(same["output_map"].as<std::string>(), "off");
  // A fit with a validation part keeps them: the data (six plays) would choose more than two.
  const io::Dataset d = generate(cp, 2.0);
  const std::size_t cut = d.size() * 3 / 4;
  const io::Dataset fit_part = d.slice(0, cut), val_part = d.slice(cut, d.size());
  training::FitRequest req;
  req.train = &fit_part;
  req.validation = &val_part;
  req.options = same;
  const auto kept = training::fit_model("pi_creep_lti", req);
  EXPECT_EQ(dynamic_cast<const PiCreepModel&>(*kept).thresholds_v(), coarse);
  req.options = again;
  const auto chosen = training::fit_model("pi_creep_lti", req);
  EXPECT_GT(dynamic_cast<const PiCreepModel&>(*chosen).thresholds_v().size(), coarse.size());
}

TEST(CreepModels, LtiOnTheHysteresisOutputRecoversByAlternatingLeastSquares) {
  CreepParams cp;
  cp.kind = CreepKind::kLti;
  cp.on_hysteresis = true;
  cp.taus_s = {20.0, 2000.0};
  cp.gains_nm_per_v = {0.08, 0.12};  // relative: 8 % and 12 % of H
  models::ModelPtr keep;
  const auto& m = fit(generate(cp, 2.0), "pi_creep_lti", keep, "hysteresis");
  ASSERT_TRUE(m.creep().on_hysteresis);
  EXPECT_NEAR(std::log10(m.creep().taus_s[0]), std::log10(20.0), 0.05);
  EXPECT_NEAR(std::log10(m.creep().taus_s[1]), std::log10(2000.0), 0.05);
  EXPECT_NEAR(m.creep().gains_nm_per_v[0], 0.08, 0.005);
  EXPECT_NEAR(m.creep().gains_nm_per_v[1], 0.12, 0.005);
  for (std::size_t i = 0; i < kW.size(); ++i) EXPECT_NEAR(m.weights()[i], kW[i], 0.05 * kW[i] + 0.02) << i;
}

TEST(CreepModels, FractionalRecoversOrderAndGain) {
  CreepParams cp;
  cp.kind = CreepKind::kFractional;
  cp.alpha = 0.3;
  cp.b_nm_per_v = 0.5;
  cp.modes_per_decade = 2;
  cp.tau_max_s = 6 * 3600;  // the fit's memory ends at the record's duration (no unidentifiable modes)
  models::ModelPtr keep;
  const auto& m = fit(generate(cp, 2.0), "pi_creep_fractional", keep);
  EXPECT_NEAR(m.creep().alpha, 0.3, 0.02);
  EXPECT_NEAR(m.creep().b_nm_per_v, 0.5, 0.05);
}

TEST(CreepModels, StepResponsesHaveTheirLawsShape) {
  // log: equal rise per decade of time; fractional: power law t^α (between the mode bands).
  auto step_response = [](const CreepParams& cp, std::vector<double> at_s) {
    PiCreepModel m({0}, {1.0}, 0.0, cp, 11.0);
    m.reset(0, 0);
    std::vector<double> out;
    std::size_t k = 0;
    for (std::size_t i = 0; k < at_s.size(); ++i) {
      const double y = m.predict_v(1.0);
      if (i >= at_s[k] * 11.0) out.push_back(y - 1.0), ++k;  // minus the instantaneous part
      m.commit({1.0, nullptr}, y);
    }
    return out;
  };
  CreepParams log;
  log.kind = CreepKind::kLog;
  log.gamma_nm_per_v = 1.0;
  log.t1_s = 0.5;
  const auto y = step_response(log, {10, 100, 1000});
  EXPECT_NEAR(y[1] - y[0], std::log(10.0), 0.1);
  EXPECT_NEAR(y[2] - y[1], std::log(10.0), 0.1);
  CreepParams fr;
  fr.kind = CreepKind::kFractional;
  fr.alpha = 0.4;
  fr.b_nm_per_v = 1.0;
  fr.modes_per_decade = 4;
  const auto z = step_response(fr, {30, 300, 3000});
  EXPECT_NEAR(std::log10(z[1] / z[0]), 0.4, 0.05);
  EXPECT_NEAR(std::log10(z[2] / z[1]), 0.4, 0.05);
  EXPECT_NEAR(z[1], std::pow(300.0, 0.4) / std::tgamma(1.4), 0.1 * z[1]);
}
