// Bag replay (rosbag play --clock, use_sim_time): the predictor's predictions on the demo bag must equal the
// predictions made offline by the same code path from the same messages, and agree with the predictions the
// live predictor recorded into the bag during the demo (once the live run's earlier start has washed out).
#include <gtest/gtest.h>
#include <rosbag/bag.h>
#include <rosbag/view.h>

#include <map>

#include "piezo_compensation/ros/predictor.h"

namespace {

struct Expected {
  double predicted_m;
  std::vector<double> drift_m;
};

}  // namespace

TEST(PredictorReplay, PredictionsMatchOfflineAndRecorded) {
  ros::NodeHandle nh, pnh("~");
  const std::string bag_path = pnh.param<std::string>("bag", ""), model = pnh.param<std::string>("model_file", "");
  std::vector<double> horizons = pnh.param<std::vector<double>>("drift_horizons_s", {1.0, 60.0});

  // Offline: the same PredictorAxis the node runs, fed in bag order.
  piezo::predictor::PredictorSettings s;
  s.axes = {"c"};
  s.model_files["c"] = model;
  s.drift_horizons_s = horizons;
  s.drift_async = false;
  s.drift_update_period_s = 0.0;
  piezo::predictor::PredictorAxis axis("c", model, piezo::predictor::load_model_file(model), s);
  std::map<double, Expected> expected;
  std::map<double, double> recorded;  // live demo predictions in the bag
  {
    rosbag::Bag bag(bag_path, rosbag::bagmode::Read);
    for (const rosbag::MessageInstance& m : rosbag::View(bag)) {
      std::vector<piezo::predictor::PredictorAxis::Output> outs;
      if (m.getTopic() == "/mm1/c/voltage") {
        if (auto v = m.instantiate<piezo_compensation::AxisVoltage>()) outs = axis.on_voltage(*v, false, m.getTime());
      } else if (m.getTopic() == "/mm1/c/encoder") {
        if (auto e = m.instantiate<piezo_compensation::EncoderPosition>()) outs = axis.on_encoder(*e, false, m.getTime());
      } else if (m.getTopic() == "/mm1/c/prediction") {
        if (auto p = m.instantiate<piezo_compensation::Prediction>()) recorded[p->header.stamp.toSec()] = p->predicted_position;
      }
      for (const auto& o : outs)
        expected[o.prediction.header.stamp.toSec()] = {o.prediction.predicted_position, o.prediction.drift};
    }
  }
  ASSERT_GT(expected.size(), 1000u) << bag_path << ": too few samples";

  std::map<double, piezo_compensation::Prediction> live;
  auto sub = nh.subscribe<piezo_compensation::Prediction>("/mm1/c/prediction", 5000,
      [&](const piezo_compensation::Prediction::ConstPtr& p) { live[p->header.stamp.toSec()] = *p; });
  // Wait for the replay to finish: all samples in, or the clock stops moving for a while.
  ros::WallTime last_change = ros::WallTime::now();
  std::size_t last_n = 0;
  while (ros::ok() && live.size() < expected.size() && (ros::WallTime::now() - last_change).toSec() < 15.0) {
    ros::WallDuration(0.05).sleep();
    ros::spinOnce();
    if (live.size() != last_n) last_n = live.size(), last_change = ros::WallTime::now();
  }
  ASSERT_GE(live.size(), expected.size() * 99 / 100) << "replay delivered too few predictions";

  std::size_t compared = 0;
  double worst_m = 0.0, worst_drift_m = 0.0;
  for (const auto& [t, p] : live) {
    auto it = expected.find(t);
    if (it == expected.end()) continue;
    ++compared;
    worst_m = std::max(worst_m, std::abs(p.predicted_position - it->second.predicted_m));
    ASSERT_EQ(p.drift.size(), it->second.drift_m.size());
    for (std::size_t i = 0; i < p.drift.size(); ++i)
      worst_drift_m = std::max(worst_drift_m, std::abs(p.drift[i] - it->second.drift_m[i]));
    EXPECT_EQ(p.header.frame_id, "mm1/base");
    EXPECT_FALSE(p.compensation_active);
  }
  EXPECT_GE(compared, expected.size() * 99 / 100);
  EXPECT_LT(worst_m, 1e-12) << "replayed prediction differs from the offline one by " << worst_m * 1e9 << " nm";
  EXPECT_LT(worst_drift_m, 1e-12) << "replayed drift differs by " << worst_drift_m * 1e9 << " nm";

  // The live run started before the bag did; compare its recorded predictions over the second half.
  ASSERT_FALSE(recorded.empty()) << bag_path << ": no recorded predictions";
  const double half = recorded.begin()->first + 0.5 * (recorded.rbegin()->first - recorded.begin()->first);
  double worst_rec = 0.0;
  std::size_t n_rec = 0;
  for (const auto& [t, x] : recorded) {
    if (t < half) continue;
    auto it = expected.find(t);
    if (it == expected.end()) continue;
    ++n_rec;
    worst_rec = std::max(worst_rec, std::abs(x - it->second.predicted_m));
  }
  EXPECT_GT(n_rec, 500u);
  EXPECT_LT(worst_rec * 1e9, pnh.param<double>("recorded_tolerance_nm", 1.0)) << "vs the live predictions in the bag";
  RecordProperty("worst_recorded_difference_nm", std::to_string(worst_rec * 1e9));
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "predictor_replay_test");
  return RUN_ALL_TESTS();
}
