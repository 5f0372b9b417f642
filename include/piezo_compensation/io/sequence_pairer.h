// The one rule that pairs a controller's voltage report, encoder reading and (simulated device) true position
// of one sample by the controller's sequence number. The predictor, the recorder, the bag reader and the demo
// all pair through this header, so recorded training data and live input treat a lost frame the same way.
//
// The rule (docs/predictor.md, "Pairing"):
//  - A sample is the encoder reading with sequence s plus the voltage report (and truth) with sequence s.
//    Reports and readings travel on separate topics: either may come first.
//  - Readings are emitted in sequence order. A reading older than one already emitted is late: dropped, counted.
//    A reading older than one still pending takes its place in front (reordering inside the wait).
//  - A report is lost when a newer report of the same stream has arrived (each stream arrives in order from
//    the driver), or when `max_pending` newer readings wait behind its reading. A lost report is replaced by
//    the newest report older than s (the value the axis held), and counted. With none, the sample is dropped.
//  - A lost reading (a gap in the encoder sequence) whose voltage report is known is emitted as a sample without
//    a measurement, just before the next reading, so a model keeps the device's sample clock.
//  - A number more than `restart_threshold` behind the newest of its stream is a controller restart: what is
//    pending from the old numbering is emitted by the lost-report rule, then pairing starts again.
#pragma once

#include <cmath>
#include <cstdint>
#include <deque>
#include <optional>
#include <vector>

namespace piezo::io {

// Serial-number order of 32-bit wrapping controller counters.
inline bool sequence_newer(std::uint32_t a, std::uint32_t b) { return static_cast<std::int32_t>(a - b) > 0; }

enum class ReportMatch { kFound, kLost, kWaiting };

// The report for sample `seq` among `reports` (any container, in arrival order; `seq_of(report)` gives its
// number). kFound: `*out` is the report with that number. kLost (a newer report arrived, or `give_up`): `*out`
// is the newest report older than `seq`, or null when there is none. kWaiting: it may still come.
template <class Container, class SeqOf>
ReportMatch match_report(const Container& reports, std::uint32_t seq, bool give_up, SeqOf seq_of,
                         const typename Container::value_type** out) {
  *out = nullptr;
  bool newer = false;
  for (auto it = reports.rbegin(); it != reports.rend(); ++it) {
    const std::uint32_t s = seq_of(*it);
    if (s == seq) {
      *out = &*it;
      return ReportMatch::kFound;
    }
    if (sequence_newer(s, seq))
      newer = true;
    else if (!*out)
      *out = &*it;  // newest older report (arrival order = sequence order within a stream)
  }
  if (newer || give_up) return ReportMatch::kLost;
  *out = nullptr;
  return ReportMatch::kWaiting;
}

struct PairerOptions {
  std::size_t max_pending = 3;            // newer readings a reading waits for its report before it is lost
  bool with_truth = false;                // wait for the true position too (simulated device)
  std::uint32_t restart_threshold = 1000; // a number this far behind its stream's newest: controller restart
  std::size_t keep_reports = 64;          // reports remembered per stream
};

struct PairedSample {
  std::uint32_t sequence = 0;
  double stamp_s = 0.0;                  // the reading's stamp (the report's when the reading was lost)
  double voltage_v = 0.0;
  bool voltage_lost = false;             // voltage_v is the held value of an earlier report
  double position_nm = std::nan("");
  bool measured = false;                 // false: reading lost, or flagged invalid by the controller
  bool reading_lost = false;             // no reading with this number arrived
  double truth_nm = std::nan("");        // with_truth only
  bool truth_lost = false;
};

struct PairerCounters {
  std::uint64_t samples = 0, lost_voltages = 0, lost_readings = 0, lost_truths = 0, late_readings = 0,
                dropped_samples = 0, restarts = 0;
};

class SequencePairer {
 public:
  explicit SequencePairer(PairerOptions options = {});

  // Each call returns the samples it completed, in sequence order.
  std::vector<PairedSample> add_voltage(std::uint32_t seq, double voltage_v, double stamp_s);
  std::vector<PairedSample> add_reading(std::uint32_t seq, double position_nm, bool valid, double stamp_s);
  std::vector<PairedSample> add_truth(std::uint32_t seq, double truth_nm, double stamp_s);
  // End of data: every pending reading completes, missing reports count as lost.
  std::vector<PairedSample> flush();
  void clear();  // forget everything (counters stay)

  const PairerCounters& counters() const { return counters_; }
  std::size_t pending() const { return pending_.size(); }

 private:
  struct Report {
    std::uint32_t seq;
    double value, stamp_s;
  };
  struct Reading {
    std::uint32_t seq;
    double position_nm, stamp_s;
    bool valid;
  };
  void remember(std::deque<Report>& q, std::uint32_t seq, double value, double stamp_s);
  bool restarted(std::optional<std::uint32_t> newest, std::uint32_t seq) const;
  void restart(std::vector<PairedSample>& out, std::uint32_t seq);
  void drain(std::vector<PairedSample>& out, bool give_up_all);
  // Emits the samples of lost readings before `seq` whose voltage report is known.
  void emit_lost_readings(std::vector<PairedSample>& out, std::uint32_t seq);

  PairerOptions o_;
  std::deque<Report> voltages_, truths_;
  std::deque<Reading> pending_;            // sorted by sequence
  std::optional<std::uint32_t> last_emitted_, newest_reading_;
  PairerCounters counters_;
};

}  // namespace piezo::io
