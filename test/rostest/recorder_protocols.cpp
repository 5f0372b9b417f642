// Recorder against the simulated device and the driver (recorder_protocols.test): every protocol, shortened,
// gives the protocol's voltage pattern and a bag that ros_io::read_data (the fit/eval reader) accepts; an
// interruption or a crash followed by ~resume gives one continuous data set; the noise protocol recovers the
// encoder σ; a silent driver stops the recording safely.
#include <gtest/gtest.h>
#include <ros/callback_queue.h>
#include <ros/ros.h>
#include <std_srvs/Trigger.h>

#include <filesystem>
#include <functional>

#include "piezo_compensation/analysis/recording_summary.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/ros/recorder.h"

namespace fs = std::filesystem;
using piezo::ros_nodes::Recorder;
using piezo::ros_nodes::RecorderOptions;

namespace {

std::string out_path(const std::string& name) {
  const std::string dir = ::testing::TempDir() + "recorder_rostest_" + std::to_string(::getpid());
  fs::create_directories(dir);
  const std::string p = dir + "/" + name + ".bag";
  fs::remove_all(p);
  fs::remove_all(p + ".parts");
  return p;
}

RecorderOptions options(const std::string& protocol, const std::string& params_yaml, const std::string& out) {
  RecorderOptions o;
  o.protocol = protocol;
  o.protocol_params = YAML::Load(params_yaml);
  o.seed = 3;
  o.out = out;
  o.chunk_period_s = 2.0;
  o.encoder_timeout_s = 2.0;
  o.startup_timeout_s = 20.0;
  o.min_free_space_mb = 10.0;
  o.progress_period_s = 5.0;
  return o;
}

// Runs a recorder until it is done (or `hook` returns true: then it is abandoned like a crash).
int run(Recorder& r, double limit_s, const std::function<bool(Recorder&)>& hook = {}) {
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(limit_s);
  while (ros::ok() && !r.done() && ros::WallTime::now() < end) {
    ros::getGlobalCallbackQueue()->callAvailable(ros::WallDuration(0.01));
    if (hook && hook(r)) r.abandon();
  }
  if (!r.done()) r.request_stop("test time limit");
  return r.exit_code();
}

// The recorded data set matches the protocol: one row per sample, no gaps, the program's voltages (a few
// samples may lag behind a large step because of the driver's slew limit).
piezo::io::Dataset check_recording(const std::string& out, const std::string& protocol, const std::string& params,
                                   std::uint64_t expected_samples, double max_late_fraction) {
  const piezo::io::Dataset d = piezo::ros_io::read_data(out);
  EXPECT_EQ(d.size(), expected_samples) << out;
  const auto cont = piezo::analysis::check_continuity(d.time_s);
  EXPECT_EQ(cont.lost_samples, 0u) << out;
  EXPECT_EQ(cont.duplicated_samples, 0u) << out;
  EXPECT_NEAR(cont.period_s, 1.0 / 11.0, 1e-6);
  auto p = piezo::protocols::make_protocol(protocol, YAML::Load(params), 11.0, 3);
  const auto program = p->program(0, d.size());
  const auto match = piezo::analysis::compare_voltages(d, program, 0.011);
  EXPECT_EQ(match.compared, d.size());
  EXPECT_LE(match.mismatched, max_late_fraction * d.size())
      << out << ": first mismatch at row " << match.first_mismatch << ", max error " << match.max_abs_error_v;
  for (const auto& a : d.axes) EXPECT_TRUE(a.has_truth()) << "axis " << a.name << " without true position";
  return d;
}

struct Case {
  std::string protocol, params;
  double duration_s;
};

}  // namespace

TEST(RecorderProtocols, EachProtocolGivesItsPatternAndAReadableBag) {
  ros::NodeHandle nh;
  const std::vector<Case> cases = {
      {"random_walk", "{duration_s: 60.0, pause_interval_s: 20.0, pause_min_s: 3.0, pause_max_s: 6.0}", 0},
      {"sweep", "{fractions: [0.5], full_range_step_sizes_v: [1.25]}", 60.0},
      {"creep", "{scenarios: 2, history_s: 20.0, hold_s: 15.0, pre_approach_s: 5.0, approach_min_s: 2.0, approach_max_s: 5.0}", 0},
      {"sawtooth", "{teeth: 2, amplitude_start_v: 10.0, amplitude_end_v: 20.0, rate_v_per_s: 10.0}", 0},
      {"plan", "{train_s: 20.0, validation_s: 10.0, test_s: 10.0, creep: {scenarios: 1, history_s: 10.0, hold_s: 10.0, pre_approach_s: 2.0, approach_min_s: 1.0, approach_max_s: 2.0}}",
       0},
  };
  for (const auto& c : cases) {
    SCOPED_TRACE(c.protocol);
    const std::string out = out_path(c.protocol);
    auto o = options(c.protocol, c.params, out);
    o.duration_s = c.duration_s;
    Recorder r(nh, o);
    EXPECT_EQ(run(r, 120.0), 0) << r.failure();
    EXPECT_EQ(r.next_sample(), r.total_samples());
    EXPECT_FALSE(fs::exists(out + ".parts")) << "chunks left behind";
    check_recording(out, c.protocol, c.params, r.total_samples(), 0.05);
    std::printf("%s: %llu samples, %llu late commands, %llu device samples skipped between rows\n",
                c.protocol.c_str(), static_cast<unsigned long long>(r.total_samples()),
                static_cast<unsigned long long>(r.late_commands()),
                static_cast<unsigned long long>(r.skipped_device_samples()));
  }
}

