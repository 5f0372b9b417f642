// The predictor against a fake driver: with compensation on it sends the model-inverted voltage (different
// from the intent on a hysteretic model), with it off the intent itself; the prediction says which; the tf
// frames of the measured, predicted and intended tip exist under the base frame. With 3 samples lost, ~snapshot
// writes the stretch after them and ~reload_model warms across them, each saying so.
#include <gtest/gtest.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>
#include <tf2_ros/buffer.h>
#include <tf2_ros/transform_listener.h>

#include <iomanip>
#include <iostream>
#include <sstream>

#include <cstdlib>
#include <filesystem>

#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/resume.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/ros/predictor.h"
#include "predictor_test_driver.h"

namespace {
std::string resume_model_path() {
  std::string p;
  ros::param::get("/mm2/predictor/model_file", p);
  return p;
}

using piezo::test::FakeDriver;

// With compensation on the predictor sends the model-inverted voltage, with it off the intent itself, and on
// again the inverted one; the prediction says which.
void check_compensation_on_off(FakeDriver& drv) {
  drv.intend(30.0);
  for (int i = 0; i < 15; ++i) ASSERT_TRUE(drv.cycle()) << "no prediction and command for sample " << i;
  ASSERT_FALSE(drv.commands.empty());
  ASSERT_FALSE(drv.predictions.empty());
  const auto on = drv.predictions.back();
  EXPECT_TRUE(on.compensation_active) << on.status;
  EXPECT_FALSE(on.fallback) << on.status;
  EXPECT_NEAR(drv.commands.back().voltage, on.corrected_voltage, 1e-9);
  EXPECT_NEAR(on.commanded_voltage, 30.0, 1e-9);
  EXPECT_GT(std::abs(on.corrected_voltage - 30.0), 0.05) << "a hysteretic model must correct the voltage";
  EXPECT_TRUE(std::isfinite(on.predicted_position));
  EXPECT_NEAR(on.measured_position, 14e-9 * drv.reported_v, 1e-15);
  ASSERT_EQ(on.drift.size(), on.drift_horizons.size());
  EXPECT_EQ(on.drift_horizons.size(), 3u);

  std_srvs::SetBool off;
  off.request.data = false;
  ASSERT_TRUE(ros::service::waitForService("/mm1/predictor/set_compensation", ros::Duration(piezo::test::kPatienceS)));
  ASSERT_TRUE(ros::service::call("/mm1/predictor/set_compensation", off));
  EXPECT_TRUE(off.response.success);
  const std::size_t n = drv.commands.size();
  for (int i = 0; i < 5; ++i) ASSERT_TRUE(drv.cycle()) << "no prediction and command for sample " << i;
  ASSERT_GT(drv.commands.size(), n);
  EXPECT_NEAR(drv.commands.back().voltage, 30.0, 1e-12) << "compensation off sends the intent unchanged";
  EXPECT_FALSE(drv.predictions.back().compensation_active);

  std_srvs::SetBool again;
  again.request.data = true;
  ASSERT_TRUE(ros::service::call("/mm1/predictor/set_compensation", again));
  for (int i = 0; i < 3; ++i) ASSERT_TRUE(drv.cycle()) << "no prediction and command for sample " << i;
  EXPECT_TRUE(drv.predictions.back().compensation_active);
  EXPECT_GT(std::abs(drv.commands.back().voltage - 30.0), 0.05);
}

// The tf frames of the measured, predicted and intended tip exist under the base frame; the measured one of
// the last sample is where its reading says (axis c → z).
void check_tf_frames(FakeDriver& drv, tf2_ros::Buffer& tf) {
  // The listener connects to /tf on its own schedule: samples keep coming until the three frames are there (on a
  // loaded host it once connected after the last sample of the steps above, and no frame ever came).
  const auto frames_known = [&] {
    for (const char* child : {"mm1/tip_measured", "mm1/tip_predicted", "mm1/tip_intended"})
      if (!tf.canTransform("mm1/base", child, ros::Time(0))) return false;
    return true;
  };
  bool cycled = true;
  piezo::test::wall_wait([&] { return frames_known() || !(cycled = drv.cycle()); }, piezo::test::kPatienceS, 0.05);
  ASSERT_TRUE(cycled) << "no prediction and command while waiting for the tf frames";
  for (const char* child : {"mm1/tip_measured", "mm1/tip_predicted", "mm1/tip_intended"}) {
    std::string err;
    EXPECT_TRUE(tf.canTransform("mm1/base", child, ros::Time(0), ros::Duration(0.0), &err)) << child << ": " << err;
  }
  // The frame of the last sample (stamped with it): wait for it rather than read whatever the listener has so far.
  const ros::Time last_stamp = drv.predictions.back().header.stamp;
  std::string err;
  ASSERT_TRUE(tf.canTransform("mm1/base", "mm1/tip_measured", last_stamp, ros::Duration(piezo::test::kPatienceS), &err))
      << err;
  const auto t = tf.lookupTransform("mm1/base", "mm1/tip_measured", last_stamp);
  EXPECT_NEAR(t.transform.translation.z, drv.predictions.back().measured_position, 1e-7);  // axis c → z
}

void check_snapshot_after_gap(FakeDriver& drv, piezo::io::Dataset* d) {
  // 3 samples lost, then 60 more: ~snapshot writes the 60 after the gap (over 60 % of the window) and says so;
  // the bag reads at a constant rate, as the offline tools require
  drv.lose(3);
  for (int i = 0; i < 60; ++i) ASSERT_TRUE(drv.cycle()) << "no prediction and command for sample " << i;
  std_srvs::Trigger snap;
  ASSERT_TRUE(ros::service::waitForService("/mm1/predictor/snapshot", ros::Duration(piezo::test::kPatienceS)));
  ASSERT_TRUE(ros::service::call("/mm1/predictor/snapshot", snap));
  ASSERT_TRUE(snap.response.success) << snap.response.message;
  std::cout << "[predictor_live] snapshot: " << snap.response.message << "\n";
  EXPECT_NE(snap.response.message.find("1 gap, 3 samples missing (3 on c after +"), std::string::npos)
      << snap.response.message;
  EXPECT_NE(snap.response.message.find("wrote the most recent stretch without one"), std::string::npos)
      << snap.response.message;
  const std::string path = snap.response.message.substr(0, snap.response.message.find(" ("));
  *d = piezo::ros_io::read_bag(path);
  EXPECT_NO_THROW(d->sample_period_s());
  EXPECT_EQ(d->size(), 60u);
}

void check_reload_warms_across_gap(FakeDriver& drv) {
  // the reload's warm-up keeps the whole window (the running model skipped the same samples) and says so; the
  // node has run about 1 s of the 1800 s ~snapshot_duration_s, so the window is every sample sent, and the reply
  // says it holds less than the window rather than reading as a short one
  std_srvs::Trigger reload;
  ASSERT_TRUE(ros::service::call("/mm1/predictor/reload_model", reload));
  ASSERT_TRUE(reload.response.success) << reload.response.message;
  std::cout << "[predictor_live] reload: " << reload.response.message << "\n";
  EXPECT_NE(reload.response.message.find("the window has 1 gap, 3 samples missing"), std::string::npos)
      << reload.response.message;
  double window_s = 0.0;
  ASSERT_TRUE(ros::param::get("/mm1/predictor/snapshot_duration_s", window_s));
  std::ostringstream warm;
  warm << std::fixed << std::setprecision(1) << " s (" << drv.samples_sent << " readings, less than the " << window_s
       << " s window)";
  EXPECT_NE(reload.response.message.find("c: warm, on the buffered "), std::string::npos) << reload.response.message;
  EXPECT_NE(reload.response.message.find(warm.str()), std::string::npos)
      << "expected '" << warm.str() << "' in: " << reload.response.message;
}

void write_resume_bag(const piezo::io::Dataset& d, std::string* resume_path) {
  // ~resume_from: mm2 resumes at its first sample on that bag, held at its last voltage until then: its first
  // prediction is what resume_model and the compensator give offline for that stamp, not a start at rest (which
  // predicts the first reading itself).
  ASSERT_TRUE(ros::param::get("/mm2/predictor/resume_from", *resume_path));
  // mm1's bag as mm2's (the node reads only its own namespace: a bag of /mm1 is refused by /mm2)
  piezo::ros_io::BagOptions as_mm2;
  as_mm2.ns = "/mm2";
  piezo::ros_io::write_bag(*resume_path, d, as_mm2);
}

// mm2 resumes on the bag: its first prediction is the offline resume's, not a start at rest.
void check_resumed_first_prediction(FakeDriver& drv, const piezo::io::Dataset& d,
                                    const std::string& resume_path) {
  piezo::ros_io::BagOptions as_mm2;
  as_mm2.ns = "/mm2";
  drv.expect_commands = false;  // no intent on mm2
  drv.applied_v = d.axis("c").voltage_v.back();
  ASSERT_TRUE(drv.cycle()) << "no prediction from the resumed predictor";
  const auto first = drv.predictions.back();
  const piezo::models::ModelPtr model = piezo::models::load_model(resume_model_path());
  const piezo::compensation::Resume r = piezo::compensation::resume_model(
      *model, piezo::ros_io::read_bag(resume_path, as_mm2), "c", first.header.stamp.toSec(), drv.applied_v);
  ASSERT_TRUE(r.resumed) << r.status;
  std::cout << "[predictor_live] " << r.status << "\n";
  piezo::compensation::AxisCompensator offline(model->clone(), piezo::compensation::IdealLine{14.0, 0.0}, {});
  offline.start_resumed(r.model->clone(), r.last_voltage_v, r.predicted_nm, r.status);
  const double expected_nm =
      offline.on_sample(drv.applied_v, first.measured_position * 1e9, true).predicted_nm;
  EXPECT_NEAR(first.predicted_position * 1e9, expected_nm, 1e-6);
  EXPECT_GT(std::abs(first.predicted_position - first.measured_position) * 1e9, 1.0)
      << "a start at rest predicts the first reading itself";
}

void check_resume_saved_periodically(FakeDriver& drv) {
  // ~resume_save_to with a 0.2-s period: mm2's own buffer appears there while it runs, for the next start
  std::string saved;
  ASSERT_TRUE(ros::param::get("/mm2/predictor/resume_save_to", saved));
  const std::size_t before = drv.samples_sent;
  for (int i = 0; i < 10; ++i) ASSERT_TRUE(drv.cycle()) << "no prediction from the resumed predictor";
  std::size_t rows = 0;
  piezo::test::wall_wait([&] {
    try {
      rows = std::filesystem::exists(saved) ? piezo::ros_io::read_bag(saved).size() : 0;
    } catch (const std::exception&) {
      rows = 0;
    }
    return rows >= before + 10 || !(drv.cycle());
  }, piezo::test::kPatienceS, 0.05);
  EXPECT_GE(rows, before + 10) << saved;
}

}  // namespace

