// Bag reader/writer for the shared data layout (include/piezo_compensation/ros/data_file.h, docs/data_formats.md).
#include <piezo_compensation/AuxSignal.h>
#include <piezo_compensation/AxisVoltage.h>
#include <piezo_compensation/EncoderPosition.h>
#include <piezo_compensation/ProtocolPhase.h>
#include <ros/time.h>
#include <rosbag/bag.h>
#include <rosbag/view.h>
#include <std_msgs/String.h>
#include <roslz4/lz4s.h>
#include <bzlib.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <functional>
#include <iomanip>
#include <limits>
#include <map>
#include <set>
#include <sstream>

#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/io/message_rows.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/ros/data_file.h"

namespace piezo::ros_io {

namespace {

constexpr double kNmPerM = 1e9;

std::string join_ns(const std::string& ns, const std::string& rest) {
  if (ns.empty() || ns == "/") return "/" + rest;
  return (ns.front() == '/' ? ns : "/" + ns) + (ns.back() == '/' ? "" : "/") + rest;
}

ros::Time stamp_of(double t_s) {
  // Header stamps carry the data's own time; ros::Time cannot be negative.
  return ros::Time(std::max(0.0, t_s));
}

ros::Time bag_time(double t_s) {
  const ros::Time t = stamp_of(t_s);
  return t < ros::TIME_MIN ? ros::TIME_MIN : t;  // rosbag refuses time 0
}

std::string detect_ns(rosbag::Bag& bag, const std::string& path) {
  rosbag::View all(bag);
  std::set<std::string> found;
  for (const rosbag::ConnectionInfo* c : all.getConnections()) {
    for (const char* ax : io::kAxisNames) {
      const std::string suffix = std::string("/") + ax + "/encoder";
      const std::string& topic = c->topic;
      if (topic.size() >= suffix.size() && topic.compare(topic.size() - suffix.size(), suffix.size(), suffix) == 0)
        found.insert(topic.substr(0, topic.size() - suffix.size()));
    }
  }
  if (found.empty()) throw io::DataError(path + ": no <ns>/<axis>/encoder topic (axis a, b or c) in the bag");
  if (found.size() > 1) {
    std::string list;
    for (const auto& f : found) list += (list.empty() ? "" : ", ") + (f.empty() ? std::string("/") : f);
    throw io::DataError(path + ": the bag holds several manipulators (" + list + "); choose one namespace");
  }
  return *found.begin();
}

template <class Msg>
boost::shared_ptr<Msg> instantiate(const rosbag::MessageInstance& m, const std::string& path) {
  auto p = m.instantiate<Msg>();
  if (!p)
    throw io::DataError(path + ": topic " + m.getTopic() + " has type " + m.getDataType() + ", expected " +
                        ros::message_traits::DataType<Msg>::value());
  return p;
}

using Reader = std::function<std::string(std::uint64_t, std::size_t)>;

std::uint64_t u32_at(const std::string& b, std::size_t at) {
  std::uint32_t v = 0;
  for (int i = 3; i >= 0; --i) v = (v << 8) | static_cast<unsigned char>(b[at + i]);
  return std::uint64_t{v};
}

std::uint64_t u64_of(const std::string& b) {
  std::uint64_t v = 0;
  for (int i = 7; i >= 0; --i) v = (v << 8) | static_cast<unsigned char>(b[i]);
  return v;
}

struct BagRecord {
  std::uint64_t at, data_pos, data_len;
  std::map<std::string, std::string> fields;
  char op = 0;
};

// rosbag trusts every length field and every position it reads (a flipped bit asks for gigabytes, an index
// entry into the wrong place of a chunk reads past the chunk buffer: found by fuzz/fuzz_bag.cpp). Before rosbag
// sees the file, walk its records (format 2.0: header length, header, data length, data) and refuse what rosbag
// would not survive: lengths that run past their container (also inside chunks, decompressed as rosbag does),
// fixed-size fields of the wrong size, chunks declared beyond kMaxChunkBytes, connection headers whose fields run
// past them, positions (index_pos, chunk_pos) that are not record starts, and index entries that do not point at
// a message record of the chunk before them.
class BagFileCheck {
 public:
  explicit BagFileCheck(const std::string& path) : path_(path), in_(path, std::ios::binary) {}
  void run();

