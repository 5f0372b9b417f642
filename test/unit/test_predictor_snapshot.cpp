// The predictor's ~snapshot: the ring buffer (bounded, cut so the file reads as it is) and the bag it writes,
// read back by the one bag reader `piezo residual` and `piezo eval` use.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>

#include "piezo_compensation/analysis/residual.h"
#include "piezo_compensation/compensation/snapshot_buffer.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/ros/predictor.h"

using namespace piezo;

namespace {

// Feeds n samples at 11 Hz from t0 as the driver publishes them: per axis the voltage report then the reading,
// the temperature once a second. The reading of axis c lags its report by 2 ms.
void feed(compensation::SnapshotBuffer& b, double t0, std::size_t n, std::uint32_t seq0 = 0) {
  for (std::size_t i = 0; i < n; ++i) {
    const double t = t0 + static_cast<double>(i) / 11.0;
    const auto seq = static_cast<std::uint32_t>(seq0 + i);
    const double va = 10.0 * std::sin(0.01 * i), vc = 20.0 * std::cos(0.013 * i);
    b.add_voltage("a", seq, va, t);
    b.add_reading("a", seq, 12.0 * va, true, t);
    // receive stamps jitter (host load): up to ±4 ms on c, one reading 0.3 s late
    const double jitter = (i == 1100 ? 0.3 : 0.004 * std::sin(1.7 * static_cast<double>(i)));
    b.add_voltage("c", seq, vc, t + jitter);
    b.add_reading("c", seq, 13.0 * vc, true, t + jitter + 0.002);
    if (i % 11 == 5) b.add_aux("temperature_c", 22.0 + 0.001 * static_cast<double>(i), t);
  }
}

}  // namespace

TEST(SnapshotBuffer, RefusesWhenEmptyAndBadOptions) {
  compensation::SnapshotBuffer b({60.0, 1000});
  EXPECT_THROW(b.take(), std::runtime_error);
  b.add_voltage("c", 1, 1.0, 100.0);  // a report without its reading is no sample
  try {
    b.take();
    FAIL() << "a buffer without readings gave a snapshot";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("no encoder reading"), std::string::npos) << e.what();
  }
  EXPECT_THROW(compensation::SnapshotBuffer({0.0, 1000}), std::invalid_argument);
  EXPECT_THROW(compensation::SnapshotBuffer({std::nan(""), 1000}), std::invalid_argument);
}

TEST(SnapshotBuffer, KeepsTheLastDurationBoundedAndCutsOnCompleteSamples) {
  compensation::SnapshotBuffer b({60.0, 100000});
  feed(b, 1000.0, 11 * 600);  // 10 min into a 1 min buffer
  // memory: 60 s (+1 s headroom) of 4 streams at 11 Hz and the temperature at 1 Hz, not 10 minutes
  EXPECT_LE(b.messages(), static_cast<std::size_t>(4 * 11 * 62 + 63));
  const compensation::Snapshot s = b.take();
  ASSERT_EQ(s.axes.size(), 2u);
  EXPECT_NEAR(s.end_s - s.begin_s, 60.0, 0.2);
  for (const auto& [axis, a] : s.axes) {
    ASSERT_FALSE(a.readings.empty());
    // the first reading's report is in, and nothing older than the window
    EXPECT_EQ(a.voltages.front().sequence, a.readings.front().sequence) << axis;
    EXPECT_GE(a.readings.front().stamp_s, s.end_s - 60.0) << axis;
  }
  ASSERT_EQ(s.aux.count("temperature_c"), 1u);
  const auto& temp = s.aux.at("temperature_c");
  EXPECT_LE(temp.front().stamp_s, s.begin_s) << "no temperature in force at the first row";
  EXPECT_GT(temp[1].stamp_s, s.begin_s);

  // the message cap bounds memory whatever the rate
  compensation::SnapshotBuffer capped({3600.0, 1000});
  feed(capped, 0.0, 11 * 600);
  EXPECT_LE(capped.messages(), 5u * 1000u);
  EXPECT_NO_THROW(capped.take());
}

