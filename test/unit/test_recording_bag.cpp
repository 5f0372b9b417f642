// The recorder's crash-safe chunked bag: closed chunks survive a crash, resume finds the next sample, the merge
// yields one valid bag with every sample once. No roscore needed.
#include <gtest/gtest.h>
#include <rosbag/view.h>

#include <filesystem>
#include <fstream>
#include <limits>
#include <random>

#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/ProtocolPhase.h"
#include "piezo_compensation/ros/recorder.h"
#include "piezo_compensation/ros/recorder_bag.h"

namespace fs = std::filesystem;
using piezo::ros_io::ChunkedBag;
using piezo::ros_io::RecorderBagError;
using piezo::ros_io::scan_recording;

namespace {

const std::string kEnc = "/mm1/a/encoder";
const std::string kPhase = "/mm1/protocol_phase";

std::string fresh_path(const std::string& name) {
  const std::string dir = ::testing::TempDir() + "recbag_" + std::to_string(::getpid());
  fs::create_directories(dir);
  const std::string p = dir + "/" + name;
  fs::remove_all(p);
  fs::remove_all(p + ".parts");
  return p;
}

void write_sample(ChunkedBag& bag, std::uint32_t i) {
  piezo_compensation::EncoderPosition e;
  e.header.stamp = ros::Time(100.0 + i / 11.0);
  e.axis = "a";
  e.sequence = i;
  e.position = 1e-9 * i;
  e.valid = true;
  bag.write(kEnc, e.header.stamp, e);
}

void write_marker(ChunkedBag& bag, std::uint32_t i, const std::string& yaml) {
  piezo_compensation::ProtocolPhase m;
  m.header.stamp = ros::Time(100.0 + i / 11.0);
  m.protocol = "noise";
  m.phase = "settle";
  m.sample_index = i;
  m.parameters_yaml = yaml;
  bag.write(kPhase, m.header.stamp, m);
}

std::vector<std::uint32_t> sequences_in(const std::string& path) {
  rosbag::Bag b(path, rosbag::bagmode::Read);
  rosbag::View v(b, rosbag::TopicQuery(kEnc));
  std::vector<std::uint32_t> out;
  for (const auto& m : v) out.push_back(m.instantiate<piezo_compensation::EncoderPosition>()->sequence);
  return out;
}

}  // namespace

TEST(RecordingBag, CrashKeepsClosedChunksAndResumeContinues) {
  const std::string out = fresh_path("crash.bag");
  {
    ChunkedBag bag(out, 1e-9, 0.0);  // every between_samples() closes the chunk
    write_marker(bag, 0, "protocol: noise");
    for (std::uint32_t i = 0; i < 30; ++i) {
      write_sample(bag, i);
      if (i % 10 == 9) bag.between_samples();  // chunks of 10 samples
    }
    bag.abandon();  // samples 30..34 never get past here: a kill -9 with a chunk open
  }
  {
    ChunkedBag bag(out, 1e9, 0.0);
    for (std::uint32_t i = 30; i < 35; ++i) write_sample(bag, i);
    bag.abandon();
  }
  auto found = scan_recording(out, kEnc, kPhase);
  ASSERT_TRUE(found.found);
  EXPECT_EQ(found.files.size(), 3u);
  EXPECT_EQ(found.set_aside.size(), 1u);  // the open chunk, renamed *.unindexed
  EXPECT_EQ(found.samples, 30u);
  EXPECT_EQ(found.next_sample, 30u);
  EXPECT_EQ(found.parameters_yaml, "protocol: noise");

  {
    ChunkedBag bag(out, 1e9, 0.0);
    for (std::uint32_t i = 30; i < 50; ++i) write_sample(bag, i);
    EXPECT_EQ(bag.finish(), 51u);  // 50 samples + 1 marker
  }
  EXPECT_FALSE(fs::exists(piezo::ros_io::parts_dir_of(out) + "/chunk_000001.bag"));
  const auto seq = sequences_in(out);
  ASSERT_EQ(seq.size(), 50u);
  for (std::uint32_t i = 0; i < 50; ++i) EXPECT_EQ(seq[i], i);

  // a second session appends to the merged bag
  {
    ChunkedBag bag(out, 1e9, 0.0);
    for (std::uint32_t i = 50; i < 60; ++i) write_sample(bag, i);
    bag.finish();
  }
  found = scan_recording(out, kEnc, kPhase);
  EXPECT_EQ(found.files.size(), 1u);
  EXPECT_EQ(found.next_sample, 60u);
  EXPECT_EQ(sequences_in(out).size(), 60u);
}

