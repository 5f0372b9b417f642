// A serial port through termios: raw 8N1, no flow control, non-blocking with poll() for every wait. A lost port
// (USB unplugged, pseudo-terminal master closed: EIO, hang-up) throws can::TransportError naming the port. An
// advisory flock() keeps two drivers off one port.
#pragma once

#include <string>

namespace piezo::nanocontrol {

// The termios speeds accepted: 9600 … 921600.
bool supported_baud(int baud);

class SerialPort {
 public:
  SerialPort() = default;
  ~SerialPort() { close(); }
  SerialPort(const SerialPort&) = delete;
  SerialPort& operator=(const SerialPort&) = delete;

  // Throws can::TransportError ("nanocontrol /dev/ttyUSB0: cannot open: No such file or directory").
  void open(const std::string& path, int baud);
  void close();
  bool is_open() const { return fd_ >= 0; }
  // Writes all bytes within timeout_s; throws TransportError when the port is lost or the write does not finish.
  void write_all(const std::string& bytes, double timeout_s);
  // Waits up to timeout_s for bytes and appends what is available; returns the number appended (0: none came).
  // Throws TransportError when the port is lost.
  std::size_t read_some(std::string& out, double timeout_s);
  // Discards what the kernel holds unread.
  void flush_input();
  const std::string& path() const { return path_; }

 private:
  [[noreturn]] void lost(const std::string& what, int err);
  int fd_ = -1;
  std::string path_;
};

}  // namespace piezo::nanocontrol
