// The NanoControl as a can::Transport, so can::DriverCore drives it unchanged: its limiter, slew, watchdog,
// reconnects and counters apply as on the CAN bus. Below DriverCore this adapter turns the set-point frames it
// writes into `fine16 <channel> <counts>` commands, one reply each, and turns each sample into the report frames
// DriverCore reads: per sample N `counterread`s (their mean and scatter: one encoder report per axis), one
// `fine16 ?` (the applied voltages as read back: one voltage report per axis) and a heartbeat (fault in the first
// sample after an i reply, which DriverCore holds every axis on). The frames never leave the process; their layout
// is frame_protocol().
//
// Threads: send() runs on DriverCore's command/tick threads, receive() on its receive thread; each exchange holds
// the port for its command and reply only, so a set point waits at most for one exchange of a sample.
#pragma once

#include <array>
#include <memory>
#include <mutex>
#include <string>

#include "piezo_compensation/can/protocol.h"
#include "piezo_compensation/can/transport.h"
#include "piezo_compensation/nanocontrol/link_state.h"

namespace piezo::nanocontrol {

struct LinkOptions {
  std::string port = "/dev/ttyUSB0";
  int baud = 115200;                    // the study's link: 115200 8N1
  double reply_timeout_s = 0.2;         // [s] a reply not complete by then is a timeout
  std::array<char, 3> channels{'A', 'B', 'C'};   // NanoControl channel of axis a, b, c
  std::array<double, 3> nm_per_count{20.0, 20.0, -20.0};  // [nm] per encoder count, signed (c falls as it rises)
  double counts_per_volt = 409.6;       // fine16 counts per volt: 32768 / 80 V
  int counter_reads = 5;                // counter reads per sample (the study: 5)
  double min_sample_period_s = 0.05;    // [s] a sample starts at least this long after the previous one
  double min_voltage_v = -80.0, max_voltage_v = 80.0;  // the driver's limits: no set point outside them
};
// Throws std::invalid_argument naming the field.
void validate(const LinkOptions& options);

// The layout of the frames between this adapter and DriverCore (in-process only): fine voltage and position
// fields, so neither the DAC count nor a mean of counter reads is rounded on the way.
can::ProtocolConfig frame_protocol();

// What the adapter knows beyond DriverCore's counters, for the driver's diagnostics. Thread-safe; shared by every
// transport the factory makes (one per reconnect).
class LinkMonitor {
 public:
  struct Snapshot {
    LinkCounters counters;
    std::string version;                    // reply to `version` at the last open
    std::array<double, 3> sigma_m{};        // reading σ of the last sample per axis [m] (scatter of its N reads)
    std::array<double, 3> position_m{};     // mean of the last sample
    double sample_period_s = 0.0;           // [s] between the last two samples
    double sample_duration_s = 0.0;         // [s] the last sample's reads and read-back took
  };
  Snapshot snapshot() const;
  void update(const Snapshot& s);

 private:
  mutable std::mutex mutex_;
  Snapshot snap_;
};

std::unique_ptr<can::Transport> make_transport(const LinkOptions& options, std::shared_ptr<LinkMonitor> monitor);

}  // namespace piezo::nanocontrol