namespace {
// Every sample 0..n-1 exactly once and in order.
void expect_complete(const std::string& path, std::uint32_t n) {
  const auto seq = sequences_in(path);
  ASSERT_EQ(seq.size(), n) << path;
  std::uint32_t reordered = 0, duplicated = 0;
  for (std::size_t k = 1; k < seq.size(); ++k) {
    duplicated += seq[k] == seq[k - 1];
    reordered += seq[k] < seq[k - 1];
  }
  EXPECT_EQ(duplicated, 0u);
  EXPECT_EQ(reordered, 0u);
  for (std::uint32_t i = 0; i < n; ++i) EXPECT_EQ(seq[i], i);
}
}  // namespace

TEST(RecordingBag, TornLastChunkAtRandomOffsetsIsSetAsideAndRecordedAgain) {
  std::mt19937 rng(16);
  for (int trial = 0; trial < 12; ++trial) {
    const std::string out = fresh_path("torn.bag");
    {
      ChunkedBag bag(out, 1e-9, 0.0);
      write_marker(bag, 0, "protocol: noise");
      for (std::uint32_t i = 0; i < 40; ++i) {
        write_sample(bag, i);
        if (i % 10 == 9) bag.between_samples();  // four closed chunks of 10 samples
      }
    }
    // Power loss while the last chunk was being written out: it ends at any byte.
    const std::string last = piezo::ros_io::parts_dir_of(out) + "/chunk_000004.bag";
    ASSERT_TRUE(fs::exists(last));
    const auto size = fs::file_size(last);
    const auto cut = std::uniform_int_distribution<std::uintmax_t>(0, size - 1)(rng);
    fs::resize_file(last, cut);
    const auto found = scan_recording(out, kEnc, kPhase);
    ASSERT_TRUE(found.found) << "cut at " << cut;
    ASSERT_EQ(found.set_aside.size(), 1u) << "cut at " << cut;
    EXPECT_EQ(found.set_aside_bytes, cut);  // what resume says it dropped
    EXPECT_EQ(found.samples, 30u) << "cut at " << cut;
    EXPECT_EQ(found.next_sample, 30u);
    {
      ChunkedBag bag(out, 1e9, 0.0);
      for (std::uint32_t i = 30; i < 50; ++i) write_sample(bag, i);
      bag.finish();
    }
    expect_complete(out, 50);
  }
}

TEST(RecordingBag, CrashBetweenMergeAndDeleteMergesOnce) {
  const std::string out = fresh_path("merged_twice.bag");
  {
    ChunkedBag bag(out, 1e-9, 0.0);
    for (std::uint32_t i = 0; i < 20; ++i) {
      write_sample(bag, i);
      if (i % 5 == 4) bag.between_samples();
    }
    bag.crash_after_merge_for_test();
    EXPECT_EQ(bag.finish(), 20u);
  }
  // FILE.bag holds every sample and so do the chunks that were not deleted.
  ASSERT_TRUE(fs::exists(piezo::ros_io::parts_dir_of(out) + "/chunk_000001.bag"));
  const auto found = scan_recording(out, kEnc, kPhase);
  EXPECT_EQ(found.files.size(), 5u);
  EXPECT_EQ(found.samples, 20u);
  EXPECT_EQ(found.duplicates, 20u);
  EXPECT_EQ(found.next_sample, 20u);
  {
    ChunkedBag bag(out, 1e9, 0.0);
    for (std::uint32_t i = 20; i < 30; ++i) write_sample(bag, i);
    EXPECT_EQ(bag.finish(), 30u);
  }
  expect_complete(out, 30);
  EXPECT_FALSE(fs::exists(piezo::ros_io::parts_dir_of(out)));
}

