// Lock-step recording (recorder_lockstep.test): driver and simulated device in synchronous mode, so the device
// takes a sample only when the driver has written that sample's set points. Each protocol gives its pattern with
// no device sample passing unrecorded and no late command, however loaded the machine (the order is the bus's,
// not a race); noise σ; interrupt and crash followed by ~resume.
#include "recorder_test_util.h"

using namespace recorder_test;
namespace fs = std::filesystem;

namespace {

struct Case {
  std::string protocol, params;
  double duration_s;
};

}  // namespace

TEST(RecorderLockstep, EachProtocolGivesItsPatternWithoutSkippedSamples) {
  ros::NodeHandle nh;
  const std::vector<Case> cases = {
      {"random_walk", "{duration_s: 120.0, pause_interval_s: 30.0, pause_min_s: 3.0, pause_max_s: 6.0}", 0},
      {"sweep", "{fractions: [0.5], full_range_step_sizes_v: [1.25]}", 90.0},
      {"creep", "{scenarios: 2, history_s: 30.0, hold_s: 20.0, pre_approach_s: 5.0, approach_min_s: 2.0, approach_max_s: 5.0}", 0},
      {"sawtooth", "{teeth: 2, amplitude_start_v: 10.0, amplitude_end_v: 20.0, rate_v_per_s: 10.0}", 0},
      {"plan", "{train_s: 40.0, validation_s: 20.0, test_s: 20.0, creep: {scenarios: 1, history_s: 20.0, hold_s: 20.0, pre_approach_s: 2.0, approach_min_s: 1.0, approach_max_s: 2.0}}",
       0},
  };
  for (const auto& c : cases) {
    SCOPED_TRACE(c.protocol);
    const std::string out = out_path("lockstep_" + c.protocol);
    auto o = (options(c.protocol, c.params, out));
    o.duration_s = c.duration_s;
    Recorder r(nh, o);
    const ros::WallTime start = ros::WallTime::now();
    EXPECT_EQ(run(r, 150.0), 0) << r.failure();
    const double wall_s = (ros::WallTime::now() - start).toSec();
    EXPECT_EQ(r.next_sample(), r.total_samples());
    EXPECT_FALSE(fs::exists(out + ".parts")) << "chunks left behind";
    // lock-step: the rows are the device's samples, so the voltages follow the program up to the slew limit
    check_recording(out, c.protocol, c.params, r.total_samples(), 0.01);
    // every sample's set points are on the bus before its SYNC: nothing is late, no device sample unrecorded
    EXPECT_EQ(r.late_commands(), 0u);
    EXPECT_EQ(r.skipped_device_samples(), 0u);
    EXPECT_EQ(r.substituted_truths(), 0u);
    std::printf("lock-step %s: %llu samples in %.1f s wall (%.0f samples/s), %llu late commands, %llu device "
                "samples skipped\n",
                c.protocol.c_str(), static_cast<unsigned long long>(r.total_samples()), wall_s,
                r.total_samples() / wall_s, static_cast<unsigned long long>(r.late_commands()),
                static_cast<unsigned long long>(r.skipped_device_samples()));
  }
}

TEST(RecorderLockstep, NoiseProtocolRecoversSigma) {
  ros::NodeHandle nh;
  const std::string params = "{settle_s: 10.0, record_s: 20.0}";
  const std::string out = out_path("lockstep_noise");
  Recorder r(nh, (options("noise", params, out)));
  ASSERT_EQ(run(r, 150.0), 0) << r.failure();
  const auto d = check_recording(out, "noise", params, r.total_samples(), 0.01);
  const auto noise = piezo::analysis::estimate_noise(d);
  bool found_c = false;
  for (const auto& n : noise)
    if (n.axis == "c") {
      found_c = true;
      EXPECT_EQ(n.window_sigma_nm.size(), 5u);
      EXPECT_NEAR(n.sigma_nm, 20.79, 0.05 * 20.79) << "encoder noise of the c axis";
      std::printf("lock-step noise protocol: sigma c = %.3f nm over %zu samples\n", n.sigma_nm, n.samples);
    }
  EXPECT_TRUE(found_c);
}

TEST(RecorderLockstep, InterruptThenResumeIsContinuous) {
  ros::NodeHandle nh;
  const std::string params = "{duration_s: 60.0, pause_interval_s: 15.0, pause_min_s: 3.0, pause_max_s: 5.0}";
  const std::string out = out_path("lockstep_interrupted");
  std::uint64_t total = 0;
  {
    auto o = (options("random_walk", params, out));
    o.stop_after_samples = 250;
    Recorder r(nh, o);
    EXPECT_EQ(run(r, 90.0), 130);
    EXPECT_EQ(r.next_sample(), 250u);
    total = r.total_samples();
  }
  {
    RecorderOptions o = (options("", "{}", out));
    o.resume = true;
    Recorder r(nh, o);
    EXPECT_EQ(r.next_sample(), 250u);
    EXPECT_EQ(run(r, 90.0), 0) << r.failure();
    EXPECT_EQ(r.skipped_device_samples(), 0u);
  }
  check_recording(out, "random_walk", params, total, 0.01);
}

TEST(RecorderLockstep, CrashThenResumeIsContinuous) {
  ros::NodeHandle nh;
  const std::string params = "{duration_s: 60.0, pause_interval_s: 15.0, pause_min_s: 3.0, pause_max_s: 5.0}";
  const std::string out = out_path("lockstep_crashed");
  std::uint64_t total = 0, crashed_at = 0;
  {
    auto o = (options("random_walk", params, out));
    o.chunk_period_s = 0.02;  // lock-step runs at thousands of samples per second
    Recorder r(nh, o);
    run(r, 90.0, [&](Recorder& rec) { return rec.next_sample() >= 400; });
    total = r.total_samples();
    crashed_at = r.next_sample();
  }
  EXPECT_FALSE(fs::exists(out));  // a crash never merged: only chunks
  {
    RecorderOptions o = (options("", "{}", out));
    o.resume = true;
    Recorder r(nh, o);
    EXPECT_GT(r.next_sample(), 0u) << "no closed chunk survived";
    EXPECT_LE(r.next_sample(), crashed_at);
    EXPECT_EQ(run(r, 90.0), 0) << r.failure();
  }
  check_recording(out, "random_walk", params, total, 0.01);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "recorder_lockstep");
  ros::NodeHandle nh;
  return RUN_ALL_TESTS();
}
