#include "piezo_compensation/can/transport.h"

#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cstring>

namespace piezo::can {

bool passes_filters(const can_frame& frame, const std::vector<can_filter>& filters) {
  if (filters.empty() || (frame.can_id & CAN_ERR_FLAG)) return true;
  for (const auto& f : filters)
    if ((frame.can_id & f.can_mask) == (f.can_id & f.can_mask)) return true;
  return false;
}

static_assert(sizeof(can_frame) == 16, "the UDP transport carries struct can_frame as 16 bytes");

std::size_t Transport::send_batch(const can_frame* frames, std::size_t count) {
  for (std::size_t i = 0; i < count; ++i)
    if (!send(frames[i])) return i;
  return count;
}

namespace {

std::string errno_text(int err) { return std::strerror(err); }

double timestamp_of(msghdr& msg) {
  for (cmsghdr* c = CMSG_FIRSTHDR(&msg); c != nullptr; c = CMSG_NXTHDR(&msg, c)) {
    if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SCM_TIMESTAMP) {
      timeval tv;
      std::memcpy(&tv, CMSG_DATA(c), sizeof tv);
      return tv.tv_sec + tv.tv_usec * 1e-6;
    }
  }
  timeval now;  // no kernel stamp (should not happen with SO_TIMESTAMP): take the time of reading
  gettimeofday(&now, nullptr);
  return now.tv_sec + now.tv_usec * 1e-6;
}

// Shared socket handling: non-blocking fd, SO_TIMESTAMP, poll + recvmsg until the queue is empty.
class SocketTransport : public Transport {
 public:
  ~SocketTransport() override { close(); }
  void close() override {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
    peer_refused_ = false;
  }
  bool is_open() const override { return fd_ >= 0; }
  std::uint64_t malformed_count() const override { return malformed_; }

  int receive(std::vector<ReceivedFrame>& out, int timeout_ms) override {
    if (fd_ < 0) throw TransportError(describe() + ": not open");
    pollfd p{fd_, POLLIN, 0};
    const int pr = ::poll(&p, 1, timeout_ms);
    if (pr < 0) {
      if (errno == EINTR) return 0;
      throw TransportError(describe() + ": poll failed: " + errno_text(errno));
    }
    if (pr == 0) return 0;
    if (p.revents & (POLLERR | POLLNVAL | POLLHUP)) {
      int err = 0;
      socklen_t len = sizeof err;
      getsockopt(fd_, SOL_SOCKET, SO_ERROR, &err, &len);
      if (p.revents & POLLNVAL) throw TransportError(describe() + ": socket closed");
      if (err != 0 && err != ECONNREFUSED) throw TransportError(describe() + ": " + errno_text(err));
      if (err == ECONNREFUSED) peer_refused_ = true;
      drain_error_queue();
    }
    int n = 0;
    const std::size_t max_frames = frames_per_datagram();
    for (int i = 0; i < 256; ++i) {  // bounded so a flood cannot starve the caller's other work
      // One byte extra so an oversize datagram is detected rather than silently truncated.
      unsigned char buf[kMaxFramesPerDatagram * sizeof(can_frame) + 1];
      iovec iov{buf, max_frames * sizeof(can_frame) + 1};
      alignas(cmsghdr) char control[CMSG_SPACE(sizeof(timeval))];
      msghdr msg{};
      msg.msg_iov = &iov;
      msg.msg_iovlen = 1;
      msg.msg_control = control;
      msg.msg_controllen = sizeof control;
      const ssize_t got = ::recvmsg(fd_, &msg, MSG_DONTWAIT);
      if (got < 0) {
        if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) break;
        if (errno == ECONNREFUSED) {  // UDP: the peer was not listening for an earlier send
          peer_refused_ = true;
          continue;
        }
        throw TransportError(describe() + ": receive failed: " + errno_text(errno));
      }
      // A whole number of frames, at least one and at most max_frames (SocketCAN: exactly one; a CAN FD frame or
      // a stray datagram is malformed as a whole).
      const std::size_t size = static_cast<std::size_t>(got);
      if (size == 0 || size % sizeof(can_frame) != 0 || size > max_frames * sizeof(can_frame) ||
          (msg.msg_flags & MSG_TRUNC)) {
        ++malformed_;
        continue;
      }
      double stamp = -1.0;  // one kernel stamp per datagram, read once
      for (std::size_t off = 0; off < size; off += sizeof(can_frame)) {
        ReceivedFrame rf;
        std::memcpy(&rf.frame, buf + off, sizeof(can_frame));
        if (!accept(rf.frame)) continue;
        if (stamp < 0.0) stamp = timestamp_of(msg);
        rf.receive_time_s = stamp;
        out.push_back(rf);
        ++n;
      }
    }
    return n;
  }