TEST(SnapshotBuffer, AllocatesItsCapacityAtConstructionAndDoesNotGrowAtTheExpectedRate) {
  compensation::SnapshotOptions o{60.0, 100000};
  o.expected_rate_hz = 11.0;
  o.axes = {"a", "c"};
  o.aux = {"temperature_c"};
  compensation::SnapshotBuffer b(o);
  // 2 axes × (voltage, encoder, prediction) + 1 aux, each sized for 61 s at 11 Hz before anything arrives
  const std::size_t allocated = b.capacity();
  EXPECT_EQ(b.messages(), 0u);
  EXPECT_GE(allocated, 7u * 61u * 11u);
  EXPECT_LE(allocated, 7u * (61u * 11u * 11u / 10u + 8u));
  feed(b, 1000.0, 11 * 600);  // 10 min at 11 Hz (with receive jitter and a late reading) into the 1 min window
  for (std::size_t i = 0; i < 11 * 600; ++i)
    b.add_prediction("c", static_cast<std::uint32_t>(i), 1.0, 1000.0 + static_cast<double>(i) / 11.0);
  EXPECT_EQ(b.capacity(), allocated);
  EXPECT_EQ(b.grown(), 0u);
  EXPECT_GE(b.messages(), 5u * 11u * 60u);  // full: a, c voltages and readings, c predictions
  EXPECT_NO_THROW(b.take());

  // 4× faster than expected: the rings double (counted), bounded by max_messages per stream, nothing lost
  compensation::SnapshotBuffer fast({60.0, 4000});
  const std::size_t fast_allocated = fast.capacity();
  for (std::size_t i = 0; i < 44 * 120; ++i) {
    const double t = static_cast<double>(i) / 44.0;
    fast.add_voltage("c", static_cast<std::uint32_t>(i), 1.0, t);
    fast.add_reading("c", static_cast<std::uint32_t>(i), 2.0, true, t);
  }
  EXPECT_GT(fast.grown(), 0u);
  EXPECT_GT(fast.capacity(), fast_allocated);
  EXPECT_LE(fast.capacity(), 3u * 4000u);
  const compensation::Snapshot s = fast.take();
  // 60 s at 44 Hz (the first one on the window's edge, in or out by rounding)
  EXPECT_NEAR(static_cast<double>(s.axes.at("c").readings.size()), 44.0 * 60.0, 1.0);

  // one clear error for a rate that cannot size a ring
  for (double bad : {0.0, -1.0, std::nan(""), HUGE_VAL, 1e6}) {
    compensation::SnapshotOptions b_o{60.0, 1000};
    b_o.expected_rate_hz = bad;
    try {
      compensation::SnapshotBuffer x(b_o);
      FAIL() << "expected_rate_hz " << bad << " accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("expected_rate_hz"), std::string::npos) << e.what();
    }
  }
}

TEST(SnapshotBuffer, AStreamThatStartsLateMovesTheStart) {
  compensation::SnapshotBuffer b({60.0, 100000});
  feed(b, 1000.0, 11 * 30);
  b.add_aux("humidity", 40.0, 1020.0);  // first value 20 s in: every row needs a value at or before it
  const compensation::Snapshot s = b.take();
  EXPECT_GE(s.begin_s, 1020.0);
  EXPECT_LE(s.aux.at("humidity").front().stamp_s, s.begin_s);
}

TEST(SnapshotBuffer, InvalidReadingsAreLeftOutAndCounted) {
  compensation::SnapshotBuffer b({60.0, 100000});
  feed(b, 1000.0, 100);
  b.add_voltage("a", 100, 1.0, 1009.05);
  b.add_reading("a", 100, 0.0, false, 1009.05);
  b.add_voltage("c", 100, 1.0, 1009.05);
  b.add_reading("c", 100, std::nan(""), true, 1009.05);
  feed(b, 1009.1, 5, 101);
  const compensation::Snapshot s = b.take();
  EXPECT_EQ(s.invalid_readings, 2u);
  EXPECT_EQ(s.axes.at("a").readings.size(), 100u);  // 105 valid, less the 5 before the first temperature
  // only invalid readings in the window: nothing to write, said so
  compensation::SnapshotBuffer only_invalid({60.0, 1000});
  only_invalid.add_voltage("c", 1, 1.0, 5.0);
  only_invalid.add_reading("c", 1, 0.0, false, 5.0);
  EXPECT_THROW(only_invalid.take(), std::runtime_error);
}

TEST(SnapshotBag, ReadsAsItIsWithTheOneBagReader) {
  compensation::SnapshotBuffer b({60.0, 100000});
  feed(b, 1.7e9, 11 * 120, 4294966000u);  // epoch-like stamps, sequence numbers wrapping at 2^32 in the window
  const compensation::Snapshot s = b.take();
  const std::string dir = ::testing::TempDir() + "snapshot_test";
  std::filesystem::remove_all(dir);
  const std::string path = predictor::snapshot_path(dir, s.end_s);
  EXPECT_NE(path.find("snapshot_20231114T"), std::string::npos) << path;
  predictor::write_snapshot_bag(path, "/mm1", s, "base");
  EXPECT_NE(predictor::snapshot_path(dir, s.end_s), path) << "a second snapshot must not overwrite the first";

  const io::Dataset d = ros_io::read_bag(path);
  // the sample clock: constant rate (what every offline tool requires) though the receive stamps jitter
  EXPECT_NEAR(d.sample_period_s(), 1.0 / 11.0, 1e-9);
  EXPECT_NEAR(s.period_s, 1.0 / 11.0, 1e-9);
  EXPECT_NEAR(s.max_restamp_s, 0.3, 0.01);  // the late reading
  ASSERT_EQ(d.axes.size(), 2u);
  EXPECT_EQ(d.time_clock, "ros");
  EXPECT_EQ(d.size(), s.axes.at("a").readings.size());
  const auto* c = &d.axis("c");
  for (std::size_t i = 0; i < d.size(); ++i) {
    ASSERT_NEAR(c->position_nm[i], 13.0 * c->voltage_v[i], 1e-6) << "row " << i << ": a reading paired with "
                                                                   << "another sample's report";
  }
  ASSERT_EQ(d.aux.size(), 1u);
  EXPECT_EQ(d.aux[0].name, "temperature_c");
  EXPECT_NEAR(d.aux[0].values.back(), s.aux.at("temperature_c").back().value, 1e-12);
}

