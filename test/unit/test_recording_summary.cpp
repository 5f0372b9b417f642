#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "piezo_compensation/analysis/evaluation/recording_summary.h"

using piezo::analysis::analyze_sequences;
using piezo::analysis::check_continuity;
using piezo::analysis::compare_voltages;
using piezo::analysis::estimate_noise;
using piezo::analysis::SequenceTracker;
using piezo::io::DataError;
using piezo::io::Dataset;
using Arrival = SequenceTracker::Arrival;

TEST(RecordingSequences, InOrderStreamHasNoProblems) {
  std::vector<std::uint32_t> s;
  for (std::uint32_t i = 5; i < 1005; ++i) s.push_back(i);
  const auto r = analyze_sequences("c", s);
  EXPECT_EQ(r.received, 1000u);
  EXPECT_EQ(r.dropped, 0u);
  EXPECT_EQ(r.out_of_order, 0u);
  EXPECT_EQ(r.duplicates, 0u);
  EXPECT_TRUE(r.gaps.empty());
}

TEST(RecordingSequences, DropsAreListedAsGaps) {
  const auto r = analyze_sequences("a", {1, 2, 3, 7, 8, 10});
  EXPECT_EQ(r.dropped, 4u);  // 4, 5, 6, 9
  ASSERT_EQ(r.gaps.size(), 2u);
  EXPECT_EQ(r.gaps[0].first_missing, 4u);
  EXPECT_EQ(r.gaps[0].count, 3u);
  EXPECT_EQ(r.gaps[1].first_missing, 9u);
  EXPECT_EQ(r.gaps[1].count, 1u);
}

TEST(RecordingSequences, LateArrivalIsOutOfOrderNotDropped) {
  SequenceTracker t;
  EXPECT_EQ(t.add(10), Arrival::kFirst);
  EXPECT_EQ(t.add(11), Arrival::kInOrder);
  EXPECT_EQ(t.add(13), Arrival::kGap);
  EXPECT_EQ(t.dropped(), 1u);
  EXPECT_EQ(t.add(12), Arrival::kLate);
  EXPECT_EQ(t.dropped(), 0u);
  EXPECT_EQ(t.out_of_order(), 1u);
  EXPECT_EQ(t.add(12), Arrival::kDuplicate);
  EXPECT_EQ(t.add(11), Arrival::kDuplicate);
  EXPECT_EQ(t.duplicates(), 2u);
  EXPECT_TRUE(t.gaps().empty());
}

TEST(RecordingSequences, PartlyFilledGapIsSplit) {
  const auto r = analyze_sequences("b", {0, 6, 3});
  EXPECT_EQ(r.dropped, 4u);
  EXPECT_EQ(r.out_of_order, 1u);
  ASSERT_EQ(r.gaps.size(), 2u);
  EXPECT_EQ(r.gaps[0].first_missing, 1u);
  EXPECT_EQ(r.gaps[0].count, 2u);
  EXPECT_EQ(r.gaps[1].first_missing, 4u);
  EXPECT_EQ(r.gaps[1].count, 2u);
}

TEST(RecordingSequences, WrapAroundIsContinuous) {
  const auto r = analyze_sequences("c", {0xFFFFFFFEu, 0xFFFFFFFFu, 0u, 1u, 3u});
  EXPECT_EQ(r.dropped, 1u);
  EXPECT_EQ(r.duplicates, 0u);
  EXPECT_EQ(r.restarts, 0u);
  ASSERT_EQ(r.gaps.size(), 1u);
  EXPECT_EQ(r.gaps[0].first_missing, 2u);
}

TEST(RecordingSequences, GapAcrossWrap) {
  const auto r = analyze_sequences("c", {0xFFFFFFFEu, 2u});
  EXPECT_EQ(r.dropped, 3u);  // 0xFFFFFFFF, 0, 1
  ASSERT_EQ(r.gaps.size(), 1u);
  EXPECT_EQ(r.gaps[0].first_missing, 0xFFFFFFFFu);
  EXPECT_EQ(r.gaps[0].count, 3u);
}

