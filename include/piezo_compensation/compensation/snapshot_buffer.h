// ROS-free ring buffer behind the predictor's ~snapshot service (docs/predictor.md, "Snapshot"): the last
// duration_s of each axis' voltage reports and encoder readings and of the auxiliary signals, as they were heard,
// cut so that the data file written from it reads as it is (every reading's voltage report is in it, every aux
// signal has a value at or before the first reading).
#pragma once

#include <cstddef>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

namespace piezo::compensation {

struct SnapshotOptions {
  double duration_s = 1800.0;           // keep this much of the newest data [s]
  std::size_t max_messages = 1000000;   // per stream (axis voltage, encoder, base prediction, aux signal): the bound
  // Each stream's ring is sized at construction for duration_s at this rate (with 5 % and 1 s headroom), capped by
  // max_messages, so its memory is committed at start-up and the callbacks that fill it do not allocate.
  double expected_rate_hz = 11.0;       // messages per second per stream [Hz] (0 < rate <= 100000)
  std::vector<std::string> axes{};      // axes whose streams are allocated at construction
  std::vector<std::string> aux{};       // aux signals allocated at construction (others on their first value)
  // gap_free_stretch (the ~snapshot bag): the most recent stretch without a missing sample is written when it spans
  // at least prefer_recent_fraction of the window, else the longest when it spans at least min_fraction.
  double prefer_recent_fraction = 0.6;
  double min_fraction = 0.25;
};

// stamp_s: the sample clock (see Snapshot); received_s: the stamp the message came with (receive time).
struct SnapshotVoltage {
  double stamp_s = 0.0;
  double received_s = 0.0;
  std::uint32_t sequence = 0;
  double voltage_v = 0.0;
};

struct SnapshotReading {
  double stamp_s = 0.0;
  double received_s = 0.0;
  std::uint32_t sequence = 0;
  double position_nm = 0.0;
};

// The running model's base prediction of one sample (compensation::SampleUpdate::base_predicted_nm), stamped like
// its reading: what a reloaded model on the same base takes its state and offset from (predictor ~reload_model).
struct SnapshotPrediction {
  double stamp_s = 0.0;
  std::uint32_t sequence = 0;
  double base_nm = 0.0;
};

struct SnapshotAux {
  double stamp_s = 0.0;
  double value = 0.0;
};

// Samples missing between two consecutive readings of one axis (frames lost beyond the predictor's queues, readings
// the controller flagged invalid, a controller restart), on the sample clock (Snapshot).
struct SnapshotGap {
  std::string axis;
  double after_s = 0.0;   // stamp of the reading before the gap
  double before_s = 0.0;  // stamp of the reading after it
  std::size_t missing = 0;
};

struct Snapshot {
  struct Axis {
    std::vector<SnapshotVoltage> voltages;
    std::vector<SnapshotReading> readings;
    std::vector<SnapshotPrediction> base_predictions;  // from the window's first reading on; not in the bag
  };
  std::map<std::string, Axis> axes;                         // by axis name
  std::map<std::string, std::vector<SnapshotAux>> aux;      // by input name (e.g. temperature_c)
  // Stamps on the controller's sample clock: the newest reading keeps its stamp, each earlier sample lies a whole
  // number of periods before it (counted by sequence number; by time across a controller restart), the period
  // being the window's mean. The driver stamps on receipt, and host load jitters those stamps by more than the
  // offline tools' constant-rate rule (1 % of a period) allows; the receive stamps stay in received_s.
  double begin_s = 0.0, end_s = 0.0;                        // stamps of the first and last reading
  double period_s = 0.0;                                    // the mean sample period
  double max_restamp_s = 0.0;                               // largest |sample clock − receive stamp| of a reading
  std::size_t invalid_readings = 0;  // readings the controller flagged invalid: left out (the reader makes no row)
  std::vector<SnapshotGap> gaps;     // by after_s; the offline tools step over one as a single sample
};

// "2 gaps, 7 samples missing (3 on c after +355.2 s, t = 1700000355.20 s; 4 on a after …)"
std::string describe_gaps(const Snapshot& s);

// What ~snapshot writes: `s` itself when it has no gap, else one stretch of it without a missing sample on any axis
// (a resumed model then runs over a history without a step it did not see; gaps are never filled). `message` ("" without
// gaps) says which stretch, how many readings were left out and where the gaps are.
struct SnapshotStretch {
  Snapshot snapshot;
  std::size_t dropped_readings = 0;  // readings of the window left out, all axes
  std::string message;
};
// The most recent gap-free stretch when it spans at least prefer_recent_fraction of the window, else the longest
// when it spans at least min_fraction (fractions of end_s − begin_s). Throws std::runtime_error naming the gaps and
// the longest stretch when none is long enough.
SnapshotStretch gap_free_stretch(const Snapshot& s, double prefer_recent_fraction = 0.6, double min_fraction = 0.25);

// A FIFO on one allocation of fixed capacity; grow() re-lays it out in a larger one.
template <class T>
class SnapshotRing {
 public:
  SnapshotRing() = default;
  // Value-initialised: every element is written here, so the pages are committed now, not while filling.
  explicit SnapshotRing(std::size_t capacity) : buf_(capacity) {}
  std::size_t size() const { return size_; }
  std::size_t capacity() const { return buf_.size(); }
  bool empty() const { return size_ == 0; }
  const T& operator[](std::size_t i) const { return buf_[wrap(head_ + i)]; }
  const T& front() const { return (*this)[0]; }
  const T& back() const { return (*this)[size_ - 1]; }
  void pop_front() {
    head_ = wrap(head_ + 1);
    --size_;
  }
  void push_back(const T& e) {  // requires size() < capacity()
    buf_[wrap(head_ + size_)] = e;
    ++size_;
  }
  void grow(std::size_t capacity) {
    std::vector<T> bigger(capacity);
    for (std::size_t i = 0; i < size_; ++i) bigger[i] = (*this)[i];
    buf_.swap(bigger);
    head_ = 0;
  }

