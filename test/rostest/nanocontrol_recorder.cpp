// The recorder runs a study protocol unchanged through the driver on the serial path (nanocontrol_recorder.test):
// a short random walk on axis c at the 10 Hz sample rate of the simulated NanoControl gives a bag the fit/eval
// reader accepts, one row per sample, the program's voltages (as read back) and the truth on every row.
#include "recorder_test_util.h"

using namespace recorder_test;

TEST(NanoControlRecorder, RecordsAShortRandomWalk) {
  ros::NodeHandle nh("mm1");
  const std::string params = "{duration_s: 6.0, pause_interval_s: 3.0, pause_min_s: 1.0, pause_max_s: 1.5}";
  const std::string out = out_path("nanocontrol_random_walk");
  RecorderOptions o = options("random_walk", params, out);
  o.sample_rate_hz = 10.0;
  o.axes = {"c"};
  Recorder r(nh, o);
  ASSERT_EQ(run(r, 45.0), 0) << r.failure();
  EXPECT_EQ(r.next_sample(), r.total_samples());
  EXPECT_EQ(r.total_samples(), 60u);
  const piezo::io::Dataset d = piezo::ros_io::read_data(out);
  ASSERT_EQ(d.size(), r.total_samples());
  const auto cont = piezo::analysis::check_continuity(d.time_s);
  EXPECT_EQ(cont.lost_samples, 0u);
  EXPECT_NEAR(cont.period_s, 0.1, 1e-6);
  auto p = piezo::protocols::make_protocol("random_walk", YAML::Load(params), 10.0, 3);
  const auto match = piezo::analysis::compare_voltages(d, p->program(0, d.size()), 0.011);
  EXPECT_EQ(match.compared, d.size());
  // a large step of the walk may take a sample longer than the slew limit allows (the CAN tests allow 5 %)
  EXPECT_LE(match.mismatched, 0.1 * d.size()) << "first mismatch at row " << match.first_mismatch;
  for (const auto& a : d.axes) EXPECT_TRUE(a.has_truth()) << "axis " << a.name;
  std::printf("%zu rows, %zu voltage mismatches (max %.4f V), %llu late commands, %llu truths substituted\n", d.size(),
              match.mismatched, match.max_abs_error_v, static_cast<unsigned long long>(r.late_commands()),
              static_cast<unsigned long long>(r.substituted_truths()));
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "nanocontrol_recorder");
  return RUN_ALL_TESTS();
}
