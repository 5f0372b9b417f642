// The residual loop on data that starts mid-history (a predictor ~snapshot, a recording begun on a stage in use):
// the base run "at rest at the first voltage" is off by its unknown initial creep state. With start transients
// (ResidualOptions::start_transients, `piezo residual --mid-history`) the thermal term comes out as the simulator
// made it; without them the cold start confounds it. Data: the live_loop rostest's device (60 nm/°C through a 20 s
// lag, 200 s temperature cycle), 1800 s of random walk cut at 500 s; base: the rostest's clean pi_creep_lti model.
#include <gtest/gtest.h>

#include <cmath>
#include <iostream>

#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"

namespace pa = piezo::analysis;

namespace {

struct TraceRun {
  pa::ResidualResult r;
  double tau_s = 0.0, gain_nm_per_c = 0.0;
};

TraceRun trace(bool start_transients) {
  piezo::sim::SimulatorConfig cfg =
      piezo::sim::load_simulator_config(std::string(PIEZO_SOURCE_DIR) + "/test/rostest/sim_fast_thermal.yaml");
  piezo::sim::enable_effect(cfg, "thermal_drift");
  YAML::Node p;
  p["duration_s"] = 1800.0;
  const auto proto = piezo::protocols::make_protocol("random_walk", p, 11.0, 5);
  piezo::sim::ManipulatorSimulator sim(cfg, 5);
  const piezo::io::Dataset all = sim.run(proto->program());
  const piezo::io::Dataset d = all.slice(500 * 11, all.size());
  const std::size_t cut = d.size() * 7 / 10;
  const auto base = piezo::models::load_model(std::string(PIEZO_SOURCE_DIR) + "/test/rostest/mm3e_sim_c_lti.yaml");
  pa::ResidualOptions o;
  o.axis = "c";
  o.start_transients = start_transients;
  TraceRun run;
  run.r = pa::trace_residual(*base, d.slice(0, cut), d.slice(cut, d.size()), o);
  for (const auto& e : run.r.effects)
    if (e.family == "aux_signal" && run.tau_s == 0.0) {
      run.tau_s = e.parameters.at("time_constant_s");
      run.gain_nm_per_c = e.parameters.at("gain_nm_per_unit");
    }
  std::cerr << (start_transients ? "mid-history: " : "as if from rest: ") << "TEST MAE " << run.r.before_test.mae_nm
            << " -> " << run.r.after_test.mae_nm << " nm (vs truth " << run.r.before_test_truth.mae_nm << " -> "
            << run.r.after_test_truth.mae_nm << " nm), effects:";
  for (const auto& e : run.r.effects) std::cerr << " " << e.family;
  std::cerr << "; aux_signal tau " << run.tau_s << " s, gain " << run.gain_nm_per_c << " nm/°C\n";
  return run;
}

}  // namespace

TEST(ResidualMidHistory, StartTransientsRecoverTheThermalTerm) {
  const TraceRun with = trace(true);
  ASSERT_EQ(with.r.effects.size(), 1u);
  EXPECT_EQ(with.r.effects[0].family, "aux_signal");
  EXPECT_EQ(with.r.effects[0].labels.at("signal"), "temperature_c");
  EXPECT_NEAR(with.tau_s, 20.0, 7.0);
  EXPECT_NEAR(with.gain_nm_per_c, 60.0, 9.0);
  // before ~51 nm against the true position; what is left is mostly the base's play states at the cut, which a decay
  // cannot express (from rest the same model reaches 1.9 nm)
  EXPECT_LT(with.r.after_test_truth.mae_nm, 15.0);
  const TraceRun without = trace(false);
  EXPECT_GT(without.r.after_test_truth.mae_nm, with.r.after_test_truth.mae_nm + 10.0)
      << "the cold start should matter on this data";
}
