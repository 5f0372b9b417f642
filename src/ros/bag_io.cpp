// TEMPORARY until the simulator issue lands its bag reader/writer.
#include "piezo_compensation/ros/data_file.h"

namespace piezo::ros_io {
io::Dataset read_bag(const std::string& path, const BagOptions&) {
  throw io::DataError(path + ": reading bags is not implemented yet");
}
void write_bag(const std::string& path, const io::Dataset&, const BagOptions&) {
  throw io::DataError(path + ": writing bags is not implemented yet");
}
}  // namespace piezo::ros_io
