// Bag reader/writer: round trips of every column, namespaces, and one clear error for each malformed bag.
#include <gtest/gtest.h>
#include <piezo_compensation/AxisVoltage.h>
#include <piezo_compensation/EncoderPosition.h>
#include <rosbag/bag.h>
#include <std_msgs/Float64.h>

#include <cmath>
#include <fstream>
#include <iostream>
#include <set>

#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"

using namespace piezo;

namespace {

std::string tmp(const std::string& name) { return ::testing::TempDir() + name; }

io::Dataset simulated(bool thermal) {
  auto cfg = sim::default_simulator_config();
  if (thermal) sim::enable_effect(cfg, "thermal_drift");
  auto p = protocols::make_protocol("creep", YAML::Load("{scenarios: 2, history_s: 100, hold_s: 60, "
                                                        "pre_approach_s: 10, approach_max_s: 20}"),
                                    11.0, 3);
  sim::ManipulatorSimulator s(cfg, 3);
  return s.run(p->program());
}

std::string error_of(const std::string& path, const ros_io::BagOptions& o = {}) {
  try {
    ros_io::read_bag(path, o);
  } catch (const io::DataError& e) {
    return e.what();
  }
  return "";
}

void expect_same(const io::Dataset& a, const io::Dataset& b) {
  ASSERT_EQ(a.size(), b.size());
  for (std::size_t i = 0; i < a.size(); ++i) ASSERT_NEAR(a.time_s[i], b.time_s[i], 1e-8) << i;
  ASSERT_EQ(a.axes.size(), b.axes.size());
  for (std::size_t k = 0; k < a.axes.size(); ++k) {
    ASSERT_EQ(a.axes[k].name, b.axes[k].name);
    ASSERT_EQ(a.axes[k].has_truth(), b.axes[k].has_truth());
    for (std::size_t i = 0; i < a.size(); ++i) {
      ASSERT_EQ(a.axes[k].voltage_v[i], b.axes[k].voltage_v[i]);
      ASSERT_NEAR(a.axes[k].position_nm[i], b.axes[k].position_nm[i], 1e-6);
      if (a.axes[k].has_truth()) {
        ASSERT_NEAR(a.axes[k].true_position_nm[i], b.axes[k].true_position_nm[i], 1e-6);
      }
    }
  }
  ASSERT_EQ(a.aux.size(), b.aux.size());
  for (std::size_t j = 0; j < a.aux.size(); ++j) {
    EXPECT_EQ(a.aux[j].name, b.aux[j].name);
    EXPECT_EQ(a.aux[j].values, b.aux[j].values);
  }
  EXPECT_EQ(a.segment, b.segment);
  EXPECT_EQ(a.phase, b.phase);
}

// A driver-like two-axis bag: per axis a voltage report `report_lead_s` before its reading (< 0: after it), axis c's clock `c_offset_s`
// after axis a's; the samples whose number is in `lost_a` / `lost_c` (reading and report) are missing on that
// axis; `c_reading_only` loses only c's reading of those numbers (its report arrives). Sample i has number
// 500 + i on a, c_first_sequence + i on c.
std::string two_axis_bag(const std::string& name, std::uint32_t n, std::set<std::uint32_t> lost_a,
                         std::set<std::uint32_t> lost_c, double c_offset_s = 0.002, bool c_reading_only = false,
                         std::uint32_t c_first_sequence = 500, double report_lead_s = 0.01) {
  const std::string path = tmp(name);
  rosbag::Bag bag(path, rosbag::bagmode::Write);
  for (std::uint32_t i = 0; i < n; ++i) {
    for (const char* axis : {"a", "c"}) {
      const bool c = axis[0] == 'c';
      const bool lost = (c ? lost_c : lost_a).count(i) > 0;
      const ros::Time t(1000.0 + i / 11.0 + (c ? c_offset_s : 0.0));
      piezo_compensation::AxisVoltage v;
      v.header.stamp = ros::Time(t.toSec() - report_lead_s);
      v.axis = axis;
      v.sequence = (c ? c_first_sequence : 500) + i;
      v.voltage = (c ? 1000.0 : 0.0) + i;  // the sample's number in every value: a fill shows
      if (!lost || (c && c_reading_only)) bag.write(std::string("/mm1/") + axis + "/voltage", v.header.stamp, v);
      piezo_compensation::EncoderPosition e;
      e.header.stamp = t;
      e.axis = axis;
      e.sequence = (c ? c_first_sequence : 500) + i;
      e.position = ((c ? 1000.0 : 0.0) + i) * 1e-9;
      e.valid = true;
      if (!lost) bag.write(std::string("/mm1/") + axis + "/encoder", t, e);
    }
  }
  return path;
}

}  // namespace

