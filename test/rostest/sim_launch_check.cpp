// sim.launch as a new user starts it: per axis a, b, c the encoder, voltage and prediction topics arrive at the
// encoder rate. ~fallback_axis (if set) must run uncorrected with a status naming ~fallback_file, while its driver
// still reports a held voltage.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include <cmath>
#include <map>
#include <string>
#include <vector>

#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/Prediction.h"

namespace {

struct Counts {
  int encoder = 0, voltage = 0, prediction = 0, fallback = 0, model_predicted = 0;
  std::string last_status, model;
  std::vector<double> voltages;
};

TEST(SimLaunch, EveryAxisPublishesAtTheEncoderRate) {
  ros::NodeHandle nh, pnh("~");
  const double rate_hz = pnh.param("encoder_rate_hz", 11.0);
  const std::string fallback_axis = pnh.param<std::string>("fallback_axis", "");
  const std::string fallback_file = pnh.param<std::string>("fallback_file", "");
  std::map<std::string, Counts> c;
  std::vector<ros::Subscriber> subs;
  bool counting = false;
  for (const std::string a : {"a", "b", "c"}) {
    subs.push_back(nh.subscribe<piezo_compensation::EncoderPosition>(
        "/mm1/" + a + "/encoder", 50, [&, a](const auto&) { c[a].encoder += counting; }));
    subs.push_back(nh.subscribe<piezo_compensation::AxisVoltage>(
        "/mm1/" + a + "/voltage", 50, [&, a](const piezo_compensation::AxisVoltage::ConstPtr& m) {
          c[a].voltage += counting;
          if (counting) c[a].voltages.push_back(m->voltage);
        }));
    subs.push_back(nh.subscribe<piezo_compensation::Prediction>(
        "/mm1/" + a + "/prediction", 50, [&, a](const piezo_compensation::Prediction::ConstPtr& m) {
          if (!counting) return;
          auto& k = c[a];
          ++k.prediction;
          k.fallback += m->fallback;
          k.model_predicted += !m->fallback && std::isfinite(m->predicted_position);
          k.last_status = m->status;
          k.model = m->model;
        }));
  }
  // Wait until every axis predicts (the nodes start and connect), then count over a fixed wall window.
  const ros::WallTime give_up = ros::WallTime::now() + ros::WallDuration(45.0);
  std::map<std::string, bool> seen;
  std::vector<ros::Subscriber> probes;
  for (const std::string a : {"a", "b", "c"})
    probes.push_back(nh.subscribe<piezo_compensation::Prediction>(
        "/mm1/" + a + "/prediction", 1, [&, a](const auto&) { seen[a] = true; }));
  while (seen.size() < 3 && ros::WallTime::now() < give_up) {
    ros::spinOnce();
    ros::WallDuration(0.02).sleep();
  }
  ASSERT_EQ(seen.size(), 3u) << "not every axis published a prediction within 45 s";
  probes.clear();
  ros::WallDuration(1.0).sleep();
  ros::spinOnce();
  counting = true;
  const double window_s = 8.0;
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(window_s);
  while (ros::WallTime::now() < end) {
    ros::spinOnce();
    ros::WallDuration(0.005).sleep();
  }
  counting = false;
  const double expected = rate_hz * window_s;
  for (const std::string a : {"a", "b", "c"}) {
    const auto& k = c[a];
    SCOPED_TRACE("axis " + a);
    EXPECT_NEAR(k.encoder, expected, 0.2 * expected) << "encoder rate";
    EXPECT_NEAR(k.voltage, expected, 0.2 * expected) << "voltage rate";
    EXPECT_NEAR(k.prediction, expected, 0.2 * expected) << "prediction rate";
    if (a == fallback_axis) {
      EXPECT_EQ(k.fallback, k.prediction) << "every prediction of the broken-model axis is a fallback";
      EXPECT_NE(k.last_status.find(fallback_file), std::string::npos) << k.last_status;
      // Held: no intent was sent, the driver keeps the start voltage.
      ASSERT_FALSE(k.voltages.empty());
      for (double v : k.voltages) EXPECT_EQ(v, k.voltages.front());
    } else {
      EXPECT_EQ(k.fallback, 0) << k.last_status;
      EXPECT_EQ(k.model_predicted, k.prediction) << "predictions from the model";
      EXPECT_NE(k.model.find("mm3e_sim_" + a), std::string::npos) << "shipped default model, got " << k.model;
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "sim_launch_check");
  return RUN_ALL_TESTS();
}
