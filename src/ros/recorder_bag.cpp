#include "piezo_compensation/ros/recorder_bag.h"

#include <rosbag/view.h>
#include <sys/statvfs.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <set>
#include <tuple>

#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/ProtocolPhase.h"
#include "piezo_compensation/io/durable.h"
#include "piezo_compensation/ros/data_file.h"

namespace fs = std::filesystem;

namespace piezo::ros_io {

namespace {
void ensure_time() {
  // Time::init() switches a node on /use_sim_time back to the wall clock (until the next /clock message):
  // only for plain programs without ROS time
  if (!ros::Time::isValid() && !ros::Time::isSimTime()) ros::Time::init();
}

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

// chunk_000012.bag[.active] → 12; 0 when the name is not a chunk
std::size_t chunk_index(const std::string& name) {
  if (name.rfind("chunk_", 0) != 0) return 0;
  try {
    return static_cast<std::size_t>(std::stoul(name.substr(6)));
  } catch (...) {
    return 0;
  }
}

std::string chunk_name(std::size_t i) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "chunk_%06zu.bag", i);
  return buf;
}

void fsync_file(const std::string& path) {
  if (const std::string e = io::fsync_path(path, false); !e.empty()) throw RecorderBagError(path + ": " + e);
}
void fsync_parent(const std::string& path) {
  if (const std::string e = io::fsync_parent(path); !e.empty()) throw RecorderBagError(path + ": directory " + e);
}

// A message's identity for de-duplication: the same topic, time and bytes is the same message (what a merge
// that was interrupted before it deleted its chunks leaves twice).
struct MessageKey {
  std::string topic;
  std::uint32_t size = 0;
  std::uint64_t hash = 0;
  bool operator<(const MessageKey& o) const { return std::tie(topic, size, hash) < std::tie(o.topic, o.size, o.hash); }
};
MessageKey key_of(const rosbag::MessageInstance& m, std::vector<std::uint8_t>& buffer) {
  MessageKey k;
  k.topic = m.getTopic();
  k.size = m.size();
  buffer.resize(k.size);
  ros::serialization::OStream stream(buffer.data(), k.size);
  m.write(stream);
  std::uint64_t h = 1469598103934665603ull;  // FNV-1a
  for (std::uint8_t b : buffer) h = (h ^ b) * 1099511628211ull;
  k.hash = h;
  return k;
}

// Keys of the messages at one time stamp: the view is in time order, so a duplicate shares its stamp.
class Deduplicator {
 public:
  bool seen(const rosbag::MessageInstance& m) {
    if (m.getTime() != time_) {
      time_ = m.getTime();
      keys_.clear();
    }
    return !keys_.insert(key_of(m, buffer_)).second;
  }

 private:
  ros::Time time_;
  std::set<MessageKey> keys_;
  std::vector<std::uint8_t> buffer_;
};

bool opens(const std::string& path) {
  try {
    check_bag_file(path);  // a torn or damaged file must not reach rosbag's unchecked reads
    rosbag::Bag b(path, rosbag::bagmode::Read);
    return true;
  } catch (const rosbag::BagException&) {
    return false;
  } catch (const io::DataError&) {
    return false;
  }
}
}  // namespace

std::string parts_dir_of(const std::string& out_path) { return out_path + ".parts"; }

double free_space_mb(const std::string& path) {
  fs::path p = fs::absolute(path);
  while (!p.empty() && !fs::exists(p)) p = p.parent_path();
  struct statvfs st {};
  if (::statvfs(p.c_str(), &st) != 0) return -1.0;
  return static_cast<double>(st.f_bavail) * static_cast<double>(st.f_frsize) / (1024.0 * 1024.0);
}

