// Controller logs in: a simulated recording written with a real log's faults (host clock with jitter, late rows and
// a gap, a counter reset, NaN read cells, a row without a read, a glitching thermocouple) and imported; every fault is
// counted and none passes on as a value. Malformed logs give one clear error each.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <string>

#include "piezo_compensation/io/controller_log.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/controller_log.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"

using namespace piezo;

namespace {

std::string tmp(const std::string& name) { return ::testing::TempDir() + "ctl_" + name; }

io::Dataset simulated_walk() {
  auto cfg = sim::default_simulator_config();
  sim::enable_effect(cfg, "thermal_drift");
  io::Dataset prog = protocols::make_protocol("random_walk", YAML::Load("{duration_s: 600}"), cfg.sample_rate_hz, 7)->program();
  sim::ManipulatorSimulator s(cfg, 7);
  return s.run(prog);
}

io::ControllerLogOptions mm3e_c() {
  io::ControllerLogOptions o;
  o.axis = "c";
  o.volts_per_step = 80.0 / 32768.0;
  o.nm_per_count = -20.0;
  return o;
}

std::string import_error(const std::string& text) {
  const std::string path = tmp("bad.csv");
  std::ofstream(path) << text;
  try {
    io::import_controller_log(path, mm3e_c());
  } catch (const io::DataError& e) {
    return e.what();
  }
  return "";
}

}  // namespace

TEST(ControllerLog, EveryFaultIsCountedAndNonePassesOn) {
  const io::Dataset sim = simulated_walk();
  sim::ControllerLogSpec spec;
  spec.zero_nm = 137.0;
  spec.gap_at_s = 200.0;
  spec.row_without_reads = 1000;
  const std::string path = tmp("walk.csv");
  const sim::ControllerLogFaults faults = sim::write_controller_log(path, sim, spec, 5);
  ASSERT_TRUE(faults.gap);
  ASSERT_GT(faults.temperature_nan, 0u);
  ASSERT_GT(faults.temperature_glitches, 0u);

  io::ControllerLogReport r;
  const io::Dataset d = io::import_controller_log(path, mm3e_c(), &r);
  std::cout << "[import] rows " << r.rows_in << " -> " << r.rows_out << ", read σ " << r.read_sigma_nm << " nm, mean σ "
            << r.mean_sigma_independent_nm << " / " << r.mean_sigma_holds_nm << " nm, temperature NaN " << r.temperature_nan
            << " glitches " << r.temperature_out_of_range << " jumps " << r.temperature_jumps << " held "
            << r.temperature_held << "\n";
  EXPECT_EQ(r.rows_in, sim.size());
  EXPECT_EQ(r.rows_without_reading, 1u);
  EXPECT_EQ(r.rows_out, sim.size() - 1);
  EXPECT_EQ(r.read_cells_bad, faults.read_cells_nan);
  EXPECT_EQ(r.temperature_nan, faults.temperature_nan);
  EXPECT_EQ(r.temperature_out_of_range, faults.temperature_glitches);
  EXPECT_EQ(r.temperature_held, r.temperature_nan + r.temperature_out_of_range + r.temperature_jumps);
  EXPECT_TRUE(r.mean_column_checked);
  ASSERT_TRUE(r.temperature_kept);

  // the reading: the mean of 5 reads of σ 21 nm on a 20-nm counter, against the truth less the reset zero
  EXPECT_NEAR(r.read_sigma_nm, std::sqrt(21.0 * 21.0 + 20.0 * 20.0 / 12.0), 2.0);
  const auto& c = d.axis("c");
  const auto& truth = sim.axis("c").true_position_nm;
  double se = 0;
  std::size_t n = 0;
  for (std::size_t i = 0, j = 0; i < d.size(); ++i, ++j) {
    if (j == spec.row_without_reads) ++j;  // the row left out
    EXPECT_NEAR(c.voltage_v[i], sim.axis("c").voltage_v[j], 80.0 / 32768.0);
    se += std::pow(c.position_nm[i] - (truth[j] - spec.zero_nm), 2), ++n;
  }
  const double rms = std::sqrt(se / static_cast<double>(n));
  std::cout << "[import] reading vs truth − zero: RMS " << rms << " nm\n";
  EXPECT_NEAR(rms, r.mean_sigma_independent_nm, 1.5);

  // no glitch or NaN passes on: every temperature cell is a plausible reading near the simulated one
  const io::AuxSignal* t = d.find_aux("temperature_c");
  ASSERT_NE(t, nullptr);
  const auto& true_t = sim.find_aux("temperature_c")->values;
  for (std::size_t i = 0; i < t->values.size(); ++i) ASSERT_NEAR(t->values[i], true_t[i < spec.row_without_reads ? i : i + 1], 0.3) << i;

  // the host clock: the gap and the late rows are stepped over and reported, the model's step is the median
  const io::TimeBase tb = io::time_base(d.time_s);
  EXPECT_FALSE(tb.constant);
  EXPECT_NEAR(d.sample_period_s(), 1.0 / 11.0, 0.002);
  EXPECT_GE(tb.late_steps, 1u);
  EXPECT_NEAR(tb.longest_step_s, spec.gap_s + 1.0 / 11.0, 0.1);
}

