// tracking_trim.test (live): piezo_demo's tracking_trim scenario on a stage whose hysteresis, creep and gain differ
// from the model's, scored by the demo itself (compensation/demo_scenario.h: |true − intended| during the moves and in
// the holds from hold_score_from_s, the tracking trim off and then on, the hold trim on in both), and the
// predictor's commands on /mm1/c/command checked one by one against the predictor's and the driver's voltage limits.
// Asserted: the moves' mean with the tracking trim at most max_move_ratio of the mean without; the holds' max and
// mean with it at most hold_margin_nm above the hold trim's alone; the tracking trim never active in the pass
// without it and active in the pass with it; no command and no applied voltage outside the limits.
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <mutex>
#include <sstream>
#include <string>

#include "piezo_compensation/VoltageCommand.h"
#include "wall_wait.h"

namespace {

std::string g_prefix, g_demo_node = "/mm1/piezo_demo";
double g_max_move_ratio = 0.25, g_hold_margin_nm = 0.5;
bool g_keep = false;

constexpr double kRunPatienceS = 400.0;  // the whole lock-step run (~30 s idle), slowed down by a loaded host
constexpr double kPatienceS = 60.0;

struct Commands {
  std::size_t n = 0, non_finite = 0;
  double min_v = INFINITY, max_v = -INFINITY;
};

// The tighter of the predictor's and the driver's limits, as the nodes read them.
void voltage_limits(double& lo_v, double& hi_v) {
  ros::NodeHandle nh;
  double p_lo = NAN, p_hi = NAN, d_lo = NAN, d_hi = NAN;
  ASSERT_TRUE(nh.getParam("/mm1/predictor/voltage_min_v", p_lo) && nh.getParam("/mm1/predictor/voltage_max_v", p_hi));
  ASSERT_TRUE(nh.getParam("/mm1/mm3e_driver/min_voltage_v", d_lo) && nh.getParam("/mm1/mm3e_driver/max_voltage_v", d_hi));
  lo_v = std::max(p_lo, d_lo), hi_v = std::min(p_hi, d_hi);
}

void print_table(const YAML::Node& j) {
  const auto row = [&](const char* name, const std::string& p) {
    std::printf("tracking_trim: | %-28s | %8.2f | %8.2f | %8.2f | %8.2f | %6d | %6d |\n", name,
                j[p + "move_max_nm"].as<double>(), j[p + "move_mean_nm"].as<double>(), j[p + "hold_max_nm"].as<double>(),
                j[p + "hold_mean_nm"].as<double>(), j[p + "move_samples"].as<int>(), j[p + "hold_samples"].as<int>());
  };
  std::printf("tracking_trim: |true - intended| [nm], moves (ramps + each hold's first %.0f s) and holds (from %.0f s)\n",
              j["settle_s"].as<double>(), j["hold_score_from_s"].as<double>());
  std::printf("tracking_trim: | %-28s | move max | mov mean | hold max | hld mean | moves  | holds  |\n", "pass");
  row("hold trim alone (ff moves)", "tracking_off_");
  row("hold trim + tracking trim", "tracking_on_");
}

TEST(TrackingTrim, ClosedLoopThroughRosQuartersTheMoveError) {
  ASSERT_FALSE(g_prefix.empty());
  double lo_v = NAN, hi_v = NAN;
  voltage_limits(lo_v, hi_v);
  ros::NodeHandle nh;
  std::mutex mu;
  Commands cmd;
  std::size_t outside = 0;
  auto sub = nh.subscribe<piezo_compensation::VoltageCommand>(
      "/mm1/c/command", 20000,
      [&](const piezo_compensation::VoltageCommand::ConstPtr& m) {
        std::lock_guard<std::mutex> lock(mu);
        ++cmd.n;
        if (!std::isfinite(m->voltage)) {
          ++cmd.non_finite;
          return;
        }
        cmd.min_v = std::min(cmd.min_v, m->voltage), cmd.max_v = std::max(cmd.max_v, m->voltage);
        if (m->voltage < lo_v || m->voltage > hi_v) {
          if (++outside <= 5) ADD_FAILURE() << "command " << m->voltage << " V outside [" << lo_v << ", " << hi_v << "] V";
        }
      },
      ros::VoidConstPtr(), ros::TransportHints().tcpNoDelay());

  const std::string json = g_prefix + ".json";
  const ros::WallTime start = ros::WallTime::now();
  YAML::Node j;
  ASSERT_TRUE(piezo::test::wall_wait(
      [&] { return piezo::test::load_complete_yaml(json, {"tracking_on_applied_max_v"}, j); }, kRunPatienceS, 0.05, true))
      << json << " not written within " << kRunPatienceS << " s";
  const double wall_s = (ros::WallTime::now() - start).toSec();
  if (!piezo::test::wall_wait([&] { return !piezo::test::node_registered(g_demo_node); }, kPatienceS, 0.05, true))
    std::printf("tracking_trim: %s still registered %.0f s after its JSON\n", g_demo_node.c_str(), kPatienceS);
  piezo::test::wall_wait([] { return false; }, 1.0, 0.05, true);  // the last commands in the queue
  sub.shutdown();
  std::printf("tracking_trim: %s\n", [&] { std::ostringstream o; o << j; return o.str(); }().c_str());
  print_table(j);

  const double off_move = j["tracking_off_move_mean_nm"].as<double>(), on_move = j["tracking_on_move_mean_nm"].as<double>();
  const double off_hold_max = j["tracking_off_hold_max_nm"].as<double>(), on_hold_max = j["tracking_on_hold_max_nm"].as<double>();
  const double off_hold = j["tracking_off_hold_mean_nm"].as<double>(), on_hold = j["tracking_on_hold_mean_nm"].as<double>();
  std::printf("tracking_trim: moves mean %.2f -> %.2f nm (%.2f of it, limit %.2f); holds max %.2f -> %.2f nm, mean "
              "%.2f -> %.2f nm (margin %.2f nm); %zu commands in [%.3f, %.3f] V (limits [%.1f, %.1f] V); %.0f s wall "
              "from the checker's start\n",
              off_move, on_move, on_move / off_move, g_max_move_ratio, off_hold_max, on_hold_max, off_hold, on_hold,
              g_hold_margin_nm, cmd.n, cmd.min_v, cmd.max_v, lo_v, hi_v, wall_s);
  // the figures also in the test's XML result
  for (const char* k : {"tracking_off_move_mean_nm", "tracking_on_move_mean_nm", "tracking_off_move_max_nm",
                        "tracking_on_move_max_nm", "tracking_off_hold_mean_nm", "tracking_on_hold_mean_nm",
                        "tracking_off_hold_max_nm", "tracking_on_hold_max_nm"})
    testing::Test::RecordProperty(k, j[k].as<std::string>());
  EXPECT_TRUE(j["lockstep"].as<bool>());
  EXPECT_GT(j["tracking_off_move_samples"].as<int>(), 1000);
  EXPECT_EQ(j["tracking_on_move_samples"].as<int>(), j["tracking_off_move_samples"].as<int>());
  EXPECT_GT(j["tracking_off_hold_samples"].as<int>(), 5000);
  EXPECT_EQ(j["tracking_on_hold_samples"].as<int>(), j["tracking_off_hold_samples"].as<int>());
  EXPECT_EQ(j["tracking_off_active_samples"].as<int>(), 0) << "the pass without the tracking trim must not track";
  EXPECT_GT(j["tracking_on_active_samples"].as<int>(), 500) << "the tracking trim never acted";
  EXPECT_LE(on_move, g_max_move_ratio * off_move);
  EXPECT_LE(on_hold_max, off_hold_max + g_hold_margin_nm);
  EXPECT_LE(on_hold, off_hold + g_hold_margin_nm);
  for (const char* p : {"tracking_off_", "tracking_on_"}) {
    EXPECT_GE(j[std::string(p) + "applied_min_v"].as<double>(), lo_v) << p;
    EXPECT_LE(j[std::string(p) + "applied_max_v"].as<double>(), hi_v) << p;
  }
  std::lock_guard<std::mutex> lock(mu);
  EXPECT_GT(cmd.n, 40000u) << "the run's commands";
  EXPECT_EQ(cmd.non_finite, 0u);
  EXPECT_EQ(outside, 0u);
  if (!HasFailure() && !g_keep) {
    std::remove(json.c_str());
    std::remove((g_prefix + ".csv").c_str());
  } else {
    std::printf("tracking_trim: kept %s.{csv,json}\n", g_prefix.c_str());
  }
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "tracking_trim_check");
  ros::NodeHandle p("~");
  p.getParam("out_prefix", g_prefix);
  p.getParam("max_move_ratio", g_max_move_ratio);
  p.getParam("hold_margin_nm", g_hold_margin_nm);
  p.getParam("keep", g_keep);
  p.getParam("demo_node", g_demo_node);
  return RUN_ALL_TESTS();
}
