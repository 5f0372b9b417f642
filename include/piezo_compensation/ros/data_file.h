// Reading and writing data files in either shared format: rosbag (the driver's topics) or CSV.
// Lives on the ROS side because bags need rosbag; the core library only knows CSV.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"

namespace rosbag {
class Bag;
}
namespace ros {
class Time;
}

namespace piezo::ros_io {

// Bag layout (docs/data_formats.md), under an optional manipulator namespace `ns` ("" or e.g. "/mm1"):
//   <ns>/<axis>/voltage        piezo_compensation/AxisVoltage      applied voltage [V]
//   <ns>/<axis>/encoder        piezo_compensation/EncoderPosition  measured position [m]
//   <ns>/<axis>/true_position  piezo_compensation/EncoderPosition  simulator ground truth [m] (optional)
//   <ns>/aux                   piezo_compensation/AuxSignal        auxiliary signals (optional)
//   <ns>/protocol_phase        piezo_compensation/ProtocolPhase    segment/phase markers (optional)
//   <ns>/data_origin           std_msgs/String                     "simulated" or "recorded" (io::Dataset::origin;
//                                                                  optional)
// One data row per encoder reading of the first axis whose sample (same sequence number, within one sample
// period) every other axis has; a sample an axis lost is never filled from a neighbour (docs/data_formats.md).
struct BagOptions {
  std::string ns;  // manipulator namespace; "" = auto-detect the single one in the bag
  // The rows of samples an axis lost are left out and the time column shows the gap; every tool steps a model
  // over it as one sample (io::TimeBase). Rows at the start or end without a partner are cut.
  // gaps (optional): one line per gap inside the data naming the time, the number of samples and the axes that
  // lost them (`piezo info` prints them).
  std::vector<std::string>* gaps = nullptr;
};

// row_sequences (optional): each row's sequence number, the sample every axis' row pairs by (io/sequence_pairer.h).
io::Dataset read_bag(const std::string& path, const BagOptions& options = {},
                     std::vector<std::uint32_t>* row_sequences = nullptr);
// The record structure of a bag checked before rosbag opens it (rosbag trusts every length and position it
// reads; docs/security.md): throws io::DataError naming the file and the record. read_bag calls it.
void check_bag_file(const std::string& path);
void write_bag(const std::string& path, const io::Dataset& data, const BagOptions& options = {});
// The one <ns>/data_origin message (io::Dataset::origin) into an open bag, at `when`.
void write_data_origin(rosbag::Bag& bag, const std::string& ns, const std::string& origin, const ros::Time& when);

// Dispatch on the extension: ".bag" → bag, anything else → CSV. Throws io::DataError with one clear line.
// notes (optional): what the reader found and left as it is (a bag's gaps).
io::Dataset read_data(const std::string& path, std::vector<std::string>* notes = nullptr);
// Several files as the recordings of one data set (io::join_recordings): each its own history and zero. One file is
// read as read_data reads it. notes: each file's notes and what the join left out.
io::Dataset read_recordings(const std::vector<std::string>& paths, std::vector<std::string>* notes = nullptr);
void write_data(const std::string& path, const io::Dataset& data);

}  // namespace piezo::ros_io
