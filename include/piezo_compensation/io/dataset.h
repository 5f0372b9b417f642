// Dataset: the one in-memory form of recorded or simulated data that every tool reads and writes.
#pragma once

#include <cstddef>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

namespace piezo::io {

// A malformed data file or an inconsistent data set. what() is one line naming file, row and column
// where they are known, e.g. "data.csv: row 17, column c_voltage_v: not a number: 'abc'".
class DataError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// One piezo axis. voltage_v and position_nm always have Dataset::size() entries; true_position_nm is
// either empty (measured data) or full (simulated data: the noise-free position, for evaluation only).
struct AxisSeries {
  std::string name;                    // "a", "b" or "c"
  std::vector<double> voltage_v;       // applied voltage [V]
  std::vector<double> position_nm;     // encoder reading [nm]
  std::vector<double> true_position_nm;  // ground truth [nm] (simulator only), else empty
  bool has_truth() const { return !true_position_nm.empty(); }
};

// A named numeric column that is neither time, an axis' voltage/position, nor a reserved marker:
// an auxiliary signal such as a temperature, a candidate explanatory variable for the residual tool.
struct AuxSignal {
  std::string name;
  std::vector<double> values;
};

// One recording of several in a data set (several files read as one, io::join_recordings): its own history — a model
// starts at rest, or from the start estimate, at its first row — and its own zero (an incremental encoder is reset
// before each run), which no tool takes as physics.
struct RecordingMark {
  std::string name;       // the file it came from
  std::size_t begin = 0;  // its first row
  double time_shift_s = 0.0;  // added to its own times so that the data set's time column keeps increasing
};

// Reserved column names (see docs/data_formats.md):
//   time_s                      sample time [s], strictly increasing; a host clock's jitter and gaps are accepted
//                               (TimeBase below: every tool steps a model once per row)
//   <axis>_voltage_v            applied voltage [V]
//   <axis>_position_nm          measured position [nm]
//   <axis>_true_position_nm     simulator ground truth [nm] (never an explanatory signal)
//   segment                     protocol segment / scenario index (integer; metadata, not a signal)
//   phase                       protocol phase code (integer; see protocols/protocol.h; metadata)
struct Dataset {
  std::string source;                // file it came from, for error messages ("" if built in memory)
  // The source for an error message: the file, or "data" for a data set built in memory.
  std::string source_or_data() const { return source.empty() ? std::string("data") : source; }
  std::string time_clock;            // "ros": time_s are ROS time stamps (bags the nodes wrote); "": own time base
  // Who made the data: kOriginSimulated (the simulator: `piezo simulate`, the simulated device's ~snapshot),
  // kOriginRecorded (a real device), "" (the file does not say). Written to and read from the file's header:
  // CSV `# origin: simulated` before the column names, a bag's <ns>/data_origin message.
  std::string origin;
  std::vector<double> time_s;
  std::vector<AxisSeries> axes;      // in the order a, b, c among those present
  std::vector<AuxSignal> aux;        // auxiliary signals, in file order
  std::vector<int> segment;          // empty or size(): protocol segment index per sample
  std::vector<int> phase;            // empty or size(): protocol phase code per sample
  // Empty: one recording (the whole data set). Else recordings[0].begin == 0 and the begins increase.
  std::vector<RecordingMark> recordings;

  std::size_t recording_count() const { return recordings.empty() ? 1 : recordings.size(); }
  // Rows [first, second) of recording k.
  std::pair<std::size_t, std::size_t> recording_rows(std::size_t k) const;
  // Whether `row` is the first row of a recording (row 0 always is).
  bool starts_recording(std::size_t row) const;
  // The recording of each row (0 for a data set of one recording).
  std::vector<std::size_t> recording_index() const;

  std::size_t size() const { return time_s.size(); }
  bool empty() const { return time_s.empty(); }
  bool has_axis(const std::string& name) const;
  const AxisSeries& axis(const std::string& name) const;  // throws DataError naming the missing column
  AxisSeries& axis(const std::string& name);
  AxisSeries& add_axis(const std::string& name);          // creates (sized to size()) or returns existing
  const AuxSignal* find_aux(const std::string& name) const;

  // The period a model steps at: the median step of the time column (TimeBase::period_s). Throws DataError on
  // fewer than 2 rows, a time that does not increase, or a step longer than kMaxStepS, naming the row.
  double sample_period_s() const;
  double sample_rate_hz() const { return 1.0 / sample_period_s(); }

  // Rows [begin, end) as a new data set (all columns; the recordings that overlap them, cut to them).
  Dataset slice(std::size_t begin, std::size_t end) const;
  // Recording k as a data set of its own (its own times, its name as source).
  Dataset recording(std::size_t k) const;
  // Appends other's rows to the last recording (same columns required, time must continue increasing; `other`
  // must be one recording).
  void append(const Dataset& other);

