#include "piezo_compensation/nanocontrol/pseudo_terminal.h"

#include <fcntl.h>
#include <stdlib.h>
#include <sys/stat.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <stdexcept>

namespace piezo::nanocontrol {

namespace {
std::runtime_error nc_pty_error(const std::string& link, const std::string& what) {
  return std::runtime_error("pseudo-terminal " + link + ": " + what + ": " + std::strerror(errno));
}
}  // namespace

PseudoTerminal::PseudoTerminal(std::string link_path) : link_(std::move(link_path)) {
  if (link_.empty()) throw std::runtime_error("pseudo-terminal: empty link path");
  struct stat st {};
  if (lstat(link_.c_str(), &st) == 0 && !S_ISLNK(st.st_mode))
    throw std::runtime_error("pseudo-terminal " + link_ + ": exists and is not a symbolic link; not replaced");
  reappear();
}

PseudoTerminal::~PseudoTerminal() { vanish(); }

void PseudoTerminal::vanish() {
  if (master_ < 0) return;
  ::unlink(link_.c_str());
  ::close(slave_hold_);
  ::close(master_);
  master_ = slave_hold_ = -1;
  slave_.clear();
}

void PseudoTerminal::reappear() {
  if (master_ >= 0) return;
  const int m = posix_openpt(O_RDWR | O_NOCTTY | O_CLOEXEC);
  if (m < 0) throw nc_pty_error(link_, "posix_openpt");
  if (grantpt(m) != 0 || unlockpt(m) != 0) {
    ::close(m);
    throw nc_pty_error(link_, "grantpt/unlockpt");
  }
  char name[128];
  if (ptsname_r(m, name, sizeof name) != 0) {
    ::close(m);
    throw nc_pty_error(link_, "ptsname_r");
  }
  const int s = ::open(name, O_RDWR | O_NOCTTY | O_CLOEXEC);
  if (s < 0) {
    ::close(m);
    throw nc_pty_error(link_, std::string("open ") + name);
  }
  termios t{};
  tcgetattr(s, &t);
  cfmakeraw(&t);
  tcsetattr(s, TCSANOW, &t);
  const int flags = fcntl(m, F_GETFL);
  fcntl(m, F_SETFL, flags | O_NONBLOCK);
  // Atomically (re)point the link: a new link beside it, renamed over it.
  const std::string tmp = link_ + ".new";
  ::unlink(tmp.c_str());
  if (symlink(name, tmp.c_str()) != 0 || rename(tmp.c_str(), link_.c_str()) != 0) {
    const auto e = nc_pty_error(link_, "symlink");
    ::close(s);
    ::close(m);
    throw e;
  }
  master_ = m;
  slave_hold_ = s;
  slave_ = name;
}

}  // namespace piezo::nanocontrol