TEST(BagIo, RoundTripAllColumns) {
  const io::Dataset d = simulated(true);
  ASSERT_NE(d.find_aux("temperature_c"), nullptr);
  ros_io::write_data(tmp("rt.bag"), d);
  const io::Dataset back = ros_io::read_data(tmp("rt.bag"));
  expect_same(d, back);
  EXPECT_NEAR(back.sample_rate_hz(), 11.0, 1e-6);
  // The same data through CSV agree with the bag.
  ros_io::write_data(tmp("rt.csv"), d);
  expect_same(ros_io::read_data(tmp("rt.csv")), back);
}

TEST(BagIo, NamespacesAndSubsetsOfAxes) {
  io::Dataset d = simulated(false);
  io::Dataset only_c;
  only_c.time_s = d.time_s;
  only_c.axes.push_back(d.axis("c"));
  ros_io::write_bag(tmp("ns.bag"), only_c, {"/mm2"});
  const io::Dataset auto_ns = ros_io::read_bag(tmp("ns.bag"));
  expect_same(only_c, auto_ns);
  expect_same(only_c, ros_io::read_bag(tmp("ns.bag"), {"/mm2"}));
  EXPECT_NE(error_of(tmp("ns.bag"), {"/mm1"}).find("no encoder messages under namespace '/mm1'"), std::string::npos)
      << error_of(tmp("ns.bag"), {"/mm1"});
}

TEST(BagIo, MatchesBySequenceThenByStamp) {
  // A driver-like bag: voltages arrive slightly before the encoder sample, one voltage message missing.
  const std::string path = tmp("driver.bag");
  {
    rosbag::Bag bag(path, rosbag::bagmode::Write);
    for (std::uint32_t i = 0; i < 20; ++i) {
      const ros::Time t(1000.0 + i / 11.0);
      piezo_compensation::EncoderPosition e;
      e.header.stamp = t;
      e.axis = "c";
      e.sequence = 100 + i;
      e.position = i * 1e-9;
      e.valid = true;
      bag.write("/mm1/c/encoder", t, e);
      if (i == 7) continue;
      piezo_compensation::AxisVoltage v;
      v.header.stamp = t - ros::Duration(0.01);
      v.axis = "c";
      v.sequence = 100 + i;
      v.voltage = 2.0 * i;
      bag.write("/mm1/c/voltage", v.header.stamp, v);
    }
  }
  const io::Dataset d = ros_io::read_bag(path);
  ASSERT_EQ(d.size(), 20u);
  EXPECT_NEAR(d.time_s[0], 1000.0, 1e-6);
  EXPECT_EQ(d.axis("c").voltage_v[5], 10.0);
  EXPECT_EQ(d.axis("c").voltage_v[7], 12.0);  // no seq 107: latest voltage before the sample
  EXPECT_NEAR(d.axis("c").position_nm[19], 19.0, 1e-9);
  EXPECT_FALSE(d.axis("c").has_truth());
  EXPECT_TRUE(d.segment.empty());
}