TEST(SnapshotBag, RefusesADirectoryItCannotCreate) {
  // a path that is a file, not a directory (and one below it), is refused with the reason, for any user
  const std::string file = ::testing::TempDir() + "snapshot_not_a_dir";
  { std::ofstream(file) << "x"; }
  for (const std::string& dir : {file, file + "/sub"}) {
    try {
      predictor::snapshot_path(dir, 1.7e9);
      FAIL() << dir << " accepted as the snapshot directory";
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find(dir), std::string::npos) << e.what();
    }
  }
}

// Issue 18: `piezo residual` finds a stroke gain in a snapshot bag. The simulated device (default physics, a
// random walk on c) with a stroke that scales by 5 %/°C with the temperature through a 30 s low-pass (the
// simulator has no gain effect: it is applied to its positions here), heard as the predictor hears it and written
// by the ~snapshot writer; base = the clean model the live_loop rostest starts with.
TEST(SnapshotBag, PiezoResidualFindsAStrokeGainInIt) {
  sim::ManipulatorSimulator device(sim::default_simulator_config(), 5);
  const io::Dataset run =
      device.run(protocols::make_protocol("random_walk", YAML::Load("{duration_s: 1800}"), 11.0, 5)->program());
  const auto& c = run.axis("c");
  compensation::SnapshotBuffer b({1800.0, 100000});
  const double t0 = 1.7e9, dt = 1.0 / 11.0, alpha = 1.0 - std::exp(-dt / 30.0);
  double lagged = 22.0;
  for (std::size_t i = 0; i < run.size(); ++i) {
    const double t = run.time_s[i];
    const double temperature = 22.0 + 1.5 * std::sin(2.0 * M_PI * t / 200.0 + 0.3);
    lagged += alpha * (temperature - lagged);
    const double gain = 0.05 * (lagged - 22.0);
    const double measured = 20.0 * std::round((c.position_nm[i] + c.true_position_nm[i] * gain) / 20.0);
    const auto seq = static_cast<std::uint32_t>(i);
    b.add_aux("temperature_c", temperature, t0 + t);
    b.add_voltage("c", seq, c.voltage_v[i], t0 + t);
    b.add_reading("c", seq, measured, true, t0 + t);
  }
  const std::string dir = ::testing::TempDir() + "snapshot_gain";
  std::filesystem::remove_all(dir);
  const compensation::Snapshot s = b.take();
  const std::string path = predictor::snapshot_path(dir, s.end_s);
  predictor::write_snapshot_bag(path, "/mm1", s, "base");
  const io::Dataset d = ros_io::read_bag(path);
  const std::size_t cut = d.size() * 7 / 10;
  const auto base = models::load_model(std::string(PIEZO_SOURCE_DIR) + "/test/rostest/mm3e_sim_c_lti.yaml");
  analysis::ResidualOptions o;
  o.permutations = 200;
  o.families = {"aux_signal", "aux_gain", "time_drift", "time_gain", "voltage_nonlinearity"};
  const analysis::ResidualResult r = analysis::trace_residual(*base, d.slice(0, cut), d.slice(cut, d.size()), o);
  ASSERT_FALSE(r.effects.empty()) << "nothing found in the snapshot";
  std::cout << "[snapshot gain] first effect " << r.effects[0].family << " on " << r.effects[0].labels.at("signal")
            << ", " << r.effects.size() << " effect(s), TEST MAE " << r.before_test.mae_nm << " -> "
            << r.after_test.mae_nm << " nm\n";
  EXPECT_EQ(r.effects[0].family, "aux_gain");
  EXPECT_EQ(r.effects[0].labels.at("signal"), "temperature_c");
  EXPECT_LT(r.after_test.mae_nm, 0.8 * r.before_test.mae_nm);
}