ExistingRecording scan_recording(const std::string& out_path, const std::string& encoder_topic,
                                 const std::string& phase_topic) {
  ensure_time();
  ExistingRecording r;
  if (fs::exists(out_path)) {
    if (!opens(out_path))
      throw RecorderBagError(out_path + ": not a readable, indexed bag (repair with `rosbag reindex` first)");
    r.files.push_back(out_path);
  }
  const std::string parts = parts_dir_of(out_path);
  if (fs::is_directory(parts)) {
    std::vector<std::pair<std::size_t, std::string>> chunks;
    for (const auto& e : fs::directory_iterator(parts)) {
      const std::string name = e.path().filename().string();
      if (name.find(".merging") != std::string::npos) {  // a merge cut short: its inputs are still here
        fs::remove(e.path());
        continue;
      }
      const std::size_t idx = chunk_index(name);
      if (idx == 0) continue;
      if (ends_with(name, ".bag")) {
        if (opens(e.path().string())) {
          chunks.emplace_back(idx, e.path().string());
          continue;
        }
      } else if (!ends_with(name, ".active")) {
        continue;
      }
      // the chunk that was open when the process died: no index, its samples are recorded again
      const std::string aside = e.path().string() + ".unindexed";
      std::error_code size_ec;
      const auto bytes = fs::file_size(e.path(), size_ec);
      fs::rename(e.path(), aside);
      r.set_aside.push_back(aside);
      r.set_aside_bytes += size_ec ? 0 : bytes;
    }
    std::sort(chunks.begin(), chunks.end());
    for (auto& c : chunks) r.files.push_back(c.second);
  }
  if (r.files.empty()) return r;
  r.found = true;

  std::vector<std::unique_ptr<rosbag::Bag>> bags;
  rosbag::View markers, encoders;
  for (const auto& f : r.files) {
    bags.push_back(std::make_unique<rosbag::Bag>(f, rosbag::bagmode::Read));
    markers.addQuery(*bags.back(), rosbag::TopicQuery(phase_topic));
    encoders.addQuery(*bags.back(), rosbag::TopicQuery(encoder_topic));
  }
  for (const auto& m : markers) {
    if (auto p = m.instantiate<piezo_compensation::ProtocolPhase>()) {
      r.parameters_yaml = p->parameters_yaml;
      break;
    }
  }
  bool any = false;
  Deduplicator dedup;
  for (const auto& m : encoders) {
    if (dedup.seen(m)) {  // FILE.bag and chunks it already holds (a merge cut short before the deletion)
      ++r.duplicates;
      continue;
    }
    if (auto e = m.instantiate<piezo_compensation::EncoderPosition>()) {
      ++r.samples;
      if (!any || e->sequence + 1u > r.next_sample) r.next_sample = std::uint64_t{e->sequence} + 1u;
      any = true;
    }
  }
  return r;
}

ChunkedBag::ChunkedBag(std::string out_path, double chunk_period_s, double min_free_space_mb)
    : out_(std::move(out_path)), parts_(parts_dir_of(out_)), chunk_period_s_(chunk_period_s),
      min_free_mb_(min_free_space_mb) {
  ensure_time();
  std::error_code ec;
  fs::create_directories(parts_, ec);
  if (ec) throw RecorderBagError(parts_ + ": cannot create the chunk directory: " + ec.message());
  for (const auto& e : fs::directory_iterator(parts_))
    next_index_ = std::max(next_index_, chunk_index(e.path().filename().string()) + 1);
  check_space();
}

ChunkedBag::~ChunkedBag() {
  try {
    close_chunk();
  } catch (...) {
    // destructor: the open chunk stays *.active and is set aside on resume
  }
}

void ChunkedBag::ensure_open() {
  if (bag_) return;
  final_chunk_path_ = (fs::path(parts_) / chunk_name(next_index_)).string();
  active_path_ = final_chunk_path_ + ".active";
  ++next_index_;
  bag_ = std::make_unique<rosbag::Bag>();
  try {
    bag_->open(active_path_, rosbag::bagmode::Write);
  } catch (const std::exception& e) {
    bag_.reset();
    throw RecorderBagError(active_path_ + ": cannot open for writing: " + e.what());
  }
  opened_at_ = std::chrono::steady_clock::now();
}

void ChunkedBag::check_space() {
  space_checked_at_ = std::chrono::steady_clock::now();
  const double mb = free_space_mb(parts_);
  if (mb >= 0.0 && mb < min_free_mb_) {
    char buf[160];
    std::snprintf(buf, sizeof buf, "disk nearly full: %.0f MB free at %s, below min_free_space_mb %.0f", mb,
                  parts_.c_str(), min_free_mb_);
    fail(buf);
  }
}

