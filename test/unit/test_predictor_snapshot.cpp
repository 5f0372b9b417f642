// The predictor's ~snapshot: the ring buffer (bounded, cut so the file reads as it is) and the bag it writes,
// read back by the one bag reader `piezo residual` and `piezo eval` use.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <algorithm>
#include <functional>
#include <iostream>

#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/compensation/reload_warmup.h"
#include "piezo_compensation/compensation/snapshot_buffer.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/ros/predictor.h"
#include "test_compensation_models.h"

using namespace piezo;

namespace {

// Feeds n samples at 11 Hz from t0 as the driver publishes them: per axis the voltage report then the reading,
// the temperature once a second. The reading of axis c lags its report by 2 ms. `lost(axis, i)`: sample i of the
// axis never arrives (report and reading dropped beyond the predictor's queues).
void feed(compensation::SnapshotBuffer& b, double t0, std::size_t n, std::uint32_t seq0 = 0,
          const std::function<bool(const char*, std::size_t)>& lost = nullptr) {
  for (std::size_t i = 0; i < n; ++i) {
    const double t = t0 + static_cast<double>(i) / 11.0;
    const auto seq = static_cast<std::uint32_t>(seq0 + i);
    const double va = 10.0 * std::sin(0.01 * i), vc = 20.0 * std::cos(0.013 * i);
    if (!lost || !lost("a", i)) {
      b.add_voltage("a", seq, va, t);
      b.add_reading("a", seq, 12.0 * va, true, t);
    }
    // receive stamps jitter (host load): up to ±4 ms on c, one reading 0.3 s late
    const double jitter = (i == 1100 ? 0.3 : 0.004 * std::sin(1.7 * static_cast<double>(i)));
    if (!lost || !lost("c", i)) {
      b.add_voltage("c", seq, vc, t + jitter);
      b.add_reading("c", seq, 13.0 * vc, true, t + jitter + 0.002);
    }
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
  EXPECT_EQ(s.gaps.size(), 2u) << "a reading left out is a missing sample on the sample clock";
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

  EXPECT_TRUE(s.gaps.empty()) << "a late reading is no gap";
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

// Samples lost beyond the predictor's queues leave a gap on the sample clock, which the offline tools step over as
// one sample (io::TimeBase). ~snapshot writes a stretch without one — never filled in — so a resumed model runs over
// a history without a step it did not see, and says what it cut.
TEST(SnapshotBag, AGapIsCutOutAndTheStretchWrittenReadsAsItIs) {
  const std::string dir = ::testing::TempDir() + "snapshot_gap";
  std::filesystem::remove_all(dir);
  struct Case {
    const char* name;
    std::size_t lost_from, lost_n;  // samples lost on both axes (the window holds samples 659 or 660 to 1319)
    const char* which;              // the stretch written
    bool before_gap;                // it ends at the gap (else it starts there)
  };
  // gap 49 s into the 60 s window: the recent 10.5 s are under 60 % of it, the 49 s before are written;
  // gap 4 s in: the most recent 55.7 s are
  for (const Case& k : {Case{"late gap", 1200, 3, "longest", true}, Case{"early gap", 704, 2, "most recent", false}}) {
    SCOPED_TRACE(k.name);
    compensation::SnapshotBuffer b({60.0, 100000});
    feed(b, 1.7e9, 11 * 120, 0, [&](const char*, std::size_t i) { return i >= k.lost_from && i < k.lost_from + k.lost_n; });
    const compensation::Snapshot s = b.take();
    std::size_t rows = 0;  // samples of the stretch, per axis
    for (const auto& r : s.axes.at("a").readings)
      rows += (k.before_gap ? r.sequence < k.lost_from : r.sequence >= k.lost_from + k.lost_n) ? 1 : 0;
    ASSERT_EQ(s.gaps.size(), 2u);  // one per axis
    for (const auto& g : s.gaps) {
      EXPECT_EQ(g.missing, k.lost_n);
      EXPECT_NEAR(g.before_s - g.after_s, (k.lost_n + 1) / 11.0, 1e-3);  // on the sample clock: whole periods
    }
    // the whole window, as it was heard: the offline reader shows the gap as one late step
    const std::string whole = dir + "/whole_" + std::to_string(k.lost_from) + ".bag";
    std::filesystem::create_directories(dir);
    predictor::write_snapshot_bag(whole, "/mm1", s, "base");
    EXPECT_EQ(io::time_base(ros_io::read_bag(whole).time_s).late_steps, 1u);

    const compensation::SnapshotStretch cut = compensation::gap_free_stretch(s);
    EXPECT_TRUE(cut.snapshot.gaps.empty());
    std::cout << "[snapshot gap] " << k.name << ": " << cut.message << "\n";
    EXPECT_NE(cut.message.find(k.which), std::string::npos) << cut.message;
    EXPECT_NE(cut.message.find(std::to_string(k.lost_n) + " on c after +"), std::string::npos) << cut.message;
    const std::size_t held = s.axes.at("a").readings.size() + s.axes.at("c").readings.size();
    EXPECT_EQ(cut.dropped_readings, held - 2 * rows);
    EXPECT_NE(cut.message.find(std::to_string(cut.dropped_readings) + " readings left out"), std::string::npos)
        << cut.message;
    const std::string path = predictor::snapshot_path(dir, cut.snapshot.end_s);
    predictor::write_snapshot_bag(path, "/mm1", cut.snapshot, "base");
    const io::Dataset d = ros_io::read_bag(path);
    EXPECT_NEAR(d.sample_period_s(), 1.0 / 11.0, 1e-9);  // contiguous: every step one period
    ASSERT_EQ(d.size(), rows);
    const double gap_at = s.gaps[0].after_s;
    EXPECT_TRUE(d.time_s.back() <= gap_at + 1e-6 || d.time_s.front() > gap_at) << "the gap is inside the bag";
    const auto& c = d.axis("c");
    for (std::size_t i = 0; i < d.size(); ++i)
      ASSERT_NEAR(c.position_nm[i], 13.0 * c.voltage_v[i], 1e-6) << "row " << i << " paired with another sample";
    const auto& temp = cut.snapshot.aux.at("temperature_c");
    EXPECT_LE(temp.front().stamp_s, cut.snapshot.begin_s) << "no temperature in force at the first row";
    EXPECT_LE(temp.back().stamp_s, cut.snapshot.end_s + 0.05);
  }

  // gaps every 10 s of a 60 s window, on c only: no stretch of 15 s (25 %), one error naming the gaps
  compensation::SnapshotBuffer b({60.0, 100000});
  feed(b, 1.7e9, 11 * 120, 0, [](const char* axis, std::size_t i) { return axis[0] == 'c' && i % 110 == 50; });
  const compensation::Snapshot s = b.take();
  EXPECT_GE(s.gaps.size(), 5u);
  try {
    compensation::gap_free_stretch(s);
    FAIL() << "a window in 10-s pieces was written";
  } catch (const std::runtime_error& e) {
    const std::string m = e.what();
    std::cout << "[snapshot gap] refused: " << m << "\n";
    EXPECT_NE(m.find("no stretch without a missing sample"), std::string::npos) << m;
    EXPECT_NE(m.find("1 on c after +"), std::string::npos) << m;
  }
}

// The warm-up's data set, made in memory from the snapshot (compensation/reload_warmup.h), is the data set its
// ~snapshot bag reads as: the same rows and sequence numbers, the same columns, across a gap and a wrap.
TEST(SnapshotReload, TheInMemoryHistoryIsTheBagsDataSet) {
  const std::string dir = ::testing::TempDir() + "snapshot_memory";
  std::filesystem::create_directories(dir);
  for (const bool gap : {false, true}) {
    SCOPED_TRACE(gap ? "a gap on a" : "no gap");
    compensation::SnapshotBuffer b({60.0, 100000});
    feed(b, 1.7e9, 11 * 120, 4294966000u, [&](const char* axis, std::size_t i) { return gap && axis[0] == 'a' && i == 1000; });
    const compensation::Snapshot s = b.take();
    const std::string path = dir + (gap ? "/gap.bag" : "/whole.bag");
    predictor::write_snapshot_bag(path, "/mm1", s, "base", io::kOriginSimulated);
    std::vector<std::uint32_t> bag_seq, mem_seq;
    const io::Dataset from_bag = ros_io::read_bag(path, {}, &bag_seq);
    const io::Dataset in_memory = compensation::snapshot_dataset(s, &mem_seq);
    EXPECT_EQ(from_bag.origin, io::kOriginSimulated);
    ASSERT_EQ(in_memory.size(), from_bag.size());
    EXPECT_EQ(mem_seq, bag_seq);
    EXPECT_EQ(in_memory.time_clock, from_bag.time_clock);
    ASSERT_EQ(in_memory.axes.size(), from_bag.axes.size());
    for (std::size_t i = 0; i < from_bag.size(); ++i) {
      ASSERT_NEAR(in_memory.time_s[i], from_bag.time_s[i], 1e-6) << "row " << i;  // the bag keeps nanoseconds
      for (std::size_t k = 0; k < from_bag.axes.size(); ++k) {
        ASSERT_EQ(in_memory.axes[k].voltage_v[i], from_bag.axes[k].voltage_v[i]) << "row " << i;
        ASSERT_NEAR(in_memory.axes[k].position_nm[i], from_bag.axes[k].position_nm[i], 1e-9) << "row " << i;
      }
    }
    ASSERT_EQ(in_memory.aux.size(), 1u);
    EXPECT_EQ(in_memory.aux[0].values, from_bag.aux[0].values);
    EXPECT_EQ(in_memory.size(), s.axes.at("a").readings.size());
    if (gap) EXPECT_LT(in_memory.size(), s.axes.at("c").readings.size()) << "the sample a lost has a row";
  }
}

// ~reload_model onto the running base (compensation/base_handover.h) when another axis lost a sample in the window:
// the reader makes no row of it, so the rows and this axis' readings no longer line up by index. Stage c is the
// base + 20 nm; the running base has seen it since rest and its predictions are buffered per sample. With the rows
// matched to the predictions by sequence number the fresh model takes the running base and finds the 20 nm, as
// with no sample lost. Across a controller restart that reuses numbers inside the window, of equal numbers the
// prediction on the row's stamp is taken.
TEST(SnapshotReload, AnotherAxisLosingASampleStillHandsOverTheRunningBase) {
  const double fs = 11.0, t0 = 1.7e9, window_s = 180.0;
  const std::size_t n_hist = 3000, n_win = 1980, n_after = 1500, lost_at = n_hist + 700;  // n_win: window_s × fs
  const test::PiCreepWalk stage = test::pi_creep_walk(n_hist + n_win + n_after, fs, 20.0);
  const std::vector<double>& v = stage.voltage_v;
  const std::vector<double>& truth = stage.position_nm;
  // the running model on c: the base since the stage's rest, up to the reload; a: 12 nm/V, one sample lost
  models::ModelPtr run_base;
  // restart: the controller restarts its numbering at 0 after the lost sample, 1100 numbers back (a restart to the
  // pairing rule, io/sequence_pairer.h), so the window holds the numbers 399 to 1099 twice
  const auto heard = [&](bool lose, bool restart) {
    compensation::SnapshotBuffer b({window_s, 100000});
    auto running = test::make_pi_creep(fs);
    running->reset(v[0], 0.0);
    for (std::size_t i = 0; i < n_hist + n_win; ++i) {
      const double t = t0 + static_cast<double>(i) / fs;
      const auto seq = static_cast<std::uint32_t>(!restart ? i : i < lost_at ? i + 1100 - lost_at : i - lost_at);
      const double va = 0.5 * v[v.size() - 1 - i];
      if (!(lose && i == lost_at)) {
        b.add_voltage("a", seq, va, t);
        b.add_reading("a", seq, 12.0 * va, true, t);
      }
      b.add_voltage("c", seq, v[i], t);
      b.add_reading("c", seq, truth[i], true, t);
      const models::ModelInput in{v[i], nullptr};
      const double p = running->predict(in);
      running->commit(in, p);
      b.add_prediction("c", seq, p, t);
    }
    run_base = std::move(running);
    return b.take();
  };
  // the augmented model `piezo residual` would write: its offset fitted against the base started at rest on the
  // window (what the window's cold start gives)
  double off = 0.0;
  {
    auto cold = test::make_pi_creep(fs);
    cold->reset(v[n_hist], 0.0);
    for (std::size_t i = n_hist; i < n_hist + n_win; ++i) {
      const models::ModelInput in{v[i], nullptr};
      const double p = cold->predict(in);
      cold->commit(in, p);
      off += (truth[i] - p) / static_cast<double>(n_win);
    }
  }
  // free-run after the reload: the worst |prediction − stage| and the predictions
  const auto after = [&](models::Model& m, std::vector<double>* out) {
    double worst = 0.0;
    for (std::size_t i = n_hist + n_win; i < v.size(); ++i) {
      const models::ModelInput in{v[i], nullptr};
      const double p = m.predict(in);
      m.commit(in, p);
      worst = std::max(worst, std::abs(p - truth[i]));
      if (out) out->push_back(p);
    }
    return worst;
  };

  const compensation::Snapshot whole = heard(false, false);
  ASSERT_TRUE(whole.gaps.empty());
  models::AugmentedModel ref(test::make_pi_creep(fs), {}, off, fs);
  std::string ref_how;
  ASSERT_EQ(compensation::warm_model(ref, "c", whole, run_base.get(), &ref_how), "");
  std::vector<double> ref_after;
  const double ref_worst = after(ref, &ref_after);
  std::cout << "[snapshot reload] no sample lost: " << ref_how << ", worst error after it " << ref_worst << " nm\n";
  EXPECT_LT(ref_worst, 1e-6);

  for (const bool restart : {false, true}) {
    const std::string name = restart ? "one lost on a at a controller restart" : "one lost on a";
    SCOPED_TRACE(name);
    const compensation::Snapshot s = heard(true, restart);
    ASSERT_EQ(s.gaps.size(), 1u);
    EXPECT_EQ(s.gaps[0].axis, "a");
    models::AugmentedModel fresh(test::make_pi_creep(fs), {}, off, fs);
    std::string how;
    ASSERT_EQ(compensation::warm_model(fresh, "c", s, run_base.get(), &how), "");
    std::cout << "[snapshot reload] " << name << ": " << how << "\n";
    EXPECT_NE(how.find("base state from the running model"), std::string::npos) << how;
    EXPECT_NE(how.find("1 of c's " + std::to_string(s.axes.at("c").readings.size()) + " readings have no row"),
              std::string::npos) << how;
    std::vector<double> got_after;
    const double worst = after(fresh, &got_after);
    // warmed from rest over the same window: the window's cold start stays in it
    models::AugmentedModel rest(test::make_pi_creep(fs), {}, off, fs);
    ASSERT_EQ(compensation::warm_model(rest, "c", s), "");
    const double rest_worst = after(rest, nullptr);
    double diff = 0.0;
    for (std::size_t i = 0; i < got_after.size(); ++i) diff = std::max(diff, std::abs(got_after[i] - ref_after[i]));
    std::cout << "[snapshot reload] " << name << ": worst error over " << n_after << " samples after the reload "
              << worst << " nm (largest difference to none lost " << diff << " nm), warmed from rest " << rest_worst
              << " nm\n";
    EXPECT_LT(worst, 1e-6);
    EXPECT_LT(diff, 1e-9) << "one sample lost on another axis changed the reloaded model";
    EXPECT_GT(rest_worst, 1.0) << "the window's cold start should matter in this test";
  }
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

// `piezo residual` finds a stroke gain in a snapshot bag. The simulated device (default physics, a
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
