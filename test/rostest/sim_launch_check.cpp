// sim.launch as a new user starts it: per axis a, b, c the encoder, voltage and prediction topics arrive at the
// encoder rate (on their stamps: the driver's receive times of the device's reports, so the rate is the device's,
// whenever the host lets us read them). ~fallback_axis (if set) must run uncorrected with a status naming ~fallback_file, while its driver
// still reports a held voltage. Every other axis fuses its encoder (the shipped models' estimator: blocks, a and b
// through the 250 nm quantiser): a finite fused position and σ on every prediction, never "model_only". With
// ~check_chart the monitor (piezo_monitor) draws the fused ±1σ band on each of those axes' strip charts.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <string>
#include <vector>

#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/Prediction.h"
#include "visualization_msgs/MarkerArray.h"

namespace {

// Deadline of a wait that takes seconds on an idle host: the waits return as soon as their condition holds.
constexpr double kPatienceS = 60.0;

struct Counts {
  int encoder = 0, voltage = 0, prediction = 0, fallback = 0, model_predicted = 0, fused = 0, model_only = 0;
  double last_fused_nm = NAN, last_measured_nm = NAN, last_predicted_nm = NAN;
  double last_sigma_nm = std::nan("");
  std::string last_status, model;
  std::vector<double> voltages;
  std::vector<double> encoder_stamps, voltage_stamps, prediction_stamps;

