// libFuzzer target for the bag reader (ros_io::read_bag, the rosbag side of every data file): any bytes must
// give a data set or io::DataError naming the file; a sanitizer report, a crash inside rosbag, an undocumented
// exception, a huge allocation or a hang is a finding. The input is handed over as a file (memfd).
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "fuzz_input.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/ros/data_file.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const piezo::fuzz::InputFile input(data, size);
  if (!input.ok()) return 0;
  try {
    const auto d = piezo::ros_io::read_bag(input.path());
    (void)d.size();
  } catch (const piezo::io::DataError&) {
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fuzz_bag: undocumented exception: %s\n", e.what());
    std::abort();
  }
  return 0;
}