TEST(RecordingSequences, CounterRestartIsNotReordering) {
  const auto r = analyze_sequences("c", {500000, 500001, 0, 1, 2});
  EXPECT_EQ(r.restarts, 1u);
  EXPECT_EQ(r.out_of_order, 0u);
  EXPECT_EQ(r.duplicates, 0u);
  EXPECT_EQ(r.dropped, 0u);
}

TEST(RecordingSequences, OldGapsStayListedOutsideTheLateWindow) {
  SequenceTracker t(100000, 16);
  t.add(0);
  t.add(2);  // 1 missing
  for (std::uint32_t i = 3; i < 100; ++i) t.add(i);
  EXPECT_EQ(t.add(1), Arrival::kDuplicate);  // too late to be recognised as the missing one
  EXPECT_EQ(t.dropped(), 1u);
  ASSERT_EQ(t.gaps().size(), 1u);
  EXPECT_EQ(t.gaps()[0].first_missing, 1u);
  // a gap larger than the window is still counted in full
  t.add(1099);
  EXPECT_EQ(t.dropped(), 1u + 999u);  // 100 .. 1098
  std::uint64_t listed = 0;
  for (const auto& g : t.gaps()) listed += g.count;
  EXPECT_EQ(listed, 1000u);
}

TEST(RecordingContinuity, FindsLostAndDuplicatedSamples) {
  std::vector<double> t;
  for (int i = 0; i < 100; ++i)
    if (i != 40 && i != 41) t.push_back(i / 11.0);
  t.insert(t.begin() + 70, t[69]);  // duplicate row
  const auto r = check_continuity(t);
  EXPECT_NEAR(r.period_s, 1 / 11.0, 1e-9);
  EXPECT_EQ(r.lost_samples, 2u);
  EXPECT_EQ(r.duplicated_samples, 1u);
  ASSERT_EQ(r.problem_rows.size(), 2u);
  EXPECT_EQ(r.problem_rows[0], 40u);
  EXPECT_EQ(r.problem_rows[1], 70u);
}

namespace {
// A noise-protocol-like data set: windows at the five study voltages, with settle rows in between that must
// not count, a slow creep trend inside each window, Gaussian noise of sigma_nm and 20 nm quantisation.
Dataset noise_data(double sigma_nm, std::uint64_t seed, bool quantise) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> noise(0.0, sigma_nm);
  Dataset d;
  auto& c = d.add_axis("c");
  const double rate = 11.0;
  std::size_t i = 0;
  int seg = 0;
  for (double v : {-80.0, -40.0, 0.0, 40.0, 80.0}) {
    for (int k = 0; k < 50; ++k, ++i) {  // settle: large motion, must be ignored
      d.time_s.push_back(i / rate);
      c.voltage_v.push_back(v);
      c.position_nm.push_back(12.5 * v + 300.0 * std::exp(-k / 10.0));
      d.segment.push_back(seg);
      d.phase.push_back(2);
    }
    for (int k = 0; k < 220; ++k, ++i) {
      d.time_s.push_back(i / rate);
      c.voltage_v.push_back(v);
      double x = 12.5 * v + 0.5 * k / rate + noise(rng);  // 0.5 nm/s creep left over
      if (quantise) x = 20.0 * std::round(x / 20.0);
      c.position_nm.push_back(x);
      d.segment.push_back(seg);
      d.phase.push_back(3);
    }
    ++seg;
  }
  return d;
}
}  // namespace

TEST(RecordingNoise, RecoversSigmaOfTheRecordWindows) {
  const Dataset d = noise_data(20.79, 7, false);
  const auto est = estimate_noise(d);
  ASSERT_EQ(est.size(), 1u);
  EXPECT_EQ(est[0].samples, 5u * 220u);
  ASSERT_EQ(est[0].window_sigma_nm.size(), 5u);
  EXPECT_NEAR(est[0].window_voltage_v[0], -80.0, 1e-9);
  EXPECT_NEAR(est[0].sigma_nm, 20.79, 0.05 * 20.79);
}

TEST(RecordingNoise, ScalesWithTheNoise) {
  EXPECT_NEAR(estimate_noise(noise_data(5.0, 3, false))[0].sigma_nm, 5.0, 0.3);
  EXPECT_NEAR(estimate_noise(noise_data(40.0, 3, false))[0].sigma_nm, 40.0, 2.0);
}

