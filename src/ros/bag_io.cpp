// Bag reader/writer for the shared data layout (include/piezo_compensation/ros/data_file.h, docs/data_formats.md).
#include <piezo_compensation/AuxSignal.h>
#include <piezo_compensation/AxisVoltage.h>
#include <piezo_compensation/EncoderPosition.h>
#include <piezo_compensation/ProtocolPhase.h>
#include <ros/time.h>
#include <rosbag/bag.h>
#include <rosbag/view.h>
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
#include "piezo_compensation/io/sequence_pairer.h"
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

struct Sample {
  double t = 0.0;
  std::uint32_t seq = 0;
  double value = 0.0;
  bool valid = true;
};

// Messages of one topic, sorted by stamp.
struct Series {
  std::vector<Sample> samples;
  void index() {
    std::stable_sort(samples.begin(), samples.end(), [](const Sample& a, const Sample& b) { return a.t < b.t; });
  }
  const Sample* latest(double t, double period_s) const {
    auto it = std::upper_bound(samples.begin(), samples.end(), t + 1e-9,
                               [](double x, const Sample& s) { return x < s.t; });
    if (it != samples.begin()) return &*(it - 1);
    // Nothing before t: accept the first message if it comes within one sample period.
    if (!samples.empty() && samples.front().t - t <= period_s) return &samples.front();
    return nullptr;
  }
};

// One axis' paired samples (in sequence order), indexed by sequence for the join across axes.
struct Paired {
  std::vector<io::PairedSample> samples;
  std::vector<std::pair<std::uint32_t, std::uint32_t>> by_seq;  // (sequence, index), sorted
  std::uint64_t dropped = 0;
  // The sample with this sequence number within one period of t (a restart or a wrap reuses numbers), or null.
  // Never a neighbour: a sample this axis lost has no value to give.
  const io::PairedSample* match(std::uint32_t seq, double t, double period_s) const {
    auto it = std::lower_bound(by_seq.begin(), by_seq.end(), seq,
                               [](const auto& e, std::uint32_t s) { return e.first < s; });
    for (; it != by_seq.end() && it->first == seq; ++it)
      if (std::fabs(samples[it->second].stamp_s - t) <= period_s) return &samples[it->second];
    return nullptr;
  }
};

