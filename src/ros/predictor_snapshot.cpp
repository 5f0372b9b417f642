// The predictor's ~snapshot: the buffered last minutes written as a bag in the layout `piezo residual` and
// `piezo eval` read as they are (ros/data_file.h: <ns>/<axis>/voltage, <ns>/<axis>/encoder, <ns>/aux).
#include <piezo_compensation/AuxSignal.h>
#include <piezo_compensation/AxisVoltage.h>
#include <piezo_compensation/EncoderPosition.h>
#include <rosbag/bag.h>

#include <algorithm>
#include <functional>
#include <vector>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <stdexcept>
#include <unistd.h>

#include "piezo_compensation/compensation/base_handover.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/ros/predictor.h"

namespace fs = std::filesystem;

namespace piezo::predictor {

namespace {

std::string topic(const std::string& ns, const std::string& rest) {
  if (ns.empty() || ns == "/") return "/" + rest;
  return (ns.front() == '/' ? ns : "/" + ns) + (ns.back() == '/' ? "" : "/") + rest;
}

// AugmentedModel::set_base_trace for one scope: the trace is cleared on every way out (a stream that throws too).
class BaseTraceScope {
 public:
  BaseTraceScope(models::AugmentedModel* m, std::vector<double>* trace) : m_(m) {
    if (m_) m_->set_base_trace(trace);
  }
  ~BaseTraceScope() {
    if (m_) m_->set_base_trace(nullptr);
  }
  BaseTraceScope(const BaseTraceScope&) = delete;
  BaseTraceScope& operator=(const BaseTraceScope&) = delete;

 private:
  models::AugmentedModel* m_;
};

// The running base's recorded prediction per row of `d` (NaN where none). Row i is the sample with sequence
// number row_seq[i] on every axis (the reader's pairing); a sample another axis lost has no row, so matching by
// index would shift every later row. A controller restart reuses numbers: of equal numbers, the axis' reading on
// the sample clock nearest the row, and the prediction stamped nearest its receive stamp (the same stamp).
std::vector<double> running_base_per_row(const compensation::Snapshot::Axis& ax, const io::Dataset& d,
                                         const std::vector<std::uint32_t>& row_seq) {
  constexpr double kSameSampleS = 1.0;  // as SnapshotBuffer::take pairs a report with its reading
  std::vector<double> base(d.size(), std::nan(""));
  if (row_seq.size() != d.size()) return base;
  // the one with number `seq` whose stamp(x) is nearest t, within kSameSampleS, or null
  const auto nearest = [](const auto& by_seq, std::uint32_t seq, double t, auto stamp) {
    const auto [lo, hi] = by_seq.equal_range(seq);
    decltype(lo->second) found = nullptr;
    double best = kSameSampleS;
    for (auto it = lo; it != hi; ++it)
      if (const double dt = std::fabs(stamp(*it->second) - t); dt <= best) best = dt, found = it->second;
    return found;
  };
  std::multimap<std::uint32_t, const compensation::SnapshotReading*> readings;
  std::multimap<std::uint32_t, const compensation::SnapshotPrediction*> predictions;
  for (const auto& r : ax.readings) readings.emplace(r.sequence, &r);
  for (const auto& p : ax.base_predictions) predictions.emplace(p.sequence, &p);
  for (std::size_t i = 0; i < d.size(); ++i) {
    const auto* r = nearest(readings, row_seq[i], d.time_s[i], [](const auto& x) { return x.stamp_s; });
    const auto* p = r ? nearest(predictions, row_seq[i], r->received_s, [](const auto& x) { return x.stamp_s; }) : nullptr;
    if (p) base[i] = p->base_nm;
  }
  return base;
}

}  // namespace

std::string snapshot_directory(const std::string& configured) {
  if (!configured.empty()) return configured;
  const char* ros_home = std::getenv("ROS_HOME");
  if (ros_home && *ros_home) return std::string(ros_home) + "/piezo_snapshots";
  const char* home = std::getenv("HOME");
  return std::string(home && *home ? home : "/tmp") + "/.ros/piezo_snapshots";
}

std::string snapshot_path(const std::string& dir, double end_stamp_s) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (!fs::is_directory(dir)) throw std::runtime_error("snapshot directory " + dir + " does not exist and cannot be created" +
                                                       (ec ? ": " + ec.message() : std::string()));
  if (::access(dir.c_str(), W_OK | X_OK) != 0)
    throw std::runtime_error("snapshot directory " + dir + " is not writable: " + std::strerror(errno));
  // named by the (ROS) time of the newest reading, UTC, so under sim time it names the simulated moment
  const std::time_t t = static_cast<std::time_t>(end_stamp_s);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char stamp[32];
  std::strftime(stamp, sizeof stamp, "%Y%m%dT%H%M%SZ", &tm);
  std::string path = dir + "/snapshot_" + stamp + ".bag";
  for (int k = 2; fs::exists(path); ++k) path = dir + "/snapshot_" + stamp + "_" + std::to_string(k) + ".bag";
  return path;
}