 private:
  static constexpr std::uint64_t kMaxChunkBytes = 256ull << 20, kMaxHeaderBytes = 1ull << 20;
  // Sequential reads keep the stream's buffer (a plan bag has millions of records).
  std::string read_file(std::uint64_t at, std::size_t n);
  io::DataError bad(std::uint64_t at, const std::string& what) const {
    return io::DataError(path_ + ": not a valid bag: record at byte " + std::to_string(at) + where_ + " " + what +
                         " (a bag cut short may be fixed by `rosbag reindex`)");
  }
  std::map<std::string, std::string> fields_of(std::uint64_t at, const std::string& header, bool fixed_sizes) const;
  void walk(const Reader& read, std::uint64_t pos, std::uint64_t end, const std::function<void(const BagRecord&)>& visit);
  void check_connection(const Reader& read, const BagRecord& r) {
    fields_of(r.at, read(r.data_pos, static_cast<std::size_t>(r.data_len)), false);
  }
  void visit_top(const BagRecord& r);
  void check_chunk(const BagRecord& r);
  void check_index(const BagRecord& r);

  const std::string path_;
  std::ifstream in_;
  std::uint64_t file_size_ = 0, offset_ = 0;
  std::string where_;  // "" at the top level, " (in the chunk at byte N)" inside a chunk
  // Where top-level records start, and the positions rosbag will seek to (index_pos of the file header,
  // chunk_pos of the chunk infos): those must be record starts too.
  std::set<std::uint64_t> starts_;
  std::vector<std::pair<std::uint64_t, std::uint64_t>> seeks_;  // (record, position)
  std::set<std::uint64_t> chunk_messages_;  // offsets of message records in the last chunk (uncompressed)
  bool in_chunk_ = false;
};

std::string BagFileCheck::read_file(std::uint64_t at, std::size_t n) {
  std::string b(n, '\0');
  if (at != offset_) {
    in_.clear();
    in_.seekg(static_cast<std::streamoff>(at));
  }
  in_.read(b.data(), static_cast<std::streamsize>(n));
  if (static_cast<std::size_t>(in_.gcount()) != n) throw io::DataError(path_ + ": read error at byte " + std::to_string(at));
  offset_ = at + n;
  return b;
}

// A header: fields of "length, name=value" (ros::Header::parse reads each length without a bound).
std::map<std::string, std::string> BagFileCheck::fields_of(std::uint64_t at, const std::string& header,
                                                           bool fixed_sizes) const {
  // rosbag copies fixed-size fields without checking their length
  static const std::map<std::string, std::size_t> kFixed = {
      {"op", 1},        {"index_pos", 8}, {"conn_count", 4}, {"chunk_count", 4}, {"conn", 4}, {"time", 8},
      {"ver", 4},       {"chunk_pos", 8}, {"start_time", 8}, {"end_time", 8},    {"count", 4}, {"size", 4}};
  std::map<std::string, std::string> fields;
  for (std::size_t f = 0; f < header.size();) {
    if (header.size() - f < 4) throw bad(at, "has a field cut short");
    const std::uint64_t len = u32_at(header, f);
    f += 4;
    if (len > header.size() - f) throw bad(at, "has a field longer than its header");
    const std::string field = header.substr(f, len);
    f += len;
    const auto eq = field.find('=');
    if (eq == std::string::npos) throw bad(at, "has a header field without '='");
    const std::string name = field.substr(0, eq), value = field.substr(eq + 1);
    const auto fixed = kFixed.find(name);
    if (fixed_sizes && fixed != kFixed.end() && value.size() != fixed->second)
      throw bad(at, "has a " + std::to_string(value.size()) + "-byte field " + name + " (expected " +
                        std::to_string(fixed->second) + ")");
    fields[name] = value;
  }
  return fields;
}

// Walks the records in [pos, end) of `read`; throws on a length that runs past it.
void BagFileCheck::walk(const Reader& read, std::uint64_t pos, std::uint64_t end,
                        const std::function<void(const BagRecord&)>& visit) {
  while (pos < end) {
    BagRecord r;
    r.at = pos;
    if (end - pos < 4) throw bad(r.at, "is cut short");
    const std::uint64_t header_len = u32_at(read(pos, 4), 0);
    pos += 4;
    if (header_len > end - pos || header_len > kMaxHeaderBytes)
      throw bad(r.at, "claims a " + std::to_string(header_len) + "-byte header");
    r.fields = fields_of(r.at, read(pos, header_len), true);
    pos += header_len;
    if (end - pos < 4) throw bad(r.at, "has no data length");
    r.data_len = u32_at(read(pos, 4), 0);
    pos += 4;
    if (r.data_len > end - pos) throw bad(r.at, "claims " + std::to_string(r.data_len) + " bytes of data");
    r.data_pos = pos;
    const auto op = r.fields.find("op");
    if (op != r.fields.end()) r.op = op->second[0];
    visit(r);
    pos += r.data_len;
  }
}

// A chunk: its records, as rosbag sees them after decompression.
void BagFileCheck::check_chunk(const BagRecord& r) {
  const auto size = r.fields.find("size");
  const auto compression = r.fields.find("compression");
  if (size == r.fields.end() || compression == r.fields.end()) throw bad(r.at, "is a chunk without size or compression");
  const std::uint64_t chunk_size = u32_at(size->second, 0);
  if (chunk_size > kMaxChunkBytes) throw bad(r.at, "declares a chunk of " + std::to_string(chunk_size) + " bytes");
  chunk_messages_.clear();
  in_chunk_ = true;
  std::string buffer;
  Reader read_chunk;
  std::uint64_t base = r.data_pos;
  if (compression->second == "none") {
    if (r.data_len != chunk_size) throw bad(r.at, "is an uncompressed chunk whose size is not its data length");
    read_chunk = [this](std::uint64_t at, std::size_t n) { return read_file(at, n); };
  } else {
    std::string packed = read_file(r.data_pos, static_cast<std::size_t>(r.data_len));
    buffer.assign(static_cast<std::size_t>(chunk_size), '\0');
    bool ok = false;
    if (compression->second == "lz4") {
      unsigned int out_size = static_cast<unsigned int>(chunk_size);
      ok = roslz4_buffToBuffDecompress(packed.data(), static_cast<unsigned int>(packed.size()), buffer.data(),
                                       &out_size) == ROSLZ4_OK &&
           out_size == chunk_size;
    } else if (compression->second == "bz2") {
      unsigned int out_size = static_cast<unsigned int>(chunk_size);
      ok = BZ2_bzBuffToBuffDecompress(buffer.data(), &out_size, packed.data(), static_cast<unsigned int>(packed.size()),
                                      0, 0) == BZ_OK &&
           out_size == chunk_size;
    } else {
      throw bad(r.at, "is a chunk compressed with '" + compression->second + "' (rosbag knows none, lz4, bz2)");
    }
    if (!ok) throw bad(r.at, "is a " + compression->second + " chunk that does not decompress to its size");
    read_chunk = [&buffer, this](std::uint64_t at, std::size_t n) {
      if (at > buffer.size() || n > buffer.size() - at) throw io::DataError(path_ + ": chunk read out of range");
      return buffer.substr(static_cast<std::size_t>(at), n);
    };
    base = 0;
  }
  where_ = " (in the chunk at byte " + std::to_string(r.at) + ")";
  walk(read_chunk, base, base + chunk_size, [&](const BagRecord& c) {
    if (c.op == '\x02') chunk_messages_.insert(c.at - base);
    else if (c.op == '\x07') check_connection(read_chunk, c);
    else throw bad(c.at, "is neither a message nor a connection record");
  });
  where_.clear();
}

// Index data of the chunk before it: entries (time, offset into the chunk).
void BagFileCheck::check_index(const BagRecord& r) {
  const auto ver = r.fields.find("ver"), count = r.fields.find("count");
  if (ver == r.fields.end() || count == r.fields.end() || u32_at(ver->second, 0) != 1)
    throw bad(r.at, "is an index record without count or of a version other than 1");
  if (!in_chunk_) throw bad(r.at, "is an index record before any chunk");
  if (u32_at(count->second, 0) * 12 != r.data_len) throw bad(r.at, "is an index record whose count is not its length");
  const std::string entries = read_file(r.data_pos, static_cast<std::size_t>(r.data_len));
  for (std::size_t e = 0; e < entries.size(); e += 12)
    if (!chunk_messages_.count(u32_at(entries, e + 8)))
      throw bad(r.at, "has an index entry to byte " + std::to_string(u32_at(entries, e + 8)) +
                          " of its chunk, which is not the start of a message record");
}

void BagFileCheck::visit_top(const BagRecord& r) {
  starts_.insert(r.at);
  for (const char* name : {"index_pos", "chunk_pos"}) {
    const auto f = r.fields.find(name);
    if (f != r.fields.end()) seeks_.emplace_back(r.at, u64_of(f->second));
  }
  if (r.op == '\x05') {
    check_chunk(r);
  } else if (r.op == '\x04') {
    check_index(r);
  } else if (r.op == '\x07') {
    check_connection([this](std::uint64_t at, std::size_t n) { return read_file(at, n); }, r);
  } else if (r.op == '\x06') {  // chunk info: (connection, count) pairs
    const auto count = r.fields.find("count");
    if (count != r.fields.end() && u32_at(count->second, 0) * 8 != r.data_len)
      throw bad(r.at, "is a chunk info whose count is not its length");
  }
}

void BagFileCheck::run() {
  if (!in_) return;  // rosbag's open says what is wrong
  in_.seekg(0, std::ios::end);
  file_size_ = static_cast<std::uint64_t>(in_.tellg());
  in_.seekg(0);
  // rosbag takes any first line it can scan as "#ROS... V<major>.<minor>"; the records start after it
  const std::string head = read_file(0, static_cast<std::size_t>(std::min<std::uint64_t>(file_size_, 4096)));
  if (head.rfind("#ROS", 0) != 0) return;  // rosbag says what it is (or is not)
  const auto newline = head.find('\n');
  if (newline == std::string::npos || newline > 64) throw bad(0, "has no version line");
  const Reader read = [this](std::uint64_t at, std::size_t n) { return read_file(at, n); };
  walk(read, newline + 1, file_size_, [this](const BagRecord& r) { visit_top(r); });
  for (const auto& [at, target] : seeks_)
    if (target != file_size_ && !starts_.count(target))
      throw bad(at, "points at byte " + std::to_string(target) + ", which is not the start of a record");
}

}  // namespace

void check_bag_file(const std::string& path) { BagFileCheck(path).run(); }

namespace {

// The messages of one manipulator's data topics in a bag (io/message_rows.h makes the rows).
void read_messages(rosbag::Bag& bag, const std::string& path, const std::string& ns, io::RecordedMessages& out,
                   std::string& origin) {
  std::map<std::string, int> topic_kind;  // 0..8 axis topics, 9 aux, 10 phase, 11 data origin
  for (int k = 0; k < 3; ++k) {
    topic_kind[join_ns(ns, std::string(io::kAxisNames[k]) + "/voltage")] = k * 3 + 0;
    topic_kind[join_ns(ns, std::string(io::kAxisNames[k]) + "/encoder")] = k * 3 + 1;
    topic_kind[join_ns(ns, std::string(io::kAxisNames[k]) + "/true_position")] = k * 3 + 2;
  }
  topic_kind[join_ns(ns, "aux")] = 9;
  topic_kind[join_ns(ns, "protocol_phase")] = 10;
  topic_kind[join_ns(ns, "data_origin")] = 11;
  std::vector<std::string> topics;
  for (const auto& kv : topic_kind) topics.push_back(kv.first);
  rosbag::View view(bag, rosbag::TopicQuery(topics));
  std::size_t n_msg = 0;
  for (const rosbag::MessageInstance& m : view) {
    ++n_msg;
    const int kind = topic_kind.at(m.getTopic());
    const std::string where = path + ": topic " + m.getTopic() + ", message " + std::to_string(n_msg);
    if (kind < 9) {
      const int k = kind / 3, what = kind % 3;
      io::StampedValue s;
      if (what == 0) {
        auto msg = instantiate<piezo_compensation::AxisVoltage>(m, path);
        s = {msg->header.stamp.toSec(), msg->sequence, msg->voltage, true};
      } else {
        auto msg = instantiate<piezo_compensation::EncoderPosition>(m, path);
        s = {msg->header.stamp.toSec(), msg->sequence, msg->position * kNmPerM, static_cast<bool>(msg->valid)};
      }
      if (!std::isfinite(s.value)) throw io::DataError(where + ": value is not finite");
      io::AxisMessages& ax = out.axes[k];
      (what == 0 ? ax.voltage : what == 1 ? ax.encoder : ax.truth).push_back(s);
    } else if (kind == 9) {
      auto msg = instantiate<piezo_compensation::AuxSignal>(m, path);
      if (msg->name.empty()) throw io::DataError(where + ": aux signal without a name");
      if (!std::isfinite(msg->value)) throw io::DataError(where + ": aux signal " + msg->name + " is not finite");
      out.aux[msg->name].push_back({msg->header.stamp.toSec(), 0, msg->value, true});
    } else if (kind == 11) {
      origin = instantiate<std_msgs::String>(m, path)->data;
      if (origin != io::kOriginSimulated && origin != io::kOriginRecorded)
        throw io::DataError(where + ": data origin '" + origin + "': expected simulated or recorded");
    } else {
      auto msg = instantiate<piezo_compensation::ProtocolPhase>(m, path);
      int phase = 0;
      try {
        phase = static_cast<int>(protocols::phase_from_name(msg->phase));
      } catch (const std::invalid_argument& e) {
        throw io::DataError(where + ": " + e.what());
      }
      out.markers.push_back({msg->header.stamp.toSec(), {static_cast<int>(msg->segment), phase}});
    }
  }
}

io::Dataset read_bag_impl(const std::string& path, const BagOptions& options, std::vector<std::uint32_t>* row_sequences) {
  check_bag_file(path);
  rosbag::Bag bag;
  try {
    bag.open(path, rosbag::bagmode::Read);
  } catch (const rosbag::BagException& e) {
    throw io::DataError(path + ": cannot open bag: " + e.what() + " (a bag cut short may be fixed by `rosbag reindex`)");
  }
  const std::string ns = options.ns.empty() ? detect_ns(bag, path) : options.ns;
  io::RecordedMessages b;
  b.source = path;
  b.ns = ns;
  std::string origin;
  try {
    read_messages(bag, path, ns, b, origin);
  } catch (const rosbag::BagException& e) {
    throw io::DataError(path + ": broken bag: " + e.what());
  }
  io::MessageRowOptions o;
  o.gaps = options.gaps;
  o.row_sequences = row_sequences;
  io::Dataset d = io::dataset_from_messages(std::move(b), o);
  d.origin = origin;
  return d;
}

}  // namespace

io::Dataset read_bag(const std::string& path, const BagOptions& options, std::vector<std::uint32_t>* row_sequences) {
  try {
    return read_bag_impl(path, options, row_sequences);
  } catch (const io::DataError&) {
    throw;
  } catch (const std::exception& e) {  // rosbag and message deserialisation errors on a damaged file
    throw io::DataError(path + ": broken bag: " + e.what());
  }
}

void write_data_origin(rosbag::Bag& bag, const std::string& ns, const std::string& origin, const ros::Time& when) {
  std_msgs::String m;
  m.data = origin;
  bag.write(join_ns(ns, "data_origin"), when, m);
}

void write_bag(const std::string& path, const io::Dataset& data, const BagOptions& options) {
  data.validate();
  if (data.empty()) throw io::DataError(path + ": nothing to write (empty data set)");
  if (!ros::Time::isValid()) ros::Time::init();
  for (double t : data.time_s)
    if (t < 0.0) throw io::DataError(path + ": column time_s: bags cannot hold negative times");
  rosbag::Bag bag;
  try {
    bag.open(path, rosbag::bagmode::Write);
    bag.setCompression(rosbag::compression::LZ4);
    const std::string frame = "base";
    if (!data.origin.empty()) write_data_origin(bag, options.ns, data.origin, bag_time(data.time_s.front()));
    int last_segment = -1, last_phase = -1;
    for (std::size_t i = 0; i < data.size(); ++i) {
      const ros::Time stamp = stamp_of(data.time_s[i]);
      const ros::Time when = bag_time(data.time_s[i]);
      const auto seq = static_cast<std::uint32_t>(i);
      if (!data.segment.empty() || !data.phase.empty()) {
        const int seg = data.segment.empty() ? 0 : data.segment[i];
        const int ph = data.phase.empty() ? 0 : data.phase[i];
        if (seg != last_segment || ph != last_phase) {
          piezo_compensation::ProtocolPhase m;
          m.header.stamp = stamp;
          m.header.seq = seq;
          // Data built from a protocol carry its name in `source` ("protocol <name>").
          m.protocol = data.source.rfind("protocol ", 0) == 0 ? data.source.substr(9) : std::string();
          m.phase = protocols::phase_name(static_cast<protocols::Phase>(ph));
          m.segment = static_cast<std::uint32_t>(seg);
          m.sample_index = i;
          bag.write(join_ns(options.ns, "protocol_phase"), when, m);
          last_segment = seg, last_phase = ph;
        }
      }
      for (const auto& ax : data.axes) {
        piezo_compensation::AxisVoltage v;
        v.header.stamp = stamp;
        v.header.frame_id = frame;
        v.axis = ax.name;
        v.sequence = seq;
        v.voltage = ax.voltage_v[i];
        bag.write(join_ns(options.ns, ax.name + "/voltage"), when, v);
        piezo_compensation::EncoderPosition e;
        e.header.stamp = stamp;
        e.header.frame_id = frame;
        e.axis = ax.name;
        e.sequence = seq;
        e.position = ax.position_nm[i] / kNmPerM;
        e.valid = true;
        bag.write(join_ns(options.ns, ax.name + "/encoder"), when, e);
        if (ax.has_truth()) {
          e.position = ax.true_position_nm[i] / kNmPerM;
          bag.write(join_ns(options.ns, ax.name + "/true_position"), when, e);
        }
      }
      for (const auto& s : data.aux) {
        piezo_compensation::AuxSignal a;
        a.header.stamp = stamp;
        a.name = s.name;
        a.value = s.values[i];
        bag.write(join_ns(options.ns, "aux"), when, a);
      }
    }
    bag.close();
  } catch (const rosbag::BagException& e) {
    throw io::DataError(path + ": cannot write bag: " + e.what());
  }
}

}  // namespace piezo::ros_io
