#include "piezo_compensation/nanocontrol/serial_port.h"

#include <fcntl.h>
#include <poll.h>
#include <sys/file.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>

#include "piezo_compensation/can/transport.h"

namespace piezo::nanocontrol {

namespace {
speed_t nc_speed(int baud) {
  switch (baud) {
    case 9600: return B9600;
    case 19200: return B19200;
    case 38400: return B38400;
    case 57600: return B57600;
    case 115200: return B115200;
    case 230400: return B230400;
    case 460800: return B460800;
    case 921600: return B921600;
    default: return B0;
  }
}

double nc_steady_s() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}
}  // namespace

bool supported_baud(int baud) { return nc_speed(baud) != B0; }

void SerialPort::lost(const std::string& what, int err) {
  const std::string text = "nanocontrol " + path_ + ": " + what + (err ? std::string(": ") + std::strerror(err) : "");
  close();
  throw can::TransportError(text);
}

void SerialPort::open(const std::string& path, int baud) {
  close();
  path_ = path;
  if (!supported_baud(baud)) throw can::TransportError("nanocontrol " + path + ": unsupported baud " + std::to_string(baud));
  fd_ = ::open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  if (fd_ < 0) lost("cannot open", errno);
  if (!isatty(fd_)) lost("is not a serial port (not a tty)", 0);
  if (flock(fd_, LOCK_EX | LOCK_NB) != 0) lost("in use by another process (flock)", errno);
  termios t{};
  if (tcgetattr(fd_, &t) != 0) lost("tcgetattr", errno);
  cfmakeraw(&t);
  t.c_cflag &= ~static_cast<tcflag_t>(PARENB | CSTOPB | CSIZE | CRTSCTS);
  t.c_cflag |= CS8 | CLOCAL | CREAD;
  t.c_iflag &= ~static_cast<tcflag_t>(IXON | IXOFF | IXANY);
  t.c_cc[VMIN] = 0;
  t.c_cc[VTIME] = 0;
  if (cfsetispeed(&t, nc_speed(baud)) != 0 || cfsetospeed(&t, nc_speed(baud)) != 0) lost("cfsetspeed", errno);
  if (tcsetattr(fd_, TCSANOW, &t) != 0) lost("tcsetattr", errno);
  tcflush(fd_, TCIOFLUSH);
}

void SerialPort::close() {
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
}

void SerialPort::write_all(const std::string& bytes, double timeout_s) {
  if (fd_ < 0) throw can::TransportError("nanocontrol " + path_ + ": port not open");
  const double deadline = nc_steady_s() + timeout_s;
  std::size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd_, bytes.data() + done, bytes.size() - done);
    if (n > 0) {
      done += static_cast<std::size_t>(n);
      continue;
    }
    if (n < 0 && errno != EAGAIN && errno != EINTR) lost("write failed (port lost)", errno);
    const double left = deadline - nc_steady_s();
    if (left <= 0) lost("write did not finish within " + std::to_string(timeout_s) + " s", 0);
    pollfd p{fd_, POLLOUT, 0};
    if (poll(&p, 1, static_cast<int>(std::ceil(left * 1000))) < 0 && errno != EINTR) lost("poll", errno);
    if (p.revents & (POLLERR | POLLHUP | POLLNVAL)) lost("port lost (hang-up)", 0);
  }
}

std::size_t SerialPort::read_some(std::string& out, double timeout_s) {
  if (fd_ < 0) throw can::TransportError("nanocontrol " + path_ + ": port not open");
  pollfd p{fd_, POLLIN, 0};
  const int ms = timeout_s <= 0 ? 0 : static_cast<int>(std::ceil(timeout_s * 1000));
  const int r = poll(&p, 1, ms);
  if (r < 0) {
    if (errno == EINTR) return 0;
    lost("poll", errno);
  }
  if (r == 0) return 0;
  if (p.revents & POLLNVAL) lost("port closed", 0);
  char buf[512];
  const ssize_t n = ::read(fd_, buf, sizeof buf);
  if (n > 0) {
    out.append(buf, static_cast<std::size_t>(n));
    return static_cast<std::size_t>(n);
  }
  if (n == 0 || (p.revents & (POLLERR | POLLHUP))) lost("port lost (hang-up)", n < 0 ? errno : 0);
  if (errno == EAGAIN || errno == EINTR) return 0;
  lost("read failed (port lost)", errno);
}

void SerialPort::flush_input() {
  if (fd_ >= 0) tcflush(fd_, TCIFLUSH);
}

}  // namespace piezo::nanocontrol
