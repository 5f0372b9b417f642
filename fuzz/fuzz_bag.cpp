// libFuzzer target for the bag reader (ros_io::read_bag, the rosbag side of every data file): any bytes must
// give a data set or io::DataError naming the file; a sanitizer report, a crash inside rosbag, an undocumented
// exception, a huge allocation or a hang is a finding. The input is handed over as a file (memfd).
#include <sys/mman.h>
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/ros/data_file.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const int fd = memfd_create("fuzz_bag", 0);
  if (fd < 0) return 0;
  for (std::size_t done = 0; done < size;) {
    const ssize_t n = write(fd, data + done, size - done);
    if (n <= 0) break;
    done += static_cast<std::size_t>(n);
  }
  try {
    const auto d = piezo::ros_io::read_bag("/proc/self/fd/" + std::to_string(fd));
    (void)d.size();
  } catch (const piezo::io::DataError&) {
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fuzz_bag: undocumented exception: %s\n", e.what());
    std::abort();
  }
  close(fd);
  return 0;
}