 protected:
  virtual bool accept(const can_frame&) { return true; }
  // Frames one read may carry: SocketCAN one (CAN_RAW delivers frame by frame), UDP up to kMaxFramesPerDatagram.
  virtual std::size_t frames_per_datagram() const { return 1; }
  void enable_timestamps() {
    const int on = 1;
    if (setsockopt(fd_, SOL_SOCKET, SO_TIMESTAMP, &on, sizeof on) < 0)
      fail("cannot enable SO_TIMESTAMP", errno);
    const int flags = fcntl(fd_, F_GETFL, 0);
    if (flags < 0 || fcntl(fd_, F_SETFL, flags | O_NONBLOCK) < 0) fail("cannot make the socket non-blocking", errno);
  }
  [[noreturn]] void fail(const std::string& what, int err) {
    close();
    throw TransportError(describe() + ": " + what + ": " + errno_text(err));
  }
  // IP_RECVERR queues one message per ICMP error; left there it would keep poll() reporting POLLERR.
  void drain_error_queue() {
    for (int i = 0; i < 256; ++i) {
      unsigned char buf[sizeof(can_frame)];
      alignas(cmsghdr) char control[512];
      iovec iov{buf, sizeof buf};
      msghdr msg{};
      msg.msg_iov = &iov;
      msg.msg_iovlen = 1;
      msg.msg_control = control;
      msg.msg_controllen = sizeof control;
      if (::recvmsg(fd_, &msg, MSG_ERRQUEUE | MSG_DONTWAIT) < 0) break;
    }
  }
  bool send_bytes(const void* data, std::size_t size, const sockaddr* to, socklen_t to_len) {
    if (fd_ < 0) throw TransportError(describe() + ": not open");
    // The kernel fails the next send with a pending ICMP error; when the receive thread took that error first
    // (SO_ERROR clears it), this send stands for it, as the kernel's would have.
    if (peer_refused_.exchange(false)) return false;
    const ssize_t sent = to ? ::sendto(fd_, data, size, MSG_DONTWAIT, to, to_len)
                            : ::send(fd_, data, size, MSG_DONTWAIT);
    if (sent == static_cast<ssize_t>(size)) return true;
    if (sent < 0 && (errno == ENOBUFS || errno == EAGAIN || errno == EWOULDBLOCK || errno == ECONNREFUSED))
      return false;
    if (sent < 0) throw TransportError(describe() + ": send failed: " + errno_text(errno));
    throw TransportError(describe() + ": short write");
  }

  int fd_ = -1;
  std::atomic<std::uint64_t> malformed_{0};  // read by status queries on other threads
  std::atomic<bool> peer_refused_{false};    // the receive thread saw ECONNREFUSED: refuse the next send
};

class SocketCanTransport : public SocketTransport {
 public:
  explicit SocketCanTransport(SocketCanOptions o) : options_(std::move(o)) {}

  void open() override {
    close();
    malformed_ = 0;
    if (options_.interface.empty() || options_.interface.size() >= IFNAMSIZ)
      throw TransportError(describe() + ": interface name must be 1.." + std::to_string(IFNAMSIZ - 1) + " characters");
    fd_ = ::socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (fd_ < 0) {
      const int err = errno;
      fd_ = -1;
      throw TransportError(describe() + ": cannot create a CAN_RAW socket (" + errno_text(err) +
                           (err == EAFNOSUPPORT ? "; this kernel has no SocketCAN, use the udp transport" : "") + ")");
    }
    ifreq ifr{};
    std::strncpy(ifr.ifr_name, options_.interface.c_str(), IFNAMSIZ - 1);
    if (ioctl(fd_, SIOCGIFINDEX, &ifr) < 0) {
      const int err = errno;
      if (err == ENODEV) {
        close();
        throw TransportError(describe() + ": interface does not exist");
      }
      fail("cannot look up the interface", err);
    }
    const int ifindex = ifr.ifr_ifindex;
    if (ioctl(fd_, SIOCGIFFLAGS, &ifr) == 0 && !(ifr.ifr_flags & IFF_UP)) {
      close();
      throw TransportError(describe() + ": interface is down (ip link set " + options_.interface + " up)");
    }
    if (!options_.filters.empty()) {
      if (setsockopt(fd_, SOL_CAN_RAW, CAN_RAW_FILTER, options_.filters.data(),
                     options_.filters.size() * sizeof(can_filter)) < 0)
        fail("cannot set CAN_RAW_FILTER", errno);
    }
    if (setsockopt(fd_, SOL_CAN_RAW, CAN_RAW_ERR_FILTER, &options_.error_mask, sizeof options_.error_mask) < 0)
      fail("cannot set CAN_RAW_ERR_FILTER", errno);
    const int own = options_.receive_own ? 1 : 0;
    setsockopt(fd_, SOL_CAN_RAW, CAN_RAW_RECV_OWN_MSGS, &own, sizeof own);
    enable_timestamps();
    sockaddr_can addr{};
    addr.can_family = AF_CAN;
    addr.can_ifindex = ifindex;
    if (::bind(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) < 0) fail("cannot bind", errno);
  }