TEST(ControllerLog, TooFewGoodTemperatureCellsLeaveTheColumnOut) {
  const io::Dataset sim = simulated_walk().slice(0, 500);
  sim::ControllerLogSpec spec;
  spec.temperature_nan_fraction = 0.9;
  const std::string path = tmp("mostly_nan.csv");
  sim::write_controller_log(path, sim, spec, 6);
  io::ControllerLogReport r;
  const io::Dataset d = io::import_controller_log(path, mm3e_c(), &r);
  EXPECT_FALSE(r.temperature_kept);
  EXPECT_EQ(d.find_aux("temperature_c"), nullptr);
  EXPECT_GT(r.temperature_nan, 400u);
}

TEST(ControllerLog, AMalformedLogIsOneClearError) {
  const std::string head = "finestep,time,c_0,c_1,temp,c_mean\n";
  EXPECT_NE(import_error("time,c_0\n0,1\n").find("missing column finestep"), std::string::npos);
  EXPECT_NE(import_error(",finestep,ca_0,cd_0\n0,1,2,3\n").find("column ca_0: not a controller-log column"), std::string::npos);
  EXPECT_NE(import_error("finestep,c_0\n1,2\n").find("missing column time"), std::string::npos);
  EXPECT_NE(import_error("finestep,time,c_1\n1,0,2\n").find("missing column c_0"), std::string::npos);
  EXPECT_NE(import_error(head + "10,0.1,1,2,22,1.5\n11,abc,1,2,22,1.5\n").find("row 3, column time: not a number: 'abc'"),
            std::string::npos);
  EXPECT_NE(import_error(head + "10,0.1,1,2,22,1.5\n11,0.1,1,2,22,1.5\n").find("row 3, column time: time does not increase"),
            std::string::npos);
  EXPECT_NE(import_error(head + "10,0.1,1,2,22,1.7\n").find("row 2, column c_mean: 1.7 is not the mean of the reads"),
            std::string::npos);
  EXPECT_NE(import_error(head + "10,0.1,1,2,22\n").find("row 2: 5 cells, the header has 6"), std::string::npos);
  EXPECT_NE(import_error(head + "10,0.1,NaN,NaN,22,NaN\n").find("no row with a reading"), std::string::npos);
  io::ControllerLogOptions zero = mm3e_c();
  zero.nm_per_count = 0;
  const std::string path = tmp("ok.csv");
  std::ofstream(path) << head << "10,0.1,1,2,22,1.5\n";
  EXPECT_THROW(io::import_controller_log(path, zero), io::DataError);
  EXPECT_THROW(io::import_controller_log(tmp("nosuch.csv"), mm3e_c()), io::DataError);
}
