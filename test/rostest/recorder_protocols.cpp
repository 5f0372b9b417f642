// Recorder against a free-running simulated device and the driver (recorder_protocols.test), as with real
// hardware: the device samples on its own clock (time_scale 10) and the recorder follows the encoder. A protocol
// gives its voltage pattern and a bag that ros_io::read_data (the fit/eval reader) accepts, with the truth on
// every row; an interruption followed by ~resume gives one continuous data set; a silent driver stops the
// recording safely. The other protocols, noise σ and crash + resume run in lock-step (recorder_lockstep.cpp).
#include <std_srvs/Trigger.h>

#include "recorder_test_util.h"

using namespace recorder_test;
namespace fs = std::filesystem;

TEST(RecorderProtocols, EachProtocolGivesItsPatternAndAReadableBag) {
  ros::NodeHandle nh;
  struct Case {
    std::string protocol, params;
  };
  const std::vector<Case> cases = {
      {"random_walk", "{duration_s: 60.0, pause_interval_s: 20.0, pause_min_s: 3.0, pause_max_s: 6.0}"},
      {"plan", "{train_s: 20.0, validation_s: 10.0, test_s: 10.0, creep: {scenarios: 1, history_s: 10.0, hold_s: 10.0, pre_approach_s: 2.0, approach_min_s: 1.0, approach_max_s: 2.0}}"},
  };
  for (const auto& c : cases) {
    SCOPED_TRACE(c.protocol);
    const std::string out = out_path(c.protocol);
    Recorder r(nh, options(c.protocol, c.params, out));
    EXPECT_EQ(run(r, 150.0), 0) << r.failure();
    EXPECT_EQ(r.next_sample(), r.total_samples());
    EXPECT_FALSE(fs::exists(out + ".parts")) << "chunks left behind";
    check_recording(out, c.protocol, c.params, r.total_samples(), 0.05);
    // the truth is matched to the reading by sequence number; under load it can come more than a sample after
    // the reading (on a loaded host, for a sizeable share of the rows): the earlier one stands in; the bound is half
    EXPECT_LE(r.substituted_truths(), 0.5 * r.total_samples());
    std::printf("%s: %llu samples, %llu late commands, %llu device samples skipped between rows, %llu truths "
                "substituted\n",
                c.protocol.c_str(), static_cast<unsigned long long>(r.total_samples()),
                static_cast<unsigned long long>(r.late_commands()),
                static_cast<unsigned long long>(r.skipped_device_samples()),
                static_cast<unsigned long long>(r.substituted_truths()));
  }
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
    EXPECT_EQ(run(r, 90.0), 130);
    EXPECT_EQ(r.next_sample(), 200u);
    total = r.total_samples();
    EXPECT_EQ(piezo::ros_io::read_data(out).size(), 200u);  // valid, indexed, everything so far
  }
  {
    RecorderOptions o = options("", "{}", out);
    o.resume = true;
    Recorder r(nh, o);
    EXPECT_EQ(r.next_sample(), 200u);
    EXPECT_EQ(run(r, 90.0), 0) << r.failure();
  }
  check_recording(out, "random_walk", params, total, 0.05);
}

TEST(RecorderProtocols, SilentDriverStopsSafely) {
  ros::NodeHandle nh;
  const std::string out = out_path("silent");
  auto o = options("random_walk", "{duration_s: 120.0}", out);
  o.encoder_timeout_s = 1.0;  // below the device's 3 s of silence
  Recorder r(nh, o);
  bool injected = false;
  const int code = run(r, 90.0, [&](Recorder& rec) {
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

// recorder_params.test: the parameter layer (ros/params.h). A wrong type and a value out of range each stop the
// recorder with one error naming the parameter; unknown private parameters are listed and warned about.
TEST(RecorderParams, WrongTypeAndOutOfRangeAreNamed) {
  const std::vector<std::pair<std::string, XmlRpc::XmlRpcValue>> cases = {
      {"seed", XmlRpc::XmlRpcValue("7")},               // was silently seed 1
      {"seed", XmlRpc::XmlRpcValue(-3)},
      {"axes", XmlRpc::XmlRpcValue("c")},               // was silently all three axes
      {"sample_rate_hz", XmlRpc::XmlRpcValue("fast")},
      {"sample_rate_hz", XmlRpc::XmlRpcValue(0.0)},
      {"chunk_period_s", XmlRpc::XmlRpcValue(-1.0)},
      {"max_wait_samples", XmlRpc::XmlRpcValue(2.5)},   // an integer, not truncated
      {"max_wait_samples", XmlRpc::XmlRpcValue(5000)},
      {"resume", XmlRpc::XmlRpcValue("yes")},
      {"voltage_tolerance_v", XmlRpc::XmlRpcValue(50.0)},
  };
  int k = 0;
  for (const auto& [param, value] : cases) {
    const std::string ns = "/recorder_bad_params/case_" + std::to_string(k++);
    ros::NodeHandle pnh(ns);
    pnh.setParam("protocol", "random_walk");
    pnh.setParam("out", "/tmp/recorder_params_never_written.bag");
    pnh.setParam(param, value);
    try {
      RecorderOptions::from_params(pnh);
      ADD_FAILURE() << param << ": accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(ns + "/" + param), std::string::npos) << param << ": " << e.what();
    }
  }
  // The same names with good values are accepted (the failures above are the values, not the setup).
  ros::NodeHandle good("/recorder_bad_params/good");
  good.setParam("protocol", "random_walk");
  good.setParam("out", "/tmp/recorder_params_never_written.bag");
  good.setParam("seed", 7);
  good.setParam("axes", std::vector<std::string>{"c"});
  const RecorderOptions o = RecorderOptions::from_params(good);
  EXPECT_EQ(o.seed, 7u);
  EXPECT_EQ(o.axes, std::vector<std::string>{"c"});
}

TEST(RecorderParams, UnknownPrivateParametersAreListed) {
  ros::NodeHandle pnh("/recorder_unknown_params");
  pnh.setParam("protocol", "random_walk");
  pnh.setParam("out", "/tmp/recorder_params_never_written.bag");
  pnh.setParam("sample_rate_hz", 11.0);
  pnh.setParam("chunk_periode_s", 5.0);  // a typo that would otherwise be ignored
  std::vector<std::string> unknown;
  RecorderOptions::from_params(pnh, &unknown);
  EXPECT_EQ(unknown, std::vector<std::string>{"chunk_periode_s"});
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "recorder_protocols");
  ros::NodeHandle nh;
  // recorder_protocols.test: the simulated device's /clock (returns at once without use_sim_time: recorder_params)
  ros::Time::waitForValid(ros::WallDuration(60.0));
  return RUN_ALL_TESTS();
}
