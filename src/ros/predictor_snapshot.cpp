// The predictor's ~snapshot: the buffered last minutes written as a bag in the layout `piezo residual` and
// `piezo eval` read as they are (ros/data_file.h: <ns>/<axis>/voltage, <ns>/<axis>/encoder, <ns>/aux,
// <ns>/data_origin).
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
#include <iomanip>
#include <fstream>
#include <map>
#include <sstream>
#include <stdexcept>
#include <unistd.h>

#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/ros/predictor.h"

namespace fs = std::filesystem;

namespace piezo::predictor {

namespace {

std::string topic(const std::string& ns, const std::string& rest) {
  if (ns.empty() || ns == "/") return "/" + rest;
  return (ns.front() == '/' ? ns : "/" + ns) + (ns.back() == '/' ? "" : "/") + rest;
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
                        const std::string& frame_id, const std::string& origin) {
  if (!ros::Time::isValid()) ros::Time::init();
  const std::string tmp = path + ".part";  // a reader never sees half a bag
  try {
    rosbag::Bag bag(tmp, rosbag::bagmode::Write);
    bag.setCompression(rosbag::compression::LZ4);
    if (!origin.empty()) ros_io::write_data_origin(bag, ns, origin, ros::Time(std::max(s.begin_s, 1e-9)));
    // header stamp: the sample clock; record time: when the message was heard
    const auto put = [&](const std::string& t, double stamp_s, double received_s, auto& m) {
      m.header.stamp = ros::Time(stamp_s);
      m.header.frame_id = frame_id;
      bag.write(topic(ns, t), ros::Time(received_s), m);
    };
    // In record-time order across the streams, as `rosbag record` writes: a reader walks the bag in time, and
    // with the streams one after the other every message read switched chunk and decompresses it again.
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

void PredictorNode::setup_snapshot() {
  compensation::SnapshotOptions so;
  so.duration_s = s_.snapshot_duration_s;
  so.max_messages = static_cast<std::size_t>(s_.snapshot_max_messages);
  so.expected_rate_hz = 0.0;  // the fastest axis' step rate
  for (const auto& a : axes_) {
    so.axes.push_back(a->logic->axis());
    so.expected_rate_hz = std::max(so.expected_rate_hz, step_rate_hz(s_, a->logic->compensator().model()));
  }
  if (!(so.expected_rate_hz > 0.0)) so.expected_rate_hz = kFallbackSampleRateHz;
  for (const auto& [name, topic] : s_.aux_topics) so.aux.push_back(name);
  snapshot_ = std::make_unique<compensation::SnapshotBuffer>(so);
}

bool PredictorNode::on_snapshot(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  try {
    // the offline tools refuse a time column with missing samples: a stretch without one is written
    const auto& so = snapshot_->options();
    const compensation::SnapshotStretch cut =
        compensation::gap_free_stretch(snapshot_->take(), so.prefer_recent_fraction, so.min_fraction);
    const compensation::Snapshot& snap = cut.snapshot;
    const std::string path = snapshot_path(snapshot_directory(s_.snapshot_dir), snap.end_s);
    write_snapshot_bag(path, nh_.getNamespace(), snap, s_.frame_prefix + "base", data_origin());
    std::size_t readings = 0;
    for (const auto& [axis, a] : snap.axes) readings += a.readings.size();
    std::ostringstream os;
    os << path << " (" << std::fixed << std::setprecision(1) << snap.end_s - snap.begin_s << " s, "
       << snap.axes.size() << " axes, " << readings << " readings, " << snap.aux.size() << " aux signals, "
       << std::setprecision(4) << snap.period_s * 1e3 << " ms sample clock, receive stamps within "
       << snap.max_restamp_s * 1e3 << " ms of it";
    if (snap.invalid_readings > 0) os << ", " << snap.invalid_readings << " invalid readings left out";
    os << ")";
    if (!cut.message.empty()) os << "; " << cut.message;
    res.success = true;
    res.message = os.str();
    if (cut.message.empty()) ROS_INFO("snapshot: %s", res.message.c_str());
    else ROS_WARN("snapshot: %s", res.message.c_str());
  } catch (const std::exception& e) {
    res.success = false;
    res.message = std::string("no snapshot written: ") + e.what();
    ROS_ERROR("%s", res.message.c_str());
  }
  return true;
}

}  // namespace piezo::predictor
