// Bag replay (rosbag play --clock, use_sim_time): the predictor's predictions on the demo bag must equal the
// predictions made offline by the same code path from the same messages, and agree with the predictions the
// live predictor recorded into the bag during the demo (once the live run's earlier start has washed out).
#include <diagnostic_msgs/DiagnosticArray.h>
#include <gtest/gtest.h>
#include <rosbag/bag.h>
#include <rosbag/view.h>
#include <topic_tools/shape_shifter.h>

#include <algorithm>
#include <cstdio>
#include <map>
#include <set>

#include "piezo_compensation/ros/predictor.h"

namespace {

struct Expected {
  double predicted_m;
  std::vector<double> drift_m;
};

// Deadline of a wait for something that takes seconds on an idle host (the nodes starting and connecting; the next
// prediction of a running replay): the waits return as soon as their condition holds, so only a failing run pays it.
constexpr double kPatienceS = 60.0;

void ignore(const topic_tools::ShapeShifter::ConstPtr&) {}

// Spins until pred() holds (true) or kPatienceS of wall time pass (false).
template <typename Pred>
bool spin_until(Pred pred) {
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(kPatienceS);
  while (ros::ok() && !pred() && ros::WallTime::now() < end) {
    ros::WallDuration(0.01).sleep();
    ros::spinOnce();
  }
  return pred();
}

// The predictor's pairing counters (its diagnostics): a sample it paired differently from the bag's order (a
// reading late or lost on a loaded host) makes its prediction differ from the offline one; a failure says so.
class PairingDiagnostics {
 public:
  explicit PairingDiagnostics(ros::NodeHandle& nh)
      : sub_(nh.subscribe<diagnostic_msgs::DiagnosticArray>(
            "/diagnostics", 50, [this](const diagnostic_msgs::DiagnosticArray::ConstPtr& a) {
              for (const auto& st : a->status)
                for (const auto& kv : st.values)
                  if (kv.key.find("lost ") == 0 || kv.key.find("late ") == 0) pairing_[kv.key] = kv.value;
            })) {}
  std::string text() const {
    std::string t;
    for (const auto& [k, v] : pairing_) t += (t.empty() ? "" : ", ") + k + " " + v;
    return t.empty() ? std::string("no pairing diagnostics heard") : "the predictor's " + t;
  }

 private:
  std::map<std::string, std::string> pairing_;
  ros::Subscriber sub_;
};

// What the bag says offline: the predictions of the same PredictorAxis the node runs, fed in bag order, the
// live demo predictions recorded in it, and the topics as played that the predictor does not take.
struct Offline {
  std::map<double, Expected> expected;
  std::map<double, double> recorded;
  std::set<std::string> others;
};

Offline predict_offline(const ros::NodeHandle& pnh, const std::string& bag_path, const std::string& model,
                        const std::vector<std::string>& predictor_inputs) {
  const auto remapped = pnh.param<std::vector<std::string>>("remapped_topics", {});
  const std::string remap_prefix = pnh.param<std::string>("remap_prefix", "");
  piezo::predictor::PredictorSettings s;
  s.axes = {"c"};
  s.model_files["c"] = model;
  s.drift_horizons_s = pnh.param<std::vector<double>>("drift_horizons_s", {1.0, 60.0});
  s.drift_async = false;
  s.drift_update_period_s = 0.0;
  piezo::predictor::PredictorAxis axis("c", model, piezo::predictor::load_model_file(model), s);
  Offline off;
  rosbag::Bag bag(bag_path, rosbag::bagmode::Read);
  for (const rosbag::ConnectionInfo* c : rosbag::View(bag).getConnections()) {
    const bool re = std::find(remapped.begin(), remapped.end(), c->topic) != remapped.end();
    const std::string played = re ? remap_prefix + c->topic : c->topic;
    if (std::find(predictor_inputs.begin(), predictor_inputs.end(), played) == predictor_inputs.end())
      off.others.insert(played);
  }
  for (const rosbag::MessageInstance& m : rosbag::View(bag)) {
    std::vector<piezo::predictor::PredictorAxis::Output> outs;
    if (m.getTopic() == "/mm1/c/voltage") {
      if (auto v = m.instantiate<piezo_compensation::AxisVoltage>())
        outs = axis.on_voltage(*v, false, m.getTime());
    } else if (m.getTopic() == "/mm1/c/encoder") {
      if (auto e = m.instantiate<piezo_compensation::EncoderPosition>())
        outs = axis.on_encoder(*e, false, m.getTime());
    } else if (m.getTopic() == "/mm1/c/prediction") {
      if (auto p = m.instantiate<piezo_compensation::Prediction>())
        off.recorded[p->header.stamp.toSec()] = p->predicted_position;
    }
    for (const auto& o : outs)
      off.expected[o.prediction.header.stamp.toSec()] = {o.prediction.predicted_position, o.prediction.drift};
  }
  return off;
}

// The replayed predictions equal the offline ones (position and drift), each in the base frame,
// uncompensated.
void expect_live_matches_offline(const std::map<double, piezo_compensation::Prediction>& live,
                                 const std::map<double, Expected>& expected,
                                 const PairingDiagnostics& pairing) {
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
  std::printf("%zu predictions compared; %s\n", compared, pairing.text().c_str());
  EXPECT_LT(worst_m, 1e-12) << "replayed prediction differs from the offline one by " << worst_m * 1e9
                            << " nm (" << pairing.text() << ")";
  EXPECT_LT(worst_drift_m, 1e-12) << "replayed drift differs by " << worst_drift_m * 1e9 << " nm ("
                                  << pairing.text() << ")";
}

// The live run started before the bag did; compare its recorded predictions over the second half.
void expect_recorded_matches_offline(const Offline& off, double tolerance_nm, const std::string& bag_path) {
  ASSERT_FALSE(off.recorded.empty()) << bag_path << ": no recorded predictions";
  const double half =
      off.recorded.begin()->first + 0.5 * (off.recorded.rbegin()->first - off.recorded.begin()->first);
  double worst_rec = 0.0;
  std::size_t n_rec = 0;
  for (const auto& [t, x] : off.recorded) {
    if (t < half) continue;
    auto it = off.expected.find(t);
    if (it == off.expected.end()) continue;
    ++n_rec;
    worst_rec = std::max(worst_rec, std::abs(x - it->second.predicted_m));
  }
  EXPECT_GT(n_rec, 500u);
  EXPECT_LT(worst_rec * 1e9, tolerance_nm) << "vs the live predictions in the bag";
  ::testing::Test::RecordProperty("worst_recorded_difference_nm", std::to_string(worst_rec * 1e9));
}

}  // namespace

