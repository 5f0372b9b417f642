// Helpers shared by the recorder rostests (recorder_protocols.cpp: free-running device, recorder_lockstep.cpp:
// device and driver in synchronous mode).
#pragma once

#include <gtest/gtest.h>
#include <ros/callback_queue.h>
#include <ros/ros.h>
#include <unistd.h>

#include <filesystem>
#include <functional>
#include <string>

#include "piezo_compensation/analysis/evaluation/recording_summary.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/ros/recorder.h"

namespace recorder_test {

using piezo::ros_nodes::Recorder;
using piezo::ros_nodes::RecorderOptions;

inline std::string out_path(const std::string& name) {
  namespace fs = std::filesystem;
  const std::string dir = ::testing::TempDir() + "recorder_rostest_" + std::to_string(::getpid());
  fs::create_directories(dir);
  const std::string p = dir + "/" + name + ".bag";
  fs::remove_all(p);
  fs::remove_all(p + ".parts");
  return p;
}

// Wall-time limits are generous: CI runs on a loaded 2-core machine.
inline RecorderOptions options(const std::string& protocol, const std::string& params_yaml, const std::string& out) {
  RecorderOptions o;
  o.protocol = protocol;
  o.protocol_params = YAML::Load(params_yaml);
  o.seed = 3;
  o.out = out;
  o.chunk_period_s = 2.0;
  o.encoder_timeout_s = 30.0;  // "driver dead" only after 30 s of wall time without a reading (the recorder's clock)
  o.startup_timeout_s = 60.0;
  o.min_free_space_mb = 10.0;
  o.progress_period_s = 5.0;
  return o;
}

// Runs a recorder until it is done (or `hook` returns true: then it is abandoned like a crash).
inline int run(Recorder& r, double limit_s, const std::function<bool(Recorder&)>& hook = {}) {
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(limit_s);
  while (ros::ok() && !r.done() && ros::WallTime::now() < end) {
    ros::getGlobalCallbackQueue()->callAvailable(ros::WallDuration(0.01));
    if (hook && hook(r)) r.abandon();
  }
  if (!r.done()) r.request_stop("test time limit");
  return r.exit_code();
}

// The recorded data set matches the protocol: one row per sample, no gaps, the program's voltages (up to
// max_late_fraction of the rows may lag behind a large step: the driver's slew limit), the truth on every row.
inline piezo::io::Dataset check_recording(const std::string& out, const std::string& protocol,
                                          const std::string& params, std::uint64_t expected_samples,
                                          double max_late_fraction) {
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

}  // namespace recorder_test
