// demo_lockstep.test: the lock-step demo's sawtooth, scored by piezo_demo itself (compensation/demo_scenario.h).
// Every uncompensated sample must carry the intent of its own step (no command late: the demo paces the device),
// and the compensated pass must meet the target while the uncompensated one shows the hysteresis.
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <yaml-cpp/yaml.h>

#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>

namespace {

std::string g_prefix;

bool exists(const std::string& path) { return std::ifstream(path).good(); }

TEST(DemoLockstep, SawtoothInStepAndCompensated) {
  ASSERT_FALSE(g_prefix.empty());
  const std::string json = g_prefix + ".json";
  const ros::WallTime deadline = ros::WallTime::now() + ros::WallDuration(80.0);
  while (!exists(json) && ros::WallTime::now() < deadline) ros::WallDuration(0.2).sleep();
  ASSERT_TRUE(exists(json)) << json << " not written within 80 s";
  ros::WallDuration(0.5).sleep();  // the demo writes the CSV before the JSON; let the JSON close
  const YAML::Node j = YAML::LoadFile(json);
  std::ifstream csv(g_prefix + ".csv");
  std::size_t lines = 0;
  for (std::string l; std::getline(csv, l);) ++lines;
  std::printf("demo_lockstep: %s\n", [&] { std::ostringstream o; o << j; return o.str(); }().c_str());
  EXPECT_TRUE(j["lockstep"].as<bool>());
  EXPECT_EQ(lines, 3858u + 1u);  // one row per step (11 Hz × 2 × 175.4 s), header
  EXPECT_EQ(j["uncompensated_saw_samples"].as<int>(), 1544);
  EXPECT_EQ(j["uncompensated_late_samples"].as<int>(), 0);
  EXPECT_GT(j["uncompensated_max_pct"].as<double>(), 4.0);  // measured 6.47 %
  EXPECT_LT(j["compensated_max_pct"].as<double>(), 1.5);    // measured 0.72 %
  std::remove(json.c_str());
  std::remove((g_prefix + ".csv").c_str());
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "demo_lockstep_check");
  ros::NodeHandle("~").getParam("out_prefix", g_prefix);
  return RUN_ALL_TESTS();
}