TEST(PredictorReplay, PredictionsMatchOfflineAndRecorded) {
  ros::NodeHandle nh, pnh("~");
  const std::string bag_path = pnh.param<std::string>("bag", ""),
                    model = pnh.param<std::string>("model_file", "");
  // The player waits for a subscriber on every topic of the bag (--wait-for-subscribers): the predictor's
  // inputs are the predictor's to take; we take the others, the last thing before the replay, once we listen
  // to the predictions.
  const auto predictor_inputs = pnh.param<std::vector<std::string>>("predictor_inputs", {});
  const PairingDiagnostics pairing(nh);
  std::map<double, piezo_compensation::Prediction> live;
  auto sub = nh.subscribe<piezo_compensation::Prediction>(
      "/mm1/c/prediction", 5000,
      [&](const piezo_compensation::Prediction::ConstPtr& p) { live[p->header.stamp.toSec()] = *p; });

  const Offline off = predict_offline(pnh, bag_path, model, predictor_inputs);
  const auto& expected = off.expected;
  ASSERT_GT(expected.size(), 1000u) << bag_path << ": too few samples";

  // The predictor is up and we hear its predictions: then we subscribe to the rest, and the player starts.
  ASSERT_TRUE(spin_until([&] { return sub.getNumPublishers() > 0; }))
      << "predictor not publishing predictions";
  ASSERT_FALSE(predictor_inputs.empty()) << "~predictor_inputs not set";
  std::vector<ros::Subscriber> sinks;
  for (const auto& t : off.others) sinks.push_back(nh.subscribe<topic_tools::ShapeShifter>(t, 1, &ignore));
  // Wait for the replay to finish: the prediction of the bag's last sample (they come in order on one
  // connection), or every sample's; a replay that stops making progress for kPatienceS gives up.
  const double last_expected_s = expected.rbegin()->first;
  const auto finished = [&] {
    return live.size() >= expected.size() || (!live.empty() && live.rbegin()->first >= last_expected_s);
  };
  std::size_t last_n = 0;
  while (ros::ok() && !finished()) {
    last_n = live.size();
    if (!spin_until([&] { return live.size() != last_n || finished(); })) break;
  }
  sinks.clear();
  EXPECT_TRUE(finished()) << "the replay stopped for " << kPatienceS << " s with " << live.size() << " of "
                          << expected.size() << " predictions";
  ASSERT_GE(live.size(), expected.size() * 99 / 100) << "replay delivered too few predictions";

  ASSERT_NO_FATAL_FAILURE(expect_live_matches_offline(live, expected, pairing));
  expect_recorded_matches_offline(off, pnh.param<double>("recorded_tolerance_nm", 1.0), bag_path);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "predictor_replay_test");
  return RUN_ALL_TESTS();
}
