// The recorder's crash-safe bag: FILE.bag is written as a series of short chunk bags in FILE.bag.parts/, each
// closed (indexed) after `chunk_period_s` of wall time; the open one is named *.bag.active. A clean end, Ctrl-C
// or a detected failure merges FILE.bag (from an earlier session, if any) and the chunks into a new FILE.bag
// atomically (write beside, rename). After a hard crash (kill -9, power) every closed chunk is a valid bag;
// the next `--resume` merges them and continues after the last sample they hold. Layout: docs/recorder.md.
// Durability: a chunk is fsynced before its rename and the directory after it; a merged bag likewise, and the
// chunks are deleted only after that. A merge that died between its rename and the deletion leaves messages
// twice (in FILE.bag and in the chunks): scanning and merging drop a message whose topic, time and bytes repeat.
#pragma once

#include <rosbag/bag.h>

#include <chrono>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

namespace piezo::ros_io {

class RecorderBagError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

std::string parts_dir_of(const std::string& out_path);  // FILE.bag.parts
double free_space_mb(const std::string& path);          // on the file system holding path (or its parent)

// What an earlier (interrupted) session left under out_path, for --resume.
struct ExistingRecording {
  bool found = false;
  std::vector<std::string> files;      // valid bags: FILE.bag first, then closed chunks in order
  std::vector<std::string> set_aside;  // unreadable leftovers (an open chunk of a crashed run), renamed *.unindexed
  std::uint64_t set_aside_bytes = 0;   // their size: what resume drops (its samples are recorded again)
  std::uint64_t duplicates = 0;        // first-axis encoder messages found twice (skipped)
  std::string parameters_yaml;         // from the first protocol_phase marker (includes the time base)
  std::uint64_t samples = 0;           // first-axis encoder messages found
  std::uint64_t next_sample = 0;       // last recorded protocol sample index + 1
};
// `encoder_topic` is the first axis' encoder topic (its sequence field is the protocol sample index).
// Throws RecorderBagError naming the file when a bag is unreadable for another reason than a missing index.
ExistingRecording scan_recording(const std::string& out_path, const std::string& encoder_topic,
                                 const std::string& phase_topic);

class ChunkedBag {
 public:
  // Continues chunk numbering after any chunks already in the parts directory.
  ChunkedBag(std::string out_path, double chunk_period_s, double min_free_space_mb);
  ~ChunkedBag();  // closes the open chunk (no merge)

  // Throws RecorderBagError on a write error or when free space drops below the minimum.
  template <class M>
  void write(const std::string& topic, const ros::Time& stamp, const M& msg) {
    ensure_open();
    try {
      bag_->write(topic, stamp, msg);
    } catch (const std::exception& e) {
      fail(std::string("write failed on ") + topic + ": " + e.what());
    }
  }
  // Call between samples: closes the chunk when it is older than the chunk period, and checks free space.
  void between_samples();
  void close_chunk();
  // Closes the open chunk and merges FILE.bag + chunks into FILE.bag (atomically); removes the parts.
  // Returns the number of messages in the merged bag. On failure the parts are kept (resume merges them).
  std::uint64_t finish();
  // Test hook for a hard crash: drop the open chunk unclosed, as kill -9 would.
  void abandon();
  // Test hook for a crash between the merged bag's rename and the deletion of its chunks.
  void crash_after_merge_for_test() { crash_after_merge_ = true; }

  const std::string& out_path() const { return out_; }
  std::size_t chunks_closed() const { return chunks_closed_; }

 private:
  void ensure_open();
  void check_space();
  [[noreturn]] void fail(const std::string& what);

  std::string out_, parts_;
  double chunk_period_s_, min_free_mb_;
  std::unique_ptr<rosbag::Bag> bag_;
  std::string active_path_, final_chunk_path_;
  std::size_t next_index_ = 1, chunks_closed_ = 0;
  bool crash_after_merge_ = false;
  std::chrono::steady_clock::time_point opened_at_, space_checked_at_;
};

// Merges bags (in time order, repeated messages once) into `out_path` via a temporary file, fsync, rename and
// fsync of the directory. Returns the number of messages written.
std::uint64_t merge_bags(const std::vector<std::string>& inputs, const std::string& out_path);

}  // namespace piezo::ros_io
