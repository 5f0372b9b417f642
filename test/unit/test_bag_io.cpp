// Bag reader/writer: round trips of every column, namespaces, and one clear error for each malformed bag.
#include <gtest/gtest.h>
#include <piezo_compensation/AxisVoltage.h>
#include <piezo_compensation/EncoderPosition.h>
#include <rosbag/bag.h>
#include <std_msgs/Float64.h>

#include <cmath>
#include <fstream>
#include <iostream>

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