// Samples missing on one axis are never filled from a neighbour: the rows of the reference axis (a) without
// their sample on c are left out, so the time column has the same gap as when a itself lost them, which every
// offline tool refuses (io::Dataset::sample_period_s). Rows of a bag without gaps read as before.
TEST(BagIo, ASampleMissingOnAnotherAxisIsNotFilled) {
  const std::uint32_t n = 40;
  const auto expect_rows = [&](const io::Dataset& d, const std::set<std::uint32_t>& missing) {
    ASSERT_EQ(d.size(), n - missing.size());
    std::size_t row = 0;
    for (std::uint32_t i = 0; i < n; ++i) {
      if (missing.count(i)) continue;
      SCOPED_TRACE("sample " + std::to_string(i) + ", row " + std::to_string(row));
      ASSERT_NEAR(d.time_s[row], 1000.0 + i / 11.0, 1e-6);
      for (const char* axis : {"a", "c"}) {
        const double own = (axis[0] == 'c' ? 1000.0 : 0.0) + i;
        ASSERT_EQ(d.axis(axis).voltage_v[row], own) << axis;
        ASSERT_NEAR(d.axis(axis).position_nm[row], own, 1e-6) << axis;
      }
      ++row;
    }
  };
  // no gap: every sample, each axis its own (c's clock 2 ms after a's, then 40 ms: under one period; the
  // reports 10 ms before their readings, then 5 ms after)
  for (const auto& [offset, lead] : {std::pair{0.002, 0.01}, std::pair{0.04, 0.01}, std::pair{0.002, -0.005}}) {
    const io::Dataset d = ros_io::read_bag(two_axis_bag("full.bag", n, {}, {}, offset, false, 500, lead));
    expect_rows(d, {});
    EXPECT_NEAR(d.sample_period_s(), 1.0 / 11.0, 1e-9);
  }
  // 3 samples lost on a: no rows for them, the gap stays in the time column; the offline tools step over it as one
  // sample, and the reader's notes say where and who
  auto notes_of = [&](const std::string& path) {
    std::vector<std::string> notes;
    const io::Dataset d = ros_io::read_data(path, &notes);
    const io::TimeBase tb = io::time_base(d.time_s);
    EXPECT_EQ(tb.late_steps, 1u);
    EXPECT_NEAR(tb.late_s, 3.0 / 11.0, 1e-3);
    EXPECT_NEAR(d.sample_period_s(), 1.0 / 11.0, 1e-6);
    return notes;
  };
  {
    const io::Dataset d = ros_io::read_bag(two_axis_bag("gap_a.bag", n, {20, 21, 22}, {}));
    expect_rows(d, {20, 21, 22});
    const auto notes = notes_of(tmp("gap_a.bag"));
    ASSERT_EQ(notes.size(), 1u);
    std::cout << "[gap on a] read_data: " << notes[0] << "\n";
    EXPECT_NE(notes[0].find("3 sample(s) missing after t = 1001.727273 s (row 21, sequence 519): axis a lost 3;"),
              std::string::npos) << notes[0];
  }
  // the same 3 lost on c only (reading and report, or the reading alone): the same rows, the same note
  for (bool reading_only : {false, true}) {
    SCOPED_TRACE(reading_only ? "c lost its readings" : "c lost its readings and reports");
    const io::Dataset d = ros_io::read_bag(two_axis_bag("gap_c.bag", n, {}, {20, 21, 22}, 0.002, reading_only));
    for (std::size_t row = 18; row < 22 && row < d.size(); ++row)
      std::cout << "[gap on c] row " << row << ": t = " << d.time_s[row] - 1000.0 << " s, a " << d.axis("a").voltage_v[row]
                << " V " << d.axis("a").position_nm[row] << " nm, c " << d.axis("c").voltage_v[row] << " V "
                << d.axis("c").position_nm[row] << " nm\n";
    expect_rows(d, {20, 21, 22});
    const auto notes = notes_of(tmp("gap_c.bag"));
    ASSERT_EQ(notes.size(), 1u);
    std::cout << "[gap on c] read_data: " << notes[0] << "\n";
    EXPECT_NE(notes[0].find("3 sample(s) missing after t = 1001.727273 s (row 21, sequence 519): axis c lost 3;"),
              std::string::npos) << notes[0];
  }
  {  // lost on both, overlapping
    two_axis_bag("gap_ac.bag", n, {20, 21}, {21, 22});
    const auto notes = notes_of(tmp("gap_ac.bag"));
    ASSERT_EQ(notes.size(), 1u);
    EXPECT_NE(notes[0].find("3 sample(s) missing after t = 1001.727273 s (row 21, sequence 519): axis a lost 2, axis c lost 2;"),
              std::string::npos) << notes[0];
  }
  // c starts one sample late and ends one early: the first and last rows have no partner and are cut
  two_axis_bag("edges.bag", n, {}, {0, n - 1});
  for (const io::Dataset& d : {ros_io::read_bag(tmp("edges.bag")), ros_io::read_data(tmp("edges.bag"))}) {
    expect_rows(d, {0, n - 1});
    EXPECT_NEAR(d.sample_period_s(), 1.0 / 11.0, 1e-9);
  }
  expect_rows(ros_io::read_data(two_axis_bag("full.bag", n, {}, {})), {});
  // c numbered apart from a: no stamp is taken for a number
  const std::string e = error_of(two_axis_bag("apart.bag", n, {}, {}, 0.002, false, 9000));
  EXPECT_NE(e.find("axis c: none of its 40 samples has the sequence number of a reading of axis a within one sample "
                   "period (0.090909 s) of it"), std::string::npos) << e;
}

