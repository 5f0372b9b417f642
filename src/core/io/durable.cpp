#include "piezo_compensation/io/durable.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>

namespace piezo::io {

std::string fsync_path(const std::string& path, bool directory) {
  const int fd = ::open(path.c_str(), (directory ? O_DIRECTORY : 0) | O_RDONLY | O_CLOEXEC);
  if (fd < 0) return std::string("cannot open to sync: ") + std::strerror(errno);
  const int rc = ::fsync(fd);
  const int err = errno;
  ::close(fd);
  return rc != 0 ? std::string("fsync failed: ") + std::strerror(err) : std::string();
}

std::string fsync_parent(const std::string& path) {
  const std::filesystem::path parent = std::filesystem::absolute(path).parent_path();
  return fsync_path(parent.empty() ? "." : parent.string(), true);
}

}  // namespace piezo::io
