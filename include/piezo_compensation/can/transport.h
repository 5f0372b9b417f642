// One way to move `struct can_frame`s, two implementations: SocketCAN raw sockets (the real bus, vcan0) and
// UDP datagrams carrying the same 16-byte frames over loopback (machines whose kernel has no AF_CAN): one frame per
// datagram from send(), up to kMaxFramesPerDatagram back to back from send_batch().
// Not thread-safe by itself: DriverCore serialises open/close/send and receives on one thread.
#pragma once

#include <linux/can.h>

#include <cstddef>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

namespace piezo::can {

// A transport failure with one line naming the interface and what went wrong.
class TransportError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// UDP: the most frames one datagram carries (send_batch packs, receive unpacks up to this many; a datagram that is
// empty, not a whole number of frames or longer is malformed). One device sample is 6 frames + a heartbeat.
constexpr std::size_t kMaxFramesPerDatagram = 16;

struct ReceivedFrame {
  can_frame frame{};
  double receive_time_s = 0.0;  // kernel receive time (SO_TIMESTAMP, CLOCK_REALTIME) [s since epoch]
};

class Transport {
 public:
  virtual ~Transport() = default;
  // Opens the socket; throws TransportError (e.g. "socketcan can0: interface does not exist").
  virtual void open() = 0;
  virtual void close() = 0;
  virtual bool is_open() const = 0;
  // Sends one frame. Returns false when the kernel refuses it (queue full: ENOBUFS/EAGAIN; UDP peer not
  // listening: ECONNREFUSED, reported on the send after the lost one); the frame is dropped and
  // the caller counts it. Throws TransportError when the link is gone (interface down, socket error).
  virtual bool send(const can_frame& frame) = 0;
  // Sends `count` frames in this order. UDP packs them into as few datagrams as it can (kMaxFramesPerDatagram
  // each; a datagram goes whole or not at all): one syscall and one wake-up of the receiver for a whole device
  // sample instead of one per frame. Other transports (SocketCAN: one frame per write, as on the bus) send them one
  // by one. Returns how many frames from the front were taken (count: all); stops at the first refusal, with
  // send()'s meaning. Throws TransportError like send().
  virtual std::size_t send_batch(const can_frame* frames, std::size_t count);
  // Waits up to timeout_ms for frames and appends every frame available (a UDP datagram's frames in their order,
  // all with its receive time). Returns the number appended; throws TransportError when the link is gone.
  virtual int receive(std::vector<ReceivedFrame>& out, int timeout_ms) = 0;
  // Datagrams or frames the transport threw away as malformed (wrong size) since open; a UDP datagram of the
  // wrong size counts once, however many bytes it had.
  virtual std::uint64_t malformed_count() const { return 0; }
  // "socketcan:can0" or "udp:127.0.0.1:47001->47002", for logs and diagnostics.
  virtual std::string describe() const = 0;
};

struct SocketCanOptions {
  std::string interface = "can0";
  std::vector<can_filter> filters;            // empty: receive everything
  can_err_mask_t error_mask = CAN_ERR_MASK;   // CAN_RAW_ERR_FILTER: error classes to receive as frames
  bool receive_own = false;                   // CAN_RAW_RECV_OWN_MSGS
};

struct UdpOptions {
  std::string host = "127.0.0.1";  // both ends on loopback unless configured otherwise
  int local_port = 0;              // port this side receives on
  int remote_port = 0;             // port the other side receives on
  std::vector<can_filter> filters; // applied in software with the kernel's semantics (empty: everything)
};

std::unique_ptr<Transport> make_socketcan_transport(const SocketCanOptions& options);
std::unique_ptr<Transport> make_udp_transport(const UdpOptions& options);

// The kernel's CAN_RAW filter rule: frame passes if (id & mask) == (filter.id & mask) for any filter;
// error frames pass regardless (they are governed by the error mask).
bool passes_filters(const can_frame& frame, const std::vector<can_filter>& filters);

}  // namespace piezo::can
