// A pseudo-terminal (posix_openpt) for the simulated NanoControl, reachable at a fixed path: a symbolic link to the
// slave device, as udev's /dev/serial/by-id links are to a USB port. vanish() closes the master, so the driver's
// port fails with EIO/hang-up and the link disappears, as when the cable is pulled; reappear() makes a new pair
// and points the link at it. The slave is kept open here too, so the master never sees a hang-up between two
// driver connections, and it is set raw (no echo, CR kept) before anyone else opens it.
#pragma once

#include <string>

namespace piezo::nanocontrol {

class PseudoTerminal {
 public:
  // Creates the pair and the link. Throws std::runtime_error naming the path (a non-link file there is never
  // replaced).
  explicit PseudoTerminal(std::string link_path);
  ~PseudoTerminal();
  PseudoTerminal(const PseudoTerminal&) = delete;
  PseudoTerminal& operator=(const PseudoTerminal&) = delete;

  void vanish();     // master closed, link removed
  void reappear();   // a new pair, the link points at it
  bool present() const { return master_ >= 0; }
  int master_fd() const { return master_; }
  const std::string& link_path() const { return link_; }
  const std::string& slave_path() const { return slave_; }

 private:
  std::string link_;
  std::string slave_;
  int master_ = -1, slave_hold_ = -1;
};

}  // namespace piezo::nanocontrol