  void on_prediction(const piezo_compensation::Prediction& m) {
    ++prediction;
    prediction_stamps.push_back(m.header.stamp.toSec());
    fallback += m.fallback;
    model_predicted += !m.fallback && std::isfinite(m.predicted_position);
    fused += std::isfinite(m.fused_position) && std::isfinite(m.fused_position_sigma) &&
             m.fused_position_sigma > 0.0;
    model_only += m.hold_trim_state == "model_only";
    last_sigma_nm = m.fused_position_sigma * 1e9;
    last_fused_nm = m.fused_position * 1e9;
    last_measured_nm = m.measured_position * 1e9;
    last_predicted_nm = m.predicted_position * 1e9;
    last_status = m.status;
    model = m.model;
  }
};

double median_interval_s(const std::vector<double>& stamps) {
  std::vector<double> d;
  for (std::size_t k = 1; k < stamps.size(); ++k) d.push_back(stamps[k] - stamps[k - 1]);
  if (d.empty()) return std::nan("");
  std::nth_element(d.begin(), d.begin() + d.size() / 2, d.end());
  return d[d.size() / 2];
}

// Messages per second of their stamps over the whole stretch (what the count over a window was, on the stamps).
double mean_rate_hz(const std::vector<double>& stamps) {
  if (stamps.size() < 2 || stamps.back() <= stamps.front()) return 0.0;
  return (stamps.size() - 1) / (stamps.back() - stamps.front());
}

// Rate on the stamps: the median interval is the device's period (a report read late moves one interval, not the
// median), the mean over the stretch says none went missing. Both within 10 % / 20 % of the encoder rate.
void expect_rate(const std::vector<double>& stamps, double rate_hz, const char* what) {
  const double median = median_interval_s(stamps);
  EXPECT_NEAR(median, 1.0 / rate_hz, 0.1 / rate_hz) << what << ": median interval of the stamps, " << stamps.size() << " messages";
  EXPECT_NEAR(mean_rate_hz(stamps), rate_hz, 0.2 * rate_hz) << what << ": messages per second of stamps";
}

// The encoder, voltage and prediction topics of axis a, counted into c[a] while *counting.
void subscribe_axis(ros::NodeHandle& nh, const std::string& a, std::map<std::string, Counts>& c,
                    const bool& counting, std::vector<ros::Subscriber>& subs) {
  subs.push_back(nh.subscribe<piezo_compensation::EncoderPosition>(
      "/mm1/" + a + "/encoder", 50, [&, a](const piezo_compensation::EncoderPosition::ConstPtr& m) {
        if (!counting) return;
        ++c[a].encoder;
        c[a].encoder_stamps.push_back(m->header.stamp.toSec());
      }));
  subs.push_back(nh.subscribe<piezo_compensation::AxisVoltage>(
      "/mm1/" + a + "/voltage", 50, [&, a](const piezo_compensation::AxisVoltage::ConstPtr& m) {
        if (!counting) return;
        ++c[a].voltage;
        c[a].voltages.push_back(m->voltage);
        c[a].voltage_stamps.push_back(m->header.stamp.toSec());
      }));
  subs.push_back(nh.subscribe<piezo_compensation::Prediction>(
      "/mm1/" + a + "/prediction", 50, [&, a](const piezo_compensation::Prediction::ConstPtr& m) {
        if (counting) c[a].on_prediction(*m);
      }));
}

// Waits until every axis predicts (the nodes start and connect).
void wait_until_every_axis_predicts(ros::NodeHandle& nh) {
  const ros::WallTime give_up = ros::WallTime::now() + ros::WallDuration(kPatienceS);
  std::map<std::string, bool> seen;
  std::vector<ros::Subscriber> probes;
  for (const std::string a : {"a", "b", "c"})
    probes.push_back(nh.subscribe<piezo_compensation::Prediction>(
        "/mm1/" + a + "/prediction", 1, [&, a](const auto&) { seen[a] = true; }));
  while (seen.size() < 3 && ros::WallTime::now() < give_up) {
    ros::spinOnce();
    ros::WallDuration(0.02).sleep();
  }
  ASSERT_EQ(seen.size(), 3u) << "not every axis published a prediction within " << kPatienceS << " s";
}

// The broken-model axis: every prediction a fallback naming the file, the voltage held.
void check_fallback_axis(const Counts& k, const std::string& fallback_file) {
  EXPECT_EQ(k.fallback, k.prediction) << "every prediction of the broken-model axis is a fallback";
  EXPECT_NE(k.last_status.find(fallback_file), std::string::npos) << k.last_status;
  // Held: no intent was sent, the driver keeps the start voltage.
  ASSERT_FALSE(k.voltages.empty());
  for (double v : k.voltages) EXPECT_EQ(v, k.voltages.front());
}

// An axis on its shipped model: model predictions, the encoder fused on every one, where the readings put it.
void check_fused_axis(const std::string& a, const Counts& k) {
  EXPECT_EQ(k.fallback, 0) << k.last_status;
  EXPECT_EQ(k.model_predicted, k.prediction) << "predictions from the model";
  EXPECT_NE(k.model.find("mm3e_sim_" + a), std::string::npos) << "shipped default model, got " << k.model;
  EXPECT_EQ(k.fused, k.prediction) << "a fused position with a finite σ on every prediction";
  EXPECT_EQ(k.model_only, 0) << "the shipped model's estimator fuses the encoder";
  std::printf(
      "axis %s: %d predictions fused, last: measured %.1f nm, predicted %.1f nm, fused %.1f nm, 1σ %.1f nm\n",
      a.c_str(), k.fused, k.last_measured_nm, k.last_predicted_nm, k.last_fused_nm, k.last_sigma_nm);
  // The fused position sits where the readings put it: within the reading's cell (half a 250 nm step on a and
  // b) and 3σ of its own and of the noise before the quantiser.
  const double half_cell_nm = a == "c" ? 0.0 : 125.0;
  EXPECT_LE(std::abs(k.last_fused_nm - k.last_measured_nm), half_cell_nm + 3.0 * k.last_sigma_nm + 3.0 * 21.0)
      << "fused far from the readings";
}

TEST(SimLaunch, EveryAxisPublishesAtTheEncoderRate) {
  ros::NodeHandle nh, pnh("~");
  const double rate_hz = pnh.param("encoder_rate_hz", 11.0);
  const std::string fallback_axis = pnh.param<std::string>("fallback_axis", "");
  const std::string fallback_file = pnh.param<std::string>("fallback_file", "");
  std::map<std::string, Counts> c;
  std::vector<ros::Subscriber> subs;
  bool counting = false;
  for (const std::string a : {"a", "b", "c"}) subscribe_axis(nh, a, c, counting, subs);
  // Once every axis predicts, collect 8 s of messages (on their stamps).
  ASSERT_NO_FATAL_FAILURE(wait_until_every_axis_predicts(nh));
  ros::WallDuration(1.0).sleep();
  ros::spinOnce();
  counting = true;
  const double window_s = 8.0;
  const int wanted = static_cast<int>(std::ceil(rate_hz * window_s)) + 1;
  const auto collected = [&] {
    for (const std::string a : {"a", "b", "c"})
      if (c[a].encoder < wanted || c[a].voltage < wanted || c[a].prediction < wanted) return false;
    return true;
  };
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(window_s + kPatienceS);
  while (ros::ok() && !collected() && ros::WallTime::now() < end) {
    ros::spinOnce();
    ros::WallDuration(0.005).sleep();
  }
  counting = false;
  for (const std::string a : {"a", "b", "c"}) {
    const auto& k = c[a];
    SCOPED_TRACE("axis " + a);
    ASSERT_GE(k.encoder, wanted) << "encoder messages";
    ASSERT_GE(k.voltage, wanted) << "voltage messages";
    ASSERT_GE(k.prediction, wanted) << "prediction messages";
    expect_rate(k.encoder_stamps, rate_hz, "encoder");
    expect_rate(k.voltage_stamps, rate_hz, "voltage");
    expect_rate(k.prediction_stamps, rate_hz, "prediction");
    if (a == fallback_axis)
      ASSERT_NO_FATAL_FAILURE(check_fallback_axis(k, fallback_file));
    else
      check_fused_axis(a, k);
  }
}

// The monitor's strip chart of each fused axis carries the fused ±1σ band (analysis/evaluation/strip_chart.h: triangles
// between consecutive samples that both have a σ).
TEST(SimLaunch, TheMonitorDrawsTheFusedBand) {
  ros::NodeHandle nh, pnh("~");
  if (!pnh.param("check_chart", false)) GTEST_SKIP() << "~check_chart off";
  std::map<std::string, std::size_t> band_points;
  auto sub = nh.subscribe<visualization_msgs::MarkerArray>(
      "/mm1/monitor/chart", 1, [&](const visualization_msgs::MarkerArray::ConstPtr& m) {
        for (const auto& mk : m->markers) {
          const auto slash = mk.ns.find('/');
          if (slash != std::string::npos && mk.ns.substr(slash + 1) == "fused_band")
            band_points[mk.ns.substr(0, slash)] = mk.points.size();
        }
      });
  const auto drawn = [&] {
    for (const std::string a : {"a", "b", "c"})
      if (band_points[a] < 60) return false;  // ten or more samples' worth of band
    return true;
  };
  const ros::WallTime give_up = ros::WallTime::now() + ros::WallDuration(kPatienceS);
  while (ros::ok() && !drawn() && ros::WallTime::now() < give_up) {
    ros::spinOnce();
    ros::WallDuration(0.05).sleep();
  }
  for (const std::string a : {"a", "b", "c"}) {
    std::printf("axis %s: fused band of %zu points on the chart\n", a.c_str(), band_points[a]);
    EXPECT_GE(band_points[a], 60u) << "axis " << a << ": no fused ±1σ band on /mm1/monitor/chart";
  }
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "sim_launch_check");
  return RUN_ALL_TESTS();
}