 private:
  std::size_t wrap(std::size_t i) const { return i >= buf_.size() ? i - buf_.size() : i; }
  std::vector<T> buf_;
  std::size_t head_ = 0, size_ = 0;
};

class SnapshotBuffer {
 public:
  explicit SnapshotBuffer(const SnapshotOptions& o);  // throws std::invalid_argument naming the bad option

  void add_voltage(const std::string& axis, std::uint32_t sequence, double voltage_v, double stamp_s);
  void add_reading(const std::string& axis, std::uint32_t sequence, double position_nm, bool valid, double stamp_s);
  void add_aux(const std::string& name, double value, double stamp_s);
  void add_prediction(const std::string& axis, std::uint32_t sequence, double base_nm, double stamp_s);

  // The last duration_s up to the newest reading. Throws std::runtime_error with the reason when there is no
  // complete sample (no reading with its voltage report, or an axis without one).
  Snapshot take() const;

  std::size_t messages() const;  // held now, all streams
  std::size_t capacity() const;  // allocated, all streams [messages]
  std::size_t grown() const { return grown_; }  // times a stream outgrew its ring (arrived faster than expected)
  const SnapshotOptions& options() const { return o_; }

 private:
  struct Reading {
    SnapshotReading r;
    bool valid = true;
  };
  struct AxisStreams {
    SnapshotRing<SnapshotVoltage> voltages;
    SnapshotRing<Reading> readings;
    SnapshotRing<SnapshotPrediction> predictions;
  };
  AxisStreams& axis_streams(const std::string& axis);
  SnapshotRing<SnapshotAux>& aux_stream(const std::string& name);
  template <class T>
  void push(SnapshotRing<T>& q, const T& e, bool keep_one_before);

  SnapshotOptions o_;
  std::size_t initial_capacity_ = 0;  // per stream
  std::size_t grown_ = 0;
  std::map<std::string, AxisStreams> axes_;
  std::map<std::string, SnapshotRing<SnapshotAux>> aux_;
};

}  // namespace piezo::compensation