void write_snapshot_bag(const std::string& path, const std::string& ns, const compensation::Snapshot& s,
                        const std::string& frame_id) {
  if (!ros::Time::isValid()) ros::Time::init();
  const std::string tmp = path + ".part";  // a reader never sees half a bag
  try {
    rosbag::Bag bag(tmp, rosbag::bagmode::Write);
    bag.setCompression(rosbag::compression::LZ4);
    // header stamp: the sample clock; record time: when the message was heard
    const auto put = [&](const std::string& t, double stamp_s, double received_s, auto& m) {
      m.header.stamp = ros::Time(stamp_s);
      m.header.frame_id = frame_id;
      bag.write(topic(ns, t), ros::Time(received_s), m);
    };
    // In record-time order across the streams, as `rosbag record` writes: a reader walks the bag in time, and
    // with the streams one after the other every message read switched chunk and decompressed it again (a
    // 20-min snapshot took 12.5 s to read instead of 0.1 s).
    std::vector<std::function<void()>> writes;
    std::vector<std::pair<double, std::size_t>> order;
    const auto add = [&](double record_s, std::function<void()> w) {
      order.emplace_back(record_s, writes.size());
      writes.push_back(std::move(w));
    };
    for (const auto& [axis, a] : s.axes) {
      for (const auto& x : a.voltages)
        add(x.received_s, [&, ax = axis, x = x] {
          piezo_compensation::AxisVoltage v;
          v.axis = ax;
          v.sequence = x.sequence;
          v.voltage = x.voltage_v;
          put(ax + "/voltage", x.stamp_s, x.received_s, v);
        });
      for (const auto& x : a.readings)
        add(x.received_s, [&, ax = axis, x = x] {
          piezo_compensation::EncoderPosition e;
          e.axis = ax;
          e.valid = true;
          e.sequence = x.sequence;
          e.position = x.position_nm * 1e-9;
          put(ax + "/encoder", x.stamp_s, x.received_s, e);
        });
    }
    for (const auto& [name, values] : s.aux)
      for (const auto& x : values)
        add(x.stamp_s, [&, nm = name, x = x] {
          piezo_compensation::AuxSignal m;
          m.name = nm;
          m.value = x.value;
          put("aux", x.stamp_s, x.stamp_s, m);
        });
    std::stable_sort(order.begin(), order.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
    for (const auto& [t, k] : order) writes[k]();
    bag.close();
  } catch (const std::exception& e) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw std::runtime_error(path + ": cannot write bag: " + e.what());
  }
  std::error_code ec;
  fs::rename(tmp, path, ec);
  if (ec) throw std::runtime_error(path + ": cannot write bag: " + ec.message());
}

std::string warm_model(models::Model& model, const std::string& axis, const compensation::Snapshot& s,
                       const std::string& ns, const models::Model* running, std::string* handover) {
  if (!s.axes.count(axis)) return "axis " + axis + " not in the buffer";
  // through a bag and the one reader, so the warm-up pairs and aligns samples exactly as `piezo residual` did
  const fs::path tmp = fs::temp_directory_path() / ("piezo_warmup_" + std::to_string(::getpid()) + ".bag");
  try {
    write_snapshot_bag(tmp.string(), ns, s, "base");
    std::vector<std::uint32_t> row_seq;
    const io::Dataset d = ros_io::read_bag(tmp.string(), {}, &row_seq);
    std::error_code ec;
    fs::remove(tmp, ec);
    // on failure the reload resets it (cold)
    auto* aug = dynamic_cast<models::AugmentedModel*>(&model);
    const bool hand_over = running && aug && handover;
    std::vector<double> warm, warm_base;  // the hand-over takes the base part from this one stream
    {
      const BaseTraceScope trace(hand_over ? aug : nullptr, &warm_base);
      warm = models::stream_model(model, d, axis, models::StreamOptions{}).prediction;
    }
    if (hand_over) {
      const auto& ax = s.axes.at(axis);
      const std::vector<double> base = running_base_per_row(ax, d, row_seq);
      const compensation::BaseHandover h = compensation::hand_over_base(*aug, *running, d, axis, warm, warm_base, base);
      std::ostringstream os;
      if (h.done)
        os << "base state from the running model, offset " << std::showpos << h.offset_change_nm << std::noshowpos
           << " nm on " << h.samples << " samples";
      else
        os << "base warmed from rest (" << h.why << ")";
      // readings of this axis without a row: samples another axis lost or has not yet (the reader fills none); the
      // rest are matched by sequence number, so they cost only their own rows
      if (ax.readings.size() > d.size())
        os << " (" << ax.readings.size() - d.size() << " of " << axis << "'s " << ax.readings.size()
           << " readings have no row, their sample missing on another axis; rows matched by sequence number)";
      *handover = os.str();
    }
  } catch (const std::exception& e) {
    std::error_code ec;
    fs::remove(tmp, ec);
    return e.what();
  }
  return "";
}

}  // namespace piezo::predictor