TEST(BagIo, MalformedBagsGiveOneClearError) {
  EXPECT_NE(error_of(tmp("missing.bag")).find("cannot open bag"), std::string::npos);
  std::ofstream(tmp("garbage.bag")) << "this is not a bag\n";
  EXPECT_NE(error_of(tmp("garbage.bag")).find("garbage.bag: cannot open bag"), std::string::npos)
      << error_of(tmp("garbage.bag"));
  {  // truncated: a valid bag cut in half
    ros_io::write_bag(tmp("whole.bag"), simulated(false));
    std::ifstream in(tmp("whole.bag"), std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    std::ofstream(tmp("cut.bag"), std::ios::binary) << bytes.substr(0, bytes.size() / 2);
    const std::string e = error_of(tmp("cut.bag"));
    EXPECT_NE(e.find("cut.bag: "), std::string::npos) << e;
    std::cout << "truncated bag: " << e << "\n";
  }
  {  // wrong type on an encoder topic
    rosbag::Bag bag(tmp("type.bag"), rosbag::bagmode::Write);
    std_msgs::Float64 f;
    f.data = 1.0;
    bag.write("/c/encoder", ros::Time(1.0), f);
    bag.close();
    EXPECT_NE(error_of(tmp("type.bag")).find("expected piezo_compensation/EncoderPosition"), std::string::npos)
        << error_of(tmp("type.bag"));
  }
  {  // encoder without voltage
    rosbag::Bag bag(tmp("novolt.bag"), rosbag::bagmode::Write);
    piezo_compensation::EncoderPosition e;
    e.header.stamp = ros::Time(1.0);
    bag.write("/c/encoder", ros::Time(1.0), e);
    bag.close();
    EXPECT_NE(error_of(tmp("novolt.bag")).find("no /c/voltage"), std::string::npos) << error_of(tmp("novolt.bag"));
  }
  {  // NaN position
    rosbag::Bag bag(tmp("nan.bag"), rosbag::bagmode::Write);
    piezo_compensation::EncoderPosition e;
    e.header.stamp = ros::Time(1.0);
    e.position = NAN;
    bag.write("/c/encoder", ros::Time(1.0), e);
    bag.close();
    EXPECT_NE(error_of(tmp("nan.bag")).find("/c/encoder, message 1: value is not finite"), std::string::npos)
        << error_of(tmp("nan.bag"));
  }
  {  // two manipulators, no namespace chosen
    io::Dataset d = simulated(false);
    rosbag::Bag bag(tmp("two.bag"), rosbag::bagmode::Write);
    for (const char* ns : {"/mm1/c/encoder", "/mm2/c/encoder"}) {
      piezo_compensation::EncoderPosition e;
      e.header.stamp = ros::Time(1.0);
      bag.write(ns, ros::Time(1.0), e);
    }
    bag.close();
    EXPECT_NE(error_of(tmp("two.bag")).find("several manipulators (/mm1, /mm2)"), std::string::npos)
        << error_of(tmp("two.bag"));
  }
  {  // an empty data set cannot be written
    io::Dataset empty;
    EXPECT_THROW(ros_io::write_bag(tmp("empty.bag"), empty), io::DataError);
  }
}
