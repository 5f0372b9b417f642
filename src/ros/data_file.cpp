#include "piezo_compensation/ros/data_file.h"

namespace piezo::ros_io {

namespace {
bool is_bag(const std::string& path) { return path.size() >= 4 && path.compare(path.size() - 4, 4, ".bag") == 0; }
}  // namespace

io::Dataset read_data(const std::string& path, std::vector<std::string>* notes) {
  BagOptions bag;
  bag.gaps = notes;
  io::Dataset d = is_bag(path) ? read_bag(path, bag) : io::read_csv(path);
  d.validate();
  return d;
}

io::Dataset read_recordings(const std::vector<std::string>& paths, std::vector<std::string>* notes) {
  if (paths.empty()) throw io::DataError("no data file given");
  std::vector<io::Dataset> parts;
  for (const auto& p : paths) {
    for (const auto& q : paths)
      if (&q < &p && q == p) throw io::DataError(p + ": given twice");
    parts.push_back(read_data(p, notes));
  }
  io::Dataset d = io::join_recordings(parts, notes);
  d.validate();
  return d;
}

void write_data(const std::string& path, const io::Dataset& data) {
  if (is_bag(path))
    write_bag(path, data);
  else
    io::write_csv(path, data);
}

}  // namespace piezo::ros_io
