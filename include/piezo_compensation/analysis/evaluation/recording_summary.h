// What a recording holds and what went wrong in it: encoder sequence gaps and reordering, time continuity,
// voltage pattern against the protocol, and the encoder noise σ of the noise protocol (study section 4.1.1).
// ROS-free: the recorder node feeds it live, `piezo record` and the tests feed it data sets.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"

namespace piezo::analysis {

// Sequence numbers [first_missing, first_missing + count) never arrived (as far as known so far).
struct SequenceGap {
  std::uint32_t first_missing = 0;
  std::uint64_t count = 0;
};

// Classifies a stream of 32-bit controller counters (wrapping at 2^32) as they arrive.
class SequenceTracker {
 public:
  enum class Arrival {
    kFirst,       // first number seen (or first after a restart)
    kInOrder,     // last + 1
    kGap,         // ahead of last + 1: the numbers in between are counted as dropped
    kLate,        // a number reported missing before, arriving now: out of order, no longer dropped
    kDuplicate,   // seen before (or older than anything still tracked)
    kRestart,     // a jump back by more than `restart_threshold`: the controller restarted its counter
  };

  // Numbers further back than `restart_threshold` mean a restarted counter, not reordering; missing
  // numbers are remembered (to recognise late arrivals) up to `late_window` behind the newest.
  explicit SequenceTracker(std::uint32_t restart_threshold = 100000, std::uint32_t late_window = 4096);

  Arrival add(std::uint32_t sequence);

  std::uint64_t received() const { return received_; }
  std::uint64_t dropped() const { return dropped_; }          // missing now (late arrivals subtracted)
  std::uint64_t out_of_order() const { return late_; }       // arrived after a newer number
  std::uint64_t duplicates() const { return duplicates_; }
  std::uint64_t restarts() const { return restarts_; }
  std::optional<std::uint32_t> newest() const { return newest_; }
  // Gaps still open, oldest first; a gap partly filled by late arrivals is listed as its remaining pieces.
  std::vector<SequenceGap> gaps() const;

 private:
  std::uint32_t restart_threshold_, late_window_;
  std::optional<std::uint32_t> newest_;
  std::uint64_t received_ = 0, dropped_ = 0, late_ = 0, duplicates_ = 0, restarts_ = 0;
  std::set<std::uint64_t> missing_recent_;  // unwrapped numbers within late_window_ of newest
  std::vector<SequenceGap> old_gaps_;       // gaps that fell out of the late window
  std::uint64_t epoch_ = 0;                 // unwrapping: 2^32 * number of wraps
};

// Per-axis encoder stream statistics, as the recorder saw them.
struct SequenceReport {
  std::string axis;
  std::uint64_t received = 0, dropped = 0, out_of_order = 0, duplicates = 0, restarts = 0;
  std::vector<SequenceGap> gaps;
};
SequenceReport report_of(const std::string& axis, const SequenceTracker& tracker);
SequenceReport analyze_sequences(const std::string& axis, const std::vector<std::uint32_t>& sequence);

// Time-column continuity: rows closer than half a period are duplicates, steps longer than 1.5 periods hold
// lost samples (round(step / period) − 1 of them). The period is the median step.
struct ContinuityReport {
  double period_s = 0.0;
  std::size_t duplicated_samples = 0;
  std::size_t lost_samples = 0;
  std::vector<std::size_t> problem_rows;  // row index where each problem starts (first 100)
};
ContinuityReport check_continuity(const std::vector<double>& time_s);

// Recorded voltages against the protocol's program, sample by sample (rows aligned by index).
struct VoltageMatch {
  std::size_t compared = 0;
  std::size_t mismatched = 0;       // |recorded − program| > tolerance on any axis
  double max_abs_error_v = 0.0;
  std::size_t first_mismatch = 0;   // row (valid when mismatched > 0)
};
VoltageMatch compare_voltages(const io::Dataset& recorded, const io::Dataset& program, double tolerance_v);

// Encoder noise of the noise protocol: each contiguous run of `phase == record` rows is one window at constant
// voltage; its readings minus the window's own straight-line fit (the study zeroes the encoder before each
// window; the line also removes creep left after settling) are pooled per axis.
struct NoiseEstimate {
  std::string axis;
  double sigma_nm = 0.0;              // pooled over windows, degrees of freedom corrected
  std::size_t samples = 0;
  std::vector<double> window_sigma_nm;
  std::vector<double> window_voltage_v;  // mean applied voltage of each window
  double resolution_nm = 0.0;         // smallest step between readings in the windows (0: all readings equal)
  // A σ well below the encoder step is not measurable (250 nm a/b encoders against ~20 nm noise).
  bool below_resolution() const { return resolution_nm == 0.0 || sigma_nm < 0.5 * resolution_nm; }
};
// Throws io::DataError naming the problem when there is no phase column or no window with ≥ 3 samples.
std::vector<NoiseEstimate> estimate_noise(const io::Dataset& data);

struct RecordingSummary {
  std::string protocol;
  std::size_t samples = 0;
  double duration_s = 0.0;
  double sample_rate_hz = 0.0;
  ContinuityReport continuity;
  std::vector<SequenceReport> sequences;  // live stream statistics (empty offline)
  std::vector<NoiseEstimate> noise;       // filled when the data has record-phase windows
  std::optional<VoltageMatch> voltages;   // filled when a program was given
};
// Everything above that the data supports; `program` (optional) is the protocol's program for the same rows.
RecordingSummary summarize(const io::Dataset& data, const std::string& protocol = "",
                           const io::Dataset* program = nullptr, double voltage_tolerance_v = 1e-6);
// Human-readable, several lines, each ending in '\n'.
std::string format_summary(const RecordingSummary& summary);

}  // namespace piezo::analysis
