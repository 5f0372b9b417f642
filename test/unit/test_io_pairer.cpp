// The one pairing rule (io/sequence_pairer.h): lost voltage, lost reading, reordering, controller restart.
#include <gtest/gtest.h>

#include <deque>

#include "piezo_compensation/io/sequence_pairer.h"

using piezo::io::PairedSample;
using piezo::io::PairerOptions;
using piezo::io::SequencePairer;

namespace {

double volt(std::uint32_t s) { return 0.5 * static_cast<double>(s % 1000) + 1.0; }
double pos(std::uint32_t s) { return 10.0 * static_cast<double>(s % 1000); }

void append(std::vector<PairedSample>& all, const std::vector<PairedSample>& more) {
  all.insert(all.end(), more.begin(), more.end());
}

}  // namespace

TEST(SequencePairer, EitherStreamMayComeFirst) {
  SequencePairer p;
  std::vector<PairedSample> out;
  for (std::uint32_t s = 10; s < 20; ++s) {
    if (s % 2) {
      append(out, p.add_voltage(s, volt(s), s * 0.1));
      append(out, p.add_reading(s, pos(s), true, s * 0.1));
    } else {
      append(out, p.add_reading(s, pos(s), true, s * 0.1));
      EXPECT_EQ(p.pending(), 1u);
      append(out, p.add_voltage(s, volt(s), s * 0.1));
    }
  }
  ASSERT_EQ(out.size(), 10u);
  for (std::size_t i = 0; i < out.size(); ++i) {
    EXPECT_EQ(out[i].sequence, 10 + i);
    EXPECT_DOUBLE_EQ(out[i].voltage_v, volt(10 + i));
    EXPECT_DOUBLE_EQ(out[i].position_nm, pos(10 + i));
    EXPECT_TRUE(out[i].measured);
    EXPECT_FALSE(out[i].voltage_lost);
  }
  EXPECT_EQ(p.counters().lost_voltages, 0u);
}

TEST(SequencePairer, LostVoltageShownByNewerReport) {
  SequencePairer p;
  std::vector<PairedSample> out;
  for (std::uint32_t s = 1; s <= 5; ++s) {
    if (s != 3) append(out, p.add_voltage(s, volt(s), s));
    append(out, p.add_reading(s, pos(s), true, s));
    // the reading of 3 waits until report 4 shows report 3 lost
    if (s == 3) {
      EXPECT_EQ(out.size(), 2u);
    }
  }
  ASSERT_EQ(out.size(), 5u);
  EXPECT_TRUE(out[2].voltage_lost);
  EXPECT_DOUBLE_EQ(out[2].voltage_v, volt(2));  // the axis held the last reported voltage
  EXPECT_DOUBLE_EQ(out[2].position_nm, pos(3));
  EXPECT_FALSE(out[3].voltage_lost);
  EXPECT_EQ(p.counters().lost_voltages, 1u);
}

TEST(SequencePairer, LostVoltageAfterMaxPendingReadings) {
  // the voltage stream stops: a reading waits for max_pending newer readings, then takes the held voltage
  PairerOptions o;
  o.max_pending = 3;
  SequencePairer p(o);
  std::vector<PairedSample> out;
  append(out, p.add_voltage(1, volt(1), 1));
  append(out, p.add_reading(1, pos(1), true, 1));
  for (std::uint32_t s = 2; s <= 4; ++s) append(out, p.add_reading(s, pos(s), true, s));
  EXPECT_EQ(out.size(), 1u);
  append(out, p.add_reading(5, pos(5), true, 5));
  ASSERT_EQ(out.size(), 2u);
  EXPECT_EQ(out[1].sequence, 2u);
  EXPECT_TRUE(out[1].voltage_lost);
  EXPECT_DOUBLE_EQ(out[1].voltage_v, volt(1));
  // the late report of 3 still pairs: 3 is pending
  append(out, p.add_voltage(3, volt(3), 3));
  ASSERT_EQ(out.size(), 3u);
  EXPECT_FALSE(out[2].voltage_lost);
  EXPECT_DOUBLE_EQ(out[2].voltage_v, volt(3));
  append(out, p.flush());
  ASSERT_EQ(out.size(), 5u);
  EXPECT_TRUE(out[3].voltage_lost);
  EXPECT_DOUBLE_EQ(out[4].voltage_v, volt(3));
}