TEST(PredictorLive, CompensationOnOffAndTfFrames) {
  tf2_ros::Buffer tf;
  tf2_ros::TransformListener listener(tf);
  FakeDriver drv;
  ASSERT_TRUE(drv.wait_connected()) << "predictor topics not connected";
  ASSERT_NO_FATAL_FAILURE(check_compensation_on_off(drv));
  ASSERT_NO_FATAL_FAILURE(check_tf_frames(drv, tf));
  piezo::io::Dataset d;
  ASSERT_NO_FATAL_FAILURE(check_snapshot_after_gap(drv, &d));
  ASSERT_NO_FATAL_FAILURE(check_reload_warms_across_gap(drv));
  std::string resume_path;
  ASSERT_NO_FATAL_FAILURE(write_resume_bag(d, &resume_path));
  FakeDriver drv2("/mm2/c");
  ASSERT_TRUE(drv2.wait_connected()) << "mm2 predictor topics not connected";
  ASSERT_NO_FATAL_FAILURE(check_resumed_first_prediction(drv2, d, resume_path));
  check_resume_saved_periodically(drv2);
}

// Without a period the history is written when the node shuts down (here: a PredictorNode in this process,
// destroyed), and not before; a node that heard no sample leaves the file as it was.
TEST(PredictorLive, SavesItsHistoryAtShutdownForTheNextStart) {
  const std::string dir = std::getenv("ROS_HOME") ? std::getenv("ROS_HOME") : "/tmp";
  const std::string path = dir + "/predictor_live_shutdown.bag";
  std::filesystem::remove(path);
  ros::param::set("/mm3/predictor/model_file", resume_model_path());
  ros::param::set("/mm3/predictor/axes", std::vector<std::string>{"c"});
  ros::param::set("/mm3/predictor/tf_period_s", 0.0);
  ros::param::set("/mm3/predictor/resume_save_to", path);
  ros::param::set("/mm3/predictor/resume_save_period_s", 0.0);
  {
    piezo::predictor::PredictorNode idle(ros::NodeHandle("/mm3"), ros::NodeHandle("/mm3/predictor"));
  }
  EXPECT_FALSE(std::filesystem::exists(path)) << "no sample heard: nothing to save";
  {
    piezo::predictor::PredictorNode node(ros::NodeHandle("/mm3"), ros::NodeHandle("/mm3/predictor"));
    piezo::test::FakeDriver drv("/mm3/c");
    ASSERT_TRUE(drv.wait_connected());
    drv.expect_commands = false;
    drv.applied_v = 12.0;
    for (int i = 0; i < 6; ++i) ASSERT_TRUE(drv.cycle()) << "no prediction for sample " << i;
    EXPECT_FALSE(std::filesystem::exists(path)) << "resume_save_period_s 0: only at shutdown";
  }
  ASSERT_TRUE(std::filesystem::exists(path));
  const piezo::io::Dataset d = piezo::ros_io::read_bag(path);
  EXPECT_EQ(d.size(), 6u);
  EXPECT_NEAR(d.axis("c").voltage_v.back(), 12.0, 1e-12);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "predictor_live_test");
  return RUN_ALL_TESTS();
}