Paired pair_axis(const Series& voltage, const Series& encoder, const Series& truth, bool with_truth) {
  io::PairerOptions o;
  o.with_truth = with_truth;
  io::SequencePairer pairer(o);
  Paired out;
  out.samples.reserve(encoder.samples.size());
  const auto take = [&](std::vector<io::PairedSample>&& ps) {
    for (auto& p : ps) out.samples.push_back(p);
  };
  // merge the three streams by stamp; on equal stamps the reports go before the reading
  std::size_t iv = 0, ie = 0, it = 0;
  const double inf = std::numeric_limits<double>::infinity();
  while (ie < encoder.samples.size() || iv < voltage.samples.size() || (with_truth && it < truth.samples.size())) {
    const double tv = iv < voltage.samples.size() ? voltage.samples[iv].t : inf;
    const double tt = with_truth && it < truth.samples.size() ? truth.samples[it].t : inf;
    const double te = ie < encoder.samples.size() ? encoder.samples[ie].t : inf;
    if (tv <= tt && tv <= te) {
      const Sample& s = voltage.samples[iv++];
      take(pairer.add_voltage(s.seq, s.value, s.t));
    } else if (tt <= te) {
      const Sample& s = truth.samples[it++];
      take(pairer.add_truth(s.seq, s.value, s.t));
    } else {
      const Sample& s = encoder.samples[ie++];
      take(pairer.add_reading(s.seq, s.value, s.valid, s.t));
    }
  }
  take(pairer.flush());
  out.dropped = pairer.counters().dropped_samples;
  out.by_seq.resize(out.samples.size());
  for (std::size_t i = 0; i < out.samples.size(); ++i)
    out.by_seq[i] = {out.samples[i].sequence, static_cast<std::uint32_t>(i)};
  std::stable_sort(out.by_seq.begin(), out.by_seq.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  return out;
}

std::string row_col(const std::string& path, std::size_t row, const std::string& col) {
  std::ostringstream os;
  os << path << ": row " << row + 2 << ", column " << col << ": ";
  return os.str();
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

// The messages of one manipulator's data topics in a bag, each topic sorted by stamp.
struct BagMessages {
  Series voltage[3], encoder[3], truth[3];
  bool has_topic[3][3] = {};  // [axis][voltage, encoder, true_position]
  std::map<std::string, Series> aux;
  std::vector<std::pair<double, std::pair<int, int>>> markers;  // stamp → (segment, phase)
  bool has_axis(int k) const { return has_topic[k][1]; }
};

void read_messages(rosbag::Bag& bag, const std::string& path, const std::string& ns, BagMessages& out) {
  std::map<std::string, int> topic_kind;  // 0..8 axis topics, 9 aux, 10 phase
  for (int k = 0; k < 3; ++k) {
    topic_kind[join_ns(ns, std::string(io::kAxisNames[k]) + "/voltage")] = k * 3 + 0;
    topic_kind[join_ns(ns, std::string(io::kAxisNames[k]) + "/encoder")] = k * 3 + 1;
    topic_kind[join_ns(ns, std::string(io::kAxisNames[k]) + "/true_position")] = k * 3 + 2;
  }
  topic_kind[join_ns(ns, "aux")] = 9;
  topic_kind[join_ns(ns, "protocol_phase")] = 10;
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
      out.has_topic[k][what] = true;
      Sample s;
      if (what == 0) {
        auto msg = instantiate<piezo_compensation::AxisVoltage>(m, path);
        s = {msg->header.stamp.toSec(), msg->sequence, msg->voltage, true};
      } else {
        auto msg = instantiate<piezo_compensation::EncoderPosition>(m, path);
        s = {msg->header.stamp.toSec(), msg->sequence, msg->position * kNmPerM, static_cast<bool>(msg->valid)};
      }
      if (!std::isfinite(s.value)) throw io::DataError(where + ": value is not finite");
      (what == 0 ? out.voltage[k] : what == 1 ? out.encoder[k] : out.truth[k]).samples.push_back(s);
    } else if (kind == 9) {
      auto msg = instantiate<piezo_compensation::AuxSignal>(m, path);
      if (msg->name.empty()) throw io::DataError(where + ": aux signal without a name");
      if (!std::isfinite(msg->value)) throw io::DataError(where + ": aux signal " + msg->name + " is not finite");
      out.aux[msg->name].samples.push_back({msg->header.stamp.toSec(), 0, msg->value, true});
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

// Every axis with messages has both voltage and encoder messages; returns the first such axis.
int first_axis(const BagMessages& b, const std::string& path, const std::string& ns) {
  int first = -1;
  for (int k = 0; k < 3; ++k) {
    if (b.has_topic[k][1] != b.has_topic[k][0])
      throw io::DataError(path + ": axis " + io::kAxisNames[k] + " has " + (b.has_topic[k][1] ? "encoder" : "voltage") +
                          " messages but no " + (b.has_topic[k][1] ? join_ns(ns, std::string(io::kAxisNames[k]) + "/voltage")
                                                                    : join_ns(ns, std::string(io::kAxisNames[k]) + "/encoder")));
    if (b.has_topic[k][1] && first < 0) first = k;
  }
  if (first < 0) throw io::DataError(path + ": no encoder messages under namespace '" + ns + "'");
  return first;
}

// The rows of the data set: samples of the first axis joined with every other axis' sample of the same sequence.
struct BagRows {
  Paired paired[3];
  int first = 0;
  std::vector<std::uint32_t> candidates;  // the first axis' samples with a reading
  std::vector<std::uint32_t> row_of;      // row → sample of the first axis
  double period = 1.0;
  const io::PairedSample* partner(int k, std::uint32_t i) const {
    const io::PairedSample& row = paired[first].samples[i];
    return k == first ? &row : paired[k].match(row.sequence, row.stamp_s, period);
  }
  double t(std::size_t r) const { return paired[first].samples[row_of[r]].stamp_s; }
};

// rows: the first axis' samples that have a reading (lost readings have no row) and whose sample every other
// axis has. A sample another axis lost is not filled from a neighbour: its row is left out, so the time column
// shows the gap as when the first axis lost it, which the offline tools step over as one sample (io::TimeBase);
// at the ends (one axis started or stopped a sample later) that cuts the rows without a partner.
void join_rows(const BagMessages& b, const std::string& path, BagRows& rows) {
  const int first = rows.first;
  const auto& samples = rows.paired[first].samples;
  for (std::uint32_t i = 0; i < samples.size(); ++i)
    if (!samples[i].reading_lost) rows.candidates.push_back(i);
  const auto& cand = rows.candidates;
  if (cand.size() >= 2)
    rows.period = (samples[cand.back()].stamp_s - samples[cand.front()].stamp_s) / static_cast<double>(cand.size() - 1);
  if (!(rows.period > 0.0)) rows.period = 1.0;
  std::size_t matched[3] = {};
  for (std::uint32_t i : cand) {
    bool complete = true;
    for (int k = 0; k < 3; ++k) {
      if (!b.has_axis(k)) continue;
      const io::PairedSample* e = rows.partner(k, i);
      if (e) ++matched[k];
      if (!e || e->reading_lost) complete = false;
    }
    if (complete) rows.row_of.push_back(i);
  }
  for (int k = 0; k < 3; ++k)
    if (b.has_axis(k) && k != first && !cand.empty() && matched[k] == 0)
      throw io::DataError(path + ": axis " + io::kAxisNames[k] + ": none of its " +
                          std::to_string(rows.paired[k].samples.size()) + " samples has the sequence number of a reading of axis " +
                          io::kAxisNames[first] + " within one sample period (" + std::to_string(rows.period) +
                          " s) of it: the axes were not recorded together");
}

// Each step of the rows longer than the sample clock (the median step of the first axis' readings; a gap does not
// move it) as one line naming where, how many samples and which axes lost them.
std::vector<std::string> describe_gaps(const BagMessages& b, const BagRows& rows, const std::string& path) {
  std::vector<std::string> out;
  const std::size_t n = rows.row_of.size();
  if (n < 2) return out;
  const auto& first = rows.paired[rows.first].samples;
  std::vector<double> reading_s;
  for (std::uint32_t i : rows.candidates) reading_s.push_back(first[i].stamp_s);
  const double clock_s = io::median_step_s(reading_s);
  for (std::size_t r = 1; clock_s > 0.0 && r < n; ++r) {
    const double step = rows.t(r) - rows.t(r - 1);
    const long missing = std::lround(step / clock_s) - 1;
    if (missing < 1) continue;  // jitter
    // who lost them: per axis, the steps in between without a reading of it (stamps within half a step)
    const io::PairedSample& before = first[rows.row_of[r - 1]];
    long lacking[3] = {};
    for (int k = 0; k < 3; ++k) {
      if (!b.has_axis(k)) continue;
      long heard = 0;
      for (const auto& e : rows.paired[k].samples)
        heard += !e.reading_lost && e.stamp_s > before.stamp_s + 0.5 * clock_s && e.stamp_s < rows.t(r) - 0.5 * clock_s;
      lacking[k] = std::max(0L, missing - heard);
    }
    std::ostringstream os;
    os << path << ": " << missing << " sample(s) missing after t = " << std::fixed << std::setprecision(6)
       << before.stamp_s << " s (row " << r + 1 << ", sequence " << before.sequence << "): ";
    std::string sep;
    for (int k = 0; k < 3; ++k)
      if (lacking[k] > 0) os << sep << "axis " << io::kAxisNames[k] << " lost " << lacking[k], sep = ", ";
    os << "; a model steps over them as one sample, nothing is filled in";
    out.push_back(os.str());
  }
  return out;
}

// Each axis' columns from its paired samples at the rows.
void fill_axes(const BagMessages& b, const BagRows& rows, const std::string& path, io::Dataset& d) {
  const std::size_t n = rows.row_of.size();
  for (int k = 0; k < 3; ++k) {
    if (!b.has_axis(k)) continue;
    auto& ax = d.add_axis(io::kAxisNames[k]);
    const bool with_truth = b.has_topic[k][2];
    if (with_truth) ax.true_position_nm.resize(n);
    for (std::size_t i = 0; i < n; ++i) {
      const io::PairedSample* e = rows.partner(k, rows.row_of[i]);
      if (!e->measured)
        throw io::DataError(row_col(path, i, io::position_column(io::kAxisNames[k])) + "encoder reading flagged invalid");
      ax.position_nm[i] = e->position_nm;
      ax.voltage_v[i] = e->voltage_v;
      if (with_truth) {
        if (!std::isfinite(e->truth_nm))
          throw io::DataError(row_col(path, i, io::true_position_column(io::kAxisNames[k])) + "no message at or before t=" +
                              std::to_string(rows.t(i)) + " s");
        ax.true_position_nm[i] = e->truth_nm;
      }
    }
    if (rows.paired[k].dropped > 0)
      throw io::DataError(path + ": axis " + io::kAxisNames[k] + ": " + std::to_string(rows.paired[k].dropped) +
                          " encoder reading(s) with no voltage message at or before them");
  }
}

// Aux columns (the latest value at each row) and the protocol markers in force at each row.
void fill_aux_and_markers(const BagMessages& b, const BagRows& rows, const std::string& path, io::Dataset& d) {
  const std::size_t n = rows.row_of.size();
  for (const auto& kv : b.aux) {
    io::AuxSignal s{kv.first, std::vector<double>(n)};
    for (std::size_t i = 0; i < n; ++i) {
      const Sample* x = kv.second.latest(rows.t(i), rows.period);
      if (!x) throw io::DataError(row_col(path, i, kv.first) + "no aux message at or before t=" +
                                  std::to_string(rows.t(i)) + " s");
      s.values[i] = x->value;
    }
    d.aux.push_back(std::move(s));
  }
  const auto& markers = b.markers;
  if (markers.empty()) return;
  d.segment.resize(n);
  d.phase.resize(n);
  if (markers.front().first - rows.t(0) > rows.period)
    throw io::DataError(row_col(path, 0, "phase") + "the first protocol_phase marker comes after the first sample");
  std::size_t m = 0;
  for (std::size_t i = 0; i < n; ++i) {
    while (m + 1 < markers.size() && markers[m + 1].first <= rows.t(i) + 1e-9) ++m;
    d.segment[i] = markers[m].second.first;
    d.phase[i] = markers[m].second.second;
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
  BagMessages b;
  try {
    read_messages(bag, path, ns, b);
  } catch (const rosbag::BagException& e) {
    throw io::DataError(path + ": broken bag: " + e.what());
  }
  BagRows rows;
  rows.first = first_axis(b, path, ns);
  for (int k = 0; k < 3; ++k) b.voltage[k].index(), b.encoder[k].index(), b.truth[k].index();
  for (auto& kv : b.aux) kv.second.index();
  std::stable_sort(b.markers.begin(), b.markers.end(), [](const auto& x, const auto& y) { return x.first < y.first; });
  // Each axis' voltage, reading and truth paired by the one rule the live nodes use (io/sequence_pairer.h),
  // fed in receive order as the predictor would have seen them.
  for (int k = 0; k < 3; ++k) {
    if (!b.has_axis(k)) continue;
    rows.paired[k] = pair_axis(b.voltage[k], b.encoder[k], b.truth[k], b.has_topic[k][2]);
    b.voltage[k] = Series(), b.encoder[k] = Series(), b.truth[k] = Series();  // free what the pairing consumed
  }
  join_rows(b, path, rows);
  if (options.gaps) *options.gaps = describe_gaps(b, rows, path);
  const std::size_t n = rows.row_of.size();
  io::Dataset d;
  d.source = path;
  d.time_clock = "ros";  // stamps are ROS time (sim time under use_sim_time)
  d.time_s.resize(n);
  for (std::size_t i = 0; i < n; ++i) d.time_s[i] = rows.t(i);
  if (row_sequences) {
    row_sequences->resize(n);
    for (std::size_t i = 0; i < n; ++i) (*row_sequences)[i] = rows.paired[rows.first].samples[rows.row_of[i]].sequence;
  }
  fill_axes(b, rows, path, d);
  fill_aux_and_markers(b, rows, path, d);
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