TEST(SequencePairer, LostReadingKeepsTheSampleClock) {
  SequencePairer p;
  std::vector<PairedSample> out;
  for (std::uint32_t s = 1; s <= 6; ++s) {
    append(out, p.add_voltage(s, volt(s), s));
    if (s != 3 && s != 4) append(out, p.add_reading(s, pos(s), true, s));
  }
  ASSERT_EQ(out.size(), 6u);
  for (std::uint32_t i = 0; i < 6; ++i) {
    EXPECT_EQ(out[i].sequence, i + 1);
    EXPECT_DOUBLE_EQ(out[i].voltage_v, volt(i + 1));
  }
  EXPECT_TRUE(out[2].reading_lost && out[3].reading_lost);
  EXPECT_FALSE(out[2].measured || out[3].measured);
  EXPECT_TRUE(out[4].measured);
  EXPECT_EQ(p.counters().lost_readings, 2u);
}

TEST(SequencePairer, InvalidReadingIsASampleWithoutMeasurement) {
  SequencePairer p;
  std::vector<PairedSample> out;
  append(out, p.add_voltage(7, volt(7), 7));
  append(out, p.add_reading(7, pos(7), false, 7));
  ASSERT_EQ(out.size(), 1u);
  EXPECT_FALSE(out[0].measured);
  EXPECT_FALSE(out[0].reading_lost);
}

TEST(SequencePairer, ReorderingInsideTheWaitAndLateReadings) {
  SequencePairer p;
  std::vector<PairedSample> out;
  // readings 1, 3, 2 before any report: emitted in sequence order once the reports come
  append(out, p.add_reading(1, pos(1), true, 1));
  append(out, p.add_reading(3, pos(3), true, 3));
  append(out, p.add_reading(2, pos(2), true, 2));
  EXPECT_TRUE(out.empty());
  for (std::uint32_t s = 1; s <= 3; ++s) append(out, p.add_voltage(s, volt(s), s));
  ASSERT_EQ(out.size(), 3u);
  for (std::uint32_t i = 0; i < 3; ++i) {
    EXPECT_EQ(out[i].sequence, i + 1);
    EXPECT_DOUBLE_EQ(out[i].position_nm, pos(i + 1));
    EXPECT_DOUBLE_EQ(out[i].voltage_v, volt(i + 1));
  }
  // a reading older than one already emitted is late: dropped and counted, nothing re-emitted
  EXPECT_TRUE(p.add_reading(2, pos(2), true, 2).empty());
  EXPECT_EQ(p.counters().late_readings, 1u);
  // reports ahead of their readings (voltage stream faster) pair when the readings come
  for (std::uint32_t s = 4; s <= 6; ++s) append(out, p.add_voltage(s, volt(s), s));
  for (std::uint32_t s = 4; s <= 6; ++s) append(out, p.add_reading(s, pos(s), true, s));
  ASSERT_EQ(out.size(), 6u);
  EXPECT_DOUBLE_EQ(out[5].voltage_v, volt(6));
  EXPECT_EQ(p.counters().lost_voltages, 0u);
}

TEST(SequencePairer, ControllerRestartReadingFirst) {
  SequencePairer p;
  std::vector<PairedSample> out;
  for (std::uint32_t s = 5000; s < 5004; ++s) {
    append(out, p.add_voltage(s, volt(s), s));
    append(out, p.add_reading(s, pos(s), true, s));
  }
  append(out, p.add_reading(5004, pos(5004), true, 5004));  // its report never comes: the controller restarts
  // new numbering: the reading of 0 before its report; old reports must not pair with it
  append(out, p.add_reading(0, 123.0, true, 6000));
  append(out, p.add_voltage(0, 7.0, 6000));
  append(out, p.add_voltage(1, 8.0, 6001));
  append(out, p.add_reading(1, 124.0, true, 6001));
  ASSERT_EQ(out.size(), 7u);
  EXPECT_EQ(out[4].sequence, 5004u);
  EXPECT_TRUE(out[4].voltage_lost);
  EXPECT_DOUBLE_EQ(out[4].voltage_v, volt(5003));
  EXPECT_EQ(out[5].sequence, 0u);
  EXPECT_DOUBLE_EQ(out[5].voltage_v, 7.0);
  EXPECT_DOUBLE_EQ(out[5].position_nm, 123.0);
  EXPECT_FALSE(out[5].voltage_lost);
  EXPECT_DOUBLE_EQ(out[6].voltage_v, 8.0);
  EXPECT_EQ(p.counters().restarts, 1u);
  EXPECT_EQ(p.counters().lost_readings, 0u);  // a restart is no gap
}