  // Checks internal consistency (sizes, finite values, increasing time); throws DataError naming what.
  void validate() const;
};

inline constexpr const char* kOriginSimulated = "simulated";
inline constexpr const char* kOriginRecorded = "recorded";
// Whether the data is the simulator's: its origin when it says, else whether an axis has the simulator's ground
// truth (a sign only: a real device has none). What a fit stores as the model's fitted_on.
bool is_simulated(const Dataset& data);

// Several data sets as the recordings of one (RecordingMark): the same axes required (a DataError naming the file and
// the axis otherwise); an aux column, a true position or the segment/phase markers that not every part has are left
// out, with a line for each in `notes`. Times are shifted so that each recording starts one period after the one
// before. One part is returned as it is.
Dataset join_recordings(const std::vector<Dataset>& parts, std::vector<std::string>* notes = nullptr);

// The voltage extremes, length and rate of one axis' recording: what data-placed features (features/
// feature_specs.h, voltage_history) are placed on and what the fit gates (analysis/selection/model_selection.h) scale by.
struct DataSpan {
  double voltage_min_v = 0, voltage_max_v = 0, duration_s = 0, sample_rate_hz = 0;
  double voltage_span_v() const { return voltage_max_v - voltage_min_v; }
};
// duration_s = rows / rate (rows × sample period); the voltage extremes of the finite voltages (0 and 0 with none).
// Throws DataError like sample_period_s() on fewer than 2 rows.
DataSpan data_span(const Dataset& data, const std::string& axis);

// How the rows of a recording sit in time (docs/data_formats.md, "Time"). Every tool steps a model once per row at
// period_s, the median step: the controller's loop period (on a sample clock, the mean step). A host clock's jitter and late rows (a missed cycle of
// the host's loop, a lost sample) are accepted as they are: the model steps over a late row's extra time without
// seeing it, and that time is reported here (late_s, clock_lag_s). Nothing is interpolated or filled in.
struct TimeBase {
  std::size_t rows = 0;
  double period_s = 0;          // median step; the mean step on a sample clock (constant)
  double mean_step_s = 0;       // (last − first) / (rows − 1)
  double jitter_s = 0;          // RMS of (step − period_s) over the steps that are not late
  std::size_t late_steps = 0;   // steps longer than kLateStepFactor × period_s
  double late_s = 0;            // Σ (step − period_s) over the late steps
  double clock_lag_s = 0;       // (last − first) − (rows − 1) × period_s: how far the model's clock falls behind
  double longest_step_s = 0;
  std::size_t longest_row = 0;  // index of the row after the longest step
  // Every step within 1 % of the period: a sample clock (simulated data, the driver's bags without a loss).
  bool constant = true;
};
constexpr double kLateStepFactor = 1.5;
// The longest step a model steps over as one sample: over a longer one the creep it misses is no longer small
// against a reading (1 s of a 30-min hold's creep is well under 1 nm; a minute's at its start is not).
constexpr double kMaxStepS = 10.0;
// The time base of a time column; rows < 2 gives rows and nothing else. Does not check that time increases.
TimeBase time_base(const std::vector<double>& time_s);

// The usual step of a time column: the median of its steps (a gap or a late sample does not move it); 0 with
// fewer than 2 times. Where a gap is named (sample_period_s, the bag reader's refusal).
double median_step_s(const std::vector<double>& time_s);

// Column name helpers.
std::string voltage_column(const std::string& axis);        // "<axis>_voltage_v"
bool is_voltage_column(const std::string& column);          // "<axis>_voltage_v" for some axis
std::string voltage_column_axis(const std::string& column); // its axis; empty when not a voltage column
std::string position_column(const std::string& axis);       // "<axis>_position_nm"
std::string true_position_column(const std::string& axis);  // "<axis>_true_position_nm"
// "<axis>_fused_position_nm": an axis' fused position (its model with its encoder, estimation/error_filter.h), a
// derived column (analysis::add_fused_positions) that another axis' model may read.
std::string fused_position_column(const std::string& axis);

// CSV I/O. read_csv throws DataError with file, row (1-based, header = row 1) and column on:
// missing time_s, an axis with voltage but no position (or vice versa), no axis at all, a non-numeric
// or empty cell, NaN/Inf, a short or long row, non-increasing time. A step longer than kMaxStepS is refused
// where the rate is needed: sample_period_s(), which every offline tool calls, names the row.
Dataset read_csv(const std::string& path);
void write_csv(const std::string& path, const Dataset& data);

}  // namespace piezo::io