void ChunkedBag::fail(const std::string& what) {
  // keep what is already written valid: close the chunk (its index needs little space)
  try {
    close_chunk();
  } catch (...) {
  }
  throw RecorderBagError(what);
}

void ChunkedBag::between_samples() {
  const auto now = std::chrono::steady_clock::now();
  if (now - space_checked_at_ > std::chrono::seconds(2)) check_space();
  if (bag_ && std::chrono::duration<double>(now - opened_at_).count() >= chunk_period_s_) close_chunk();
}

void ChunkedBag::close_chunk() {
  if (!bag_) return;
  std::unique_ptr<rosbag::Bag> b = std::move(bag_);
  try {
    b->close();
  } catch (const std::exception& e) {
    throw RecorderBagError(active_path_ + ": closing failed: " + e.what());
  }
  fsync_file(active_path_);
  std::error_code ec;
  fs::rename(active_path_, final_chunk_path_, ec);
  if (ec) throw RecorderBagError(active_path_ + ": cannot rename the closed chunk: " + ec.message());
  fsync_parent(final_chunk_path_);
  // rosbag does not see every failed buffered write: reading the index back does
  if (!opens(final_chunk_path_))
    throw RecorderBagError(final_chunk_path_ + ": unreadable after closing (write error, disk full?)");
  ++chunks_closed_;
}

void ChunkedBag::abandon() {
  if (!bag_) return;
  // leave the open file as a killed process would: no close, no index. The object is kept (reachable, so
  // LeakSanitizer does not count it) rather than destroyed, since its destructor would write the index.
  static std::vector<std::unique_ptr<rosbag::Bag>> abandoned;
  abandoned.push_back(std::move(bag_));
}

std::uint64_t ChunkedBag::finish() {
  close_chunk();
  std::vector<std::pair<std::size_t, std::string>> chunks;
  for (const auto& e : fs::directory_iterator(parts_)) {
    const std::string name = e.path().filename().string();
    if (ends_with(name, ".bag") && chunk_index(name) > 0) chunks.emplace_back(chunk_index(name), e.path().string());
  }
  std::sort(chunks.begin(), chunks.end());
  std::vector<std::string> inputs;
  if (fs::exists(out_)) inputs.push_back(out_);
  for (auto& c : chunks) inputs.push_back(c.second);
  if (inputs.empty()) return 0;
  const std::uint64_t n = merge_bags(inputs, out_);  // durable (file and directory synced) before the deletion
  if (crash_after_merge_) return n;
  std::error_code ec;
  for (auto& c : chunks) fs::remove(c.second, ec);
  bool leftovers = false;
  for (const auto& e : fs::directory_iterator(parts_)) {
    (void)e;
    leftovers = true;
  }
  if (!leftovers) fs::remove(parts_, ec);
  return n;
}

std::uint64_t merge_bags(const std::vector<std::string>& inputs, const std::string& out_path) {
  ensure_time();
  const std::string tmp = parts_dir_of(out_path) + "/out.merging-" + std::to_string(::getpid()) + ".bag";
  std::uint64_t n = 0;
  try {
    std::vector<std::unique_ptr<rosbag::Bag>> in;
    rosbag::View view;
    for (const auto& f : inputs) {
      in.push_back(std::make_unique<rosbag::Bag>(f, rosbag::bagmode::Read));
      view.addQuery(*in.back());
    }
    fs::create_directories(parts_dir_of(out_path));
    rosbag::Bag out(tmp, rosbag::bagmode::Write);
    Deduplicator dedup;
    for (const rosbag::MessageInstance& m : view) {
      if (dedup.seen(m)) continue;
      out.write(m.getTopic(), m.getTime(), m, m.getConnectionHeader());
      ++n;
    }
    out.close();
    fsync_file(tmp);
  } catch (const std::exception& e) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw RecorderBagError(out_path + ": merging the chunks failed (" + e.what() +
                           "); the chunks are kept in " + parts_dir_of(out_path) + ", --resume merges them");
  }
  std::error_code ec;
  fs::rename(tmp, out_path, ec);
  if (ec) throw RecorderBagError(out_path + ": cannot replace it with the merged bag: " + ec.message());
  fsync_parent(out_path);
  return n;
}

}  // namespace piezo::ros_io