TEST(RecorderProtocols, NoiseProtocolRecoversSigma) {
  ros::NodeHandle nh;
  const std::string params = "{settle_s: 5.0, record_s: 20.0}";
  const std::string out = out_path("noise");
  Recorder r(nh, options("noise", params, out));
  ASSERT_EQ(run(r, 120.0), 0) << r.failure();
  const auto d = check_recording(out, "noise", params, r.total_samples(), 0.05);
  const auto noise = piezo::analysis::estimate_noise(d);
  bool found_c = false;
  for (const auto& n : noise)
    if (n.axis == "c") {
      found_c = true;
      EXPECT_EQ(n.window_sigma_nm.size(), 5u);
      EXPECT_NEAR(n.sigma_nm, 20.79, 0.05 * 20.79) << "encoder noise of the c axis";
      RecordProperty("sigma_c_nm", std::to_string(n.sigma_nm));
      std::printf("noise protocol: sigma c = %.3f nm over %zu samples\n", n.sigma_nm, n.samples);
    }
  EXPECT_TRUE(found_c);
}

TEST(RecorderProtocols, InterruptThenResumeIsContinuous) {
  ros::NodeHandle nh;
  const std::string params = "{duration_s: 50.0, pause_interval_s: 15.0, pause_min_s: 3.0, pause_max_s: 5.0}";
  const std::string out = out_path("interrupted");
  std::uint64_t total = 0;
  {
    auto o = options("random_walk", params, out);
    o.stop_after_samples = 200;  // behaves like Ctrl-C after 200 samples
    Recorder r(nh, o);
    EXPECT_EQ(run(r, 60.0), 130);
    EXPECT_EQ(r.next_sample(), 200u);
    total = r.total_samples();
    EXPECT_EQ(piezo::ros_io::read_data(out).size(), 200u);  // valid, indexed, everything so far
  }
  {
    RecorderOptions o = options("", "{}", out);
    o.resume = true;
    Recorder r(nh, o);
    EXPECT_EQ(r.next_sample(), 200u);
    EXPECT_EQ(run(r, 60.0), 0) << r.failure();
  }
  check_recording(out, "random_walk", params, total, 0.05);
}

TEST(RecorderProtocols, CrashThenResumeIsContinuous) {
  ros::NodeHandle nh;
  const std::string params = "{duration_s: 50.0, pause_interval_s: 15.0, pause_min_s: 3.0, pause_max_s: 5.0}";
  const std::string out = out_path("crashed");
  std::uint64_t total = 0, crashed_at = 0;
  {
    auto o = options("random_walk", params, out);
    o.chunk_period_s = 0.3;
    Recorder r(nh, o);
    run(r, 60.0, [&](Recorder& rec) { return rec.next_sample() >= 300; });
    total = r.total_samples();
    crashed_at = r.next_sample();
  }
  EXPECT_FALSE(fs::exists(out));  // a crash never merged: only chunks
  {
    RecorderOptions o = options("", "{}", out);
    o.resume = true;
    Recorder r(nh, o);
    EXPECT_GT(r.next_sample(), 0u) << "no closed chunk survived";
    EXPECT_LE(r.next_sample(), crashed_at);
    EXPECT_EQ(run(r, 60.0), 0) << r.failure();
  }
  check_recording(out, "random_walk", params, total, 0.05);
}

TEST(RecorderProtocols, SilentDriverStopsSafely) {
  ros::NodeHandle nh;
  const std::string out = out_path("silent");
  auto o = options("random_walk", "{duration_s: 120.0}", out);
  o.encoder_timeout_s = 1.0;
  Recorder r(nh, o);
  bool injected = false;
  const int code = run(r, 60.0, [&](Recorder& rec) {
    if (!injected && rec.next_sample() >= 100) {
      std_srvs::Trigger t;
      injected = ros::service::call("mm3e_sim/inject_bus_off", t);  // the device goes quiet for 3 s
      EXPECT_TRUE(injected);
    }
    return false;
  });
  EXPECT_EQ(code, 1);
  EXPECT_NE(r.failure().find("driver dead"), std::string::npos) << r.failure();
  EXPECT_LT(r.next_sample(), r.total_samples());
  EXPECT_EQ(piezo::ros_io::read_data(out).size(), r.next_sample());  // a valid bag with what was recorded
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "recorder_protocols");
  ros::NodeHandle nh;
  ros::Time::waitForValid(ros::WallDuration(20.0));
  return RUN_ALL_TESTS();
}