TEST(RecordingBag, NothingToResume) {
  const auto found = scan_recording(fresh_path("none.bag"), kEnc, kPhase);
  EXPECT_FALSE(found.found);
  EXPECT_EQ(found.next_sample, 0u);
}

TEST(RecordingBag, BrokenBagIsNamed) {
  const std::string out = fresh_path("broken.bag");
  std::ofstream(out) << "not a bag at all";
  try {
    scan_recording(out, kEnc, kPhase);
    FAIL() << "no error";
  } catch (const RecorderBagError& e) {
    EXPECT_NE(std::string(e.what()).find("broken.bag: not a readable"), std::string::npos) << e.what();
  }
}

TEST(RecordingBag, FullDiskStopsWithOneClearMessage) {
  const std::string out = fresh_path("full.bag");
  try {
    ChunkedBag bag(out, 60.0, 1e12);  // asks for more free space than any disk has
    FAIL() << "no error";
  } catch (const RecorderBagError& e) {
    EXPECT_NE(std::string(e.what()).find("disk nearly full"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("min_free_space_mb"), std::string::npos) << e.what();
  }
}

TEST(RecorderOptions, BadParametersAreNamed) {
  using piezo::ros_nodes::RecorderOptions;
  auto message = [](const RecorderOptions& o) -> std::string {
    try {
      o.validate();
    } catch (const std::invalid_argument& e) {
      return e.what();
    }
    return "";
  };
  RecorderOptions ok;
  ok.protocol = "noise";
  ok.out = "/tmp/x.bag";
  EXPECT_EQ(message(ok), "");
  auto o = ok;
  o.out = "/tmp/x.csv";
  EXPECT_NE(message(o).find("~out must end in .bag"), std::string::npos);
  o = ok;
  o.protocol.clear();
  EXPECT_NE(message(o).find("~protocol"), std::string::npos);
  o.resume = true;  // resuming takes the protocol from the bag
  EXPECT_EQ(message(o), "");
  o = ok;
  o.sample_rate_hz = 0.0;
  EXPECT_NE(message(o).find("~sample_rate_hz"), std::string::npos);
  o = ok;
  o.encoder_timeout_s = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(message(o).find("~encoder_timeout_s"), std::string::npos);
  o = ok;
  o.axes = {"a", "x"};
  EXPECT_NE(message(o).find("~axes: unknown axis 'x'"), std::string::npos);
  o = ok;
  o.max_wait_samples = -1;
  EXPECT_NE(message(o).find("~max_wait_samples"), std::string::npos);
}

TEST(RecorderOptions, SpecRoundTripsThroughTheMarkerYaml) {
  using piezo::ros_nodes::Recorder;
  using piezo::ros_nodes::RecorderOptions;
  RecorderOptions o;
  std::uint64_t total = 0;
  double t0 = 0;
  Recorder::parse_spec(
      "protocol: creep\nseed: 9\nsample_rate_hz: 11\nsamples: 1234\nt0_s: 1700000000.5\nparameters: {scenarios: 2}\n", o,
      total, t0);
  EXPECT_EQ(o.protocol, "creep");
  EXPECT_EQ(o.seed, 9u);
  EXPECT_EQ(total, 1234u);
  EXPECT_DOUBLE_EQ(t0, 1700000000.5);
  EXPECT_EQ(o.protocol_params["scenarios"].as<int>(), 2);
  EXPECT_THROW(Recorder::parse_spec("protocol: creep\n", o, total, t0), RecorderBagError);
}
