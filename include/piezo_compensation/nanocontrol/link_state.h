// The driver's fault state machine for one NanoControl link: what each command's reply (or its absence) means for
// the command path. Pure: the transport feeds it exchanges, it keeps the counters and the breakdown latch.
//   o        → done (a set point counts as written)
//   e        → refused: counted, named (command and message); a set point is not written, the axis waits for the
//              read-back voltage (never driven on a guess)
//   i        → info; the study's code names a piezo voltage breakdown as one: latched, no set point goes out until
//              the link is opened again (~recover), and the driver holds every axis (device fault)
//   no reply → timeout: like a refusal for a set point; the rest of the sample is dropped; stray bytes are drained
//              before the next command, so a late reply cannot answer it
//   garbled  → like a timeout, counted as malformed
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "piezo_compensation/nanocontrol/line_protocol.h"

namespace piezo::nanocontrol {

enum class Outcome { kOk, kRefused, kInfo, kTimeout, kGarbled };
const char* to_string(Outcome outcome);

struct Exchange {
  std::string command;   // without the CR
  Outcome outcome = Outcome::kOk;
  std::string message;   // the reply's message, or what was wrong with the line
};
// line: the reply without its CR, nullopt when none came within the timeout.
Exchange classify(const std::string& command, const std::optional<std::string>& line);

struct LinkCounters {
  std::uint64_t exchanges = 0, ok = 0, refused = 0, infos = 0, timeouts = 0, garbled = 0;
  std::uint64_t breakdowns = 0;      // i replies (each latches)
  std::uint64_t samples = 0;         // complete samples (N counter reads and a read-back)
  std::uint64_t samples_dropped = 0; // samples abandoned at a failed exchange
  bool breakdown = false;            // latched until the link is opened again
  std::string last_refusal;          // "`fine16 C 40000`: value out of range"
  std::string last_info;             // "`counterread`: Piezo Voltage Breakdown"
  std::string last_timeout;          // "`counterread`: no reply within 0.2 s"
  std::string last_garbled;          // "`fine16 ?`: 3 values in "1 2 3", four expected"
};

class LinkState {
 public:
  void reset();  // the link was opened: breakdown cleared, input drained before the first command
  // Records an exchange; returns whether it succeeded (o).
  bool record(const Exchange& e, double reply_timeout_s);
  // A set point may be written (no breakdown latched).
  bool set_point_allowed() const { return !counters_.breakdown; }
  // After a timeout or a garbled line: drain stray bytes before the next command.
  bool needs_drain() const { return needs_drain_; }
  void drained() { needs_drain_ = false; }
  void sample_done(bool complete);
  const LinkCounters& counters() const { return counters_; }

 private:
  LinkCounters counters_;
  bool needs_drain_ = true;
};

}  // namespace piezo::nanocontrol