  bool send(const can_frame& frame) override {
    try {
      return send_bytes(&frame, sizeof frame, nullptr, 0);
    } catch (const TransportError&) {
      if (errno == ENETDOWN || errno == ENODEV || errno == ENXIO)
        throw TransportError(describe() + ": interface went down");
      throw;
    }
  }

  std::string describe() const override { return "socketcan:" + options_.interface; }

 private:
  SocketCanOptions options_;
};

class UdpTransport : public SocketTransport {
 public:
  explicit UdpTransport(UdpOptions o) : options_(std::move(o)) {}

  void open() override {
    close();
    malformed_ = 0;
    if (options_.local_port <= 0 || options_.local_port > 65535)
      throw TransportError(describe() + ": local port must be 1..65535");
    if (options_.remote_port <= 0 || options_.remote_port > 65535)
      throw TransportError(describe() + ": remote port must be 1..65535");
    in_addr addr{};
    if (inet_pton(AF_INET, options_.host.c_str(), &addr) != 1)
      throw TransportError(describe() + ": host must be an IPv4 address");
    fd_ = ::socket(AF_INET, SOCK_DGRAM, 0);
    if (fd_ < 0) {
      const int err = errno;
      fd_ = -1;
      throw TransportError(describe() + ": cannot create a UDP socket: " + errno_text(err));
    }
    const int on = 1;
    setsockopt(fd_, SOL_SOCKET, SO_REUSEADDR, &on, sizeof on);
    // Without it Linux drops the ICMP "port unreachable" of an unconnected UDP socket: with it the next send
    // fails with ECONNREFUSED, so a peer that is not listening shows as refused sends (like a full CAN queue).
    if (setsockopt(fd_, IPPROTO_IP, IP_RECVERR, &on, sizeof on) < 0) fail("cannot set IP_RECVERR", errno);
    enable_timestamps();
    sockaddr_in local{};
    local.sin_family = AF_INET;
    local.sin_addr = addr;
    local.sin_port = htons(static_cast<std::uint16_t>(options_.local_port));
    if (::bind(fd_, reinterpret_cast<sockaddr*>(&local), sizeof local) < 0) fail("cannot bind", errno);
    remote_ = sockaddr_in{};
    remote_.sin_family = AF_INET;
    remote_.sin_addr = addr;
    remote_.sin_port = htons(static_cast<std::uint16_t>(options_.remote_port));
  }

  bool send(const can_frame& frame) override {
    return send_bytes(&frame, sizeof frame, reinterpret_cast<const sockaddr*>(&remote_), sizeof remote_);
  }

  // The frames back to back, kMaxFramesPerDatagram per datagram: each datagram is one sendto and one wake-up of
  // the receiver, and goes whole or not at all.
  std::size_t send_batch(const can_frame* frames, std::size_t count) override {
    std::size_t done = 0;
    while (done < count) {
      const std::size_t n = std::min(count - done, kMaxFramesPerDatagram);
      if (!send_bytes(frames + done, n * sizeof(can_frame), reinterpret_cast<const sockaddr*>(&remote_),
                      sizeof remote_))
        return done;
      done += n;
    }
    return done;
  }

  std::string describe() const override {
    return "udp:" + options_.host + ":" + std::to_string(options_.local_port) + "->" +
           std::to_string(options_.remote_port);
  }

 protected:
  bool accept(const can_frame& frame) override { return passes_filters(frame, options_.filters); }
  std::size_t frames_per_datagram() const override { return kMaxFramesPerDatagram; }

 private:
  UdpOptions options_;
  sockaddr_in remote_{};
};

}  // namespace

std::unique_ptr<Transport> make_socketcan_transport(const SocketCanOptions& options) {
  return std::make_unique<SocketCanTransport>(options);
}

std::unique_ptr<Transport> make_udp_transport(const UdpOptions& options) {
  return std::make_unique<UdpTransport>(options);
}

}  // namespace piezo::can
