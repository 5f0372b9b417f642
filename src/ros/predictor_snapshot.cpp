// The predictor's ~snapshot: the buffered last minutes written as a bag in the layout `piezo residual` and
// `piezo eval` read as they are (ros/data_file.h: <ns>/<axis>/voltage, <ns>/<axis>/encoder, <ns>/aux).
#include <piezo_compensation/AuxSignal.h>
#include <piezo_compensation/AxisVoltage.h>
#include <piezo_compensation/EncoderPosition.h>
#include <rosbag/bag.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <stdexcept>
#include <unistd.h>

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
    for (const auto& [axis, a] : s.axes) {
      piezo_compensation::AxisVoltage v;
      v.axis = axis;
      for (const auto& x : a.voltages) {
        v.sequence = x.sequence;
        v.voltage = x.voltage_v;
        put(axis + "/voltage", x.stamp_s, x.received_s, v);
      }
      piezo_compensation::EncoderPosition e;
      e.axis = axis;
      e.valid = true;
      for (const auto& x : a.readings) {
        e.sequence = x.sequence;
        e.position = x.position_nm * 1e-9;
        put(axis + "/encoder", x.stamp_s, x.received_s, e);
      }
    }
    for (const auto& [name, values] : s.aux) {
      piezo_compensation::AuxSignal m;
      m.name = name;
      for (const auto& x : values) {
        m.value = x.value;
        put("aux", x.stamp_s, x.stamp_s, m);
      }
    }
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
                       const std::string& ns) {
  if (!s.axes.count(axis)) return "axis " + axis + " not in the buffer";
  // through a bag and the one reader, so the warm-up pairs and aligns samples exactly as `piezo residual` did
  const fs::path tmp = fs::temp_directory_path() / ("piezo_warmup_" + std::to_string(::getpid()) + ".bag");
  try {
    write_snapshot_bag(tmp.string(), ns, s, "base");
    const io::Dataset d = ros_io::read_bag(tmp.string());
    std::error_code ec;
    fs::remove(tmp, ec);
    models::stream_model(model, d, axis, models::StreamOptions{});  // on failure the reload resets it (cold)
  } catch (const std::exception& e) {
    std::error_code ec;
    fs::remove(tmp, ec);
    return e.what();
  }
  return "";
}

}  // namespace piezo::predictor