TEST(SequencePairer, ControllerRestartReportFirst) {
  SequencePairer p;
  std::vector<PairedSample> out;
  for (std::uint32_t s = 9000; s < 9003; ++s) {
    append(out, p.add_voltage(s, volt(s), s));
    append(out, p.add_reading(s, pos(s), true, s));
  }
  append(out, p.add_voltage(0, 7.0, 1));
  append(out, p.add_reading(0, 123.0, true, 1));
  ASSERT_EQ(out.size(), 4u);
  EXPECT_EQ(out[3].sequence, 0u);
  EXPECT_DOUBLE_EQ(out[3].voltage_v, 7.0);
  EXPECT_FALSE(out[3].voltage_lost);
  EXPECT_EQ(p.counters().restarts, 1u);
}

TEST(SequencePairer, WrapsAroundTheCounter) {
  SequencePairer p;
  std::vector<PairedSample> out;
  for (std::uint32_t s = 0xFFFFFFFEu, i = 0; i < 4; ++s, ++i) {
    append(out, p.add_reading(s, 1.0 * i, true, i));
    append(out, p.add_voltage(s, 2.0 * i, i));
  }
  ASSERT_EQ(out.size(), 4u);
  EXPECT_EQ(out[2].sequence, 0u);
  EXPECT_DOUBLE_EQ(out[3].voltage_v, 6.0);
  EXPECT_EQ(p.counters().restarts, 0u);
}

TEST(SequencePairer, TruthWaitsAndLostTruthIsSubstituted) {
  PairerOptions o;
  o.with_truth = true;
  SequencePairer p(o);
  std::vector<PairedSample> out;
  append(out, p.add_voltage(1, 1.0, 1));
  append(out, p.add_reading(1, 10.0, true, 1));
  EXPECT_TRUE(out.empty());  // the truth is on its way
  append(out, p.add_truth(1, 11.0, 1));
  ASSERT_EQ(out.size(), 1u);
  EXPECT_DOUBLE_EQ(out[0].truth_nm, 11.0);
  append(out, p.add_voltage(2, 2.0, 2));
  append(out, p.add_reading(2, 20.0, true, 2));
  append(out, p.add_truth(3, 31.0, 3));  // truth 2 lost
  ASSERT_EQ(out.size(), 2u);
  EXPECT_TRUE(out[1].truth_lost);
  EXPECT_DOUBLE_EQ(out[1].truth_nm, 11.0);
  EXPECT_EQ(p.counters().lost_truths, 1u);
}

TEST(MatchReport, RecorderStyleQueue) {
  struct Msg {
    std::uint32_t sequence;
    double v;
  };
  std::deque<Msg> q{{4, 0.4}, {5, 0.5}, {7, 0.7}};
  const Msg* m = nullptr;
  const auto seq = [](const Msg& x) { return x.sequence; };
  EXPECT_EQ(piezo::io::match_report(q, 5, false, seq, &m), piezo::io::ReportMatch::kFound);
  EXPECT_DOUBLE_EQ(m->v, 0.5);
  EXPECT_EQ(piezo::io::match_report(q, 6, false, seq, &m), piezo::io::ReportMatch::kLost);
  EXPECT_DOUBLE_EQ(m->v, 0.5);
  EXPECT_EQ(piezo::io::match_report(q, 8, false, seq, &m), piezo::io::ReportMatch::kWaiting);
  EXPECT_EQ(m, nullptr);
  EXPECT_EQ(piezo::io::match_report(q, 8, true, seq, &m), piezo::io::ReportMatch::kLost);
  EXPECT_DOUBLE_EQ(m->v, 0.7);
}
