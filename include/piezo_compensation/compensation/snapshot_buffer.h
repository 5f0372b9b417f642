// ROS-free ring buffer behind the predictor's ~snapshot service (docs/predictor.md, "Snapshot"): the last
// duration_s of each axis' voltage reports and encoder readings and of the auxiliary signals, as they were heard,
// cut so that the data file written from it reads as it is (every reading's voltage report is in it, every aux
// signal has a value at or before the first reading).
#pragma once

#include <cstddef>
#include <cstdint>
#include <deque>
#include <map>
#include <string>
#include <vector>

namespace piezo::compensation {

struct SnapshotOptions {
  double duration_s = 1800.0;           // keep this much of the newest data [s]
  std::size_t max_messages = 1000000;   // per stream (axis voltage, axis encoder, aux signal): the memory bound
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
  const SnapshotOptions& options() const { return o_; }

 private:
  struct Reading {
    SnapshotReading r;
    bool valid = true;
  };
  struct AxisStreams {
    std::deque<SnapshotVoltage> voltages;
    std::deque<Reading> readings;
    std::deque<SnapshotPrediction> predictions;
  };
  template <class Q>
  void trim(Q& q, double newest_s, bool keep_one_before) const;

  SnapshotOptions o_;
  std::map<std::string, AxisStreams> axes_;
  std::map<std::string, std::deque<SnapshotAux>> aux_;
};

}  // namespace piezo::compensation