TEST(RecordingNoise, QuantisationAddsItsOwnVariance) {
  // 20 nm steps add about q^2/12 of variance: sqrt(20.79^2 + 400/12) = 21.57 nm
  const double s = estimate_noise(noise_data(20.79, 11, true))[0].sigma_nm;
  EXPECT_NEAR(s, std::sqrt(20.79 * 20.79 + 400.0 / 12.0), 1.0);
}

TEST(RecordingNoise, ClearErrorWithoutRecordWindows) {
  Dataset d;
  d.source = "x.csv";
  d.time_s = {0, 1, 2};
  d.add_axis("c");
  try {
    estimate_noise(d);
    FAIL() << "no error";
  } catch (const DataError& e) {
    EXPECT_NE(std::string(e.what()).find("x.csv: no phase column"), std::string::npos) << e.what();
  }
  d.phase = {0, 0, 0};
  d.segment = {0, 0, 0};
  EXPECT_THROW(estimate_noise(d), DataError);
}

TEST(RecordingVoltages, CountsMismatchesAgainstTheProgram) {
  Dataset prog;
  prog.time_s = {0, 1, 2, 3};
  prog.add_axis("a").voltage_v = {0, 1, 2, 3};
  Dataset rec = prog;
  auto m = compare_voltages(rec, prog, 1e-6);
  EXPECT_EQ(m.compared, 4u);
  EXPECT_EQ(m.mismatched, 0u);
  rec.axis("a").voltage_v[2] = 2.5;
  m = compare_voltages(rec, prog, 1e-6);
  EXPECT_EQ(m.mismatched, 1u);
  EXPECT_EQ(m.first_mismatch, 2u);
  EXPECT_DOUBLE_EQ(m.max_abs_error_v, 0.5);
}

TEST(RecordingSummaryText, NamesTheProblems) {
  Dataset d = noise_data(20.79, 5, false);
  d.time_s.erase(d.time_s.begin() + 10);  // keep sizes consistent: drop a full row
  for (auto& a : d.axes) {
    a.voltage_v.erase(a.voltage_v.begin() + 10);
    a.position_nm.erase(a.position_nm.begin() + 10);
  }
  d.segment.erase(d.segment.begin() + 10);
  d.phase.erase(d.phase.begin() + 10);
  auto s = piezo::analysis::summarize(d, "noise");
  s.sequences.push_back(analyze_sequences("c", {1, 2, 5}));
  const std::string text = piezo::analysis::format_summary(s);
  EXPECT_NE(text.find("protocol noise"), std::string::npos) << text;
  EXPECT_NE(text.find("1 lost"), std::string::npos) << text;
  EXPECT_NE(text.find("missing sequence 3 .. 4 (2)"), std::string::npos) << text;
  EXPECT_NE(text.find("encoder noise c: sigma"), std::string::npos) << text;
  ASSERT_EQ(s.noise.size(), 1u);
}

TEST(RecordingNoise, FlagsSigmaBelowTheEncoderStep) {
  Dataset d = noise_data(20.79, 13, false);
  auto& c = d.axis("c");
  for (std::size_t i = 0; i < d.size(); ++i)  // a/b-axis encoder, readings next to a step: 0 or 250 nm
    c.position_nm[i] = 250.0 * std::round((c.position_nm[i] - 12.5 * c.voltage_v[i] + 125.0) / 250.0);
  const auto est = estimate_noise(d);
  EXPECT_NEAR(est[0].resolution_nm, 250.0, 1e-9);
  EXPECT_TRUE(est[0].below_resolution());
  for (auto& x : c.position_nm) x = 500.0;  // nothing moves at all: no step seen, no measurable noise
  EXPECT_TRUE(estimate_noise(d)[0].below_resolution());
  const auto fine = estimate_noise(noise_data(20.79, 13, true));
  EXPECT_NEAR(fine[0].resolution_nm, 20.0, 1e-9);
  EXPECT_FALSE(fine[0].below_resolution());
}
