// piezo_recorder: drives the axes through the driver's command topics following a protocol, one protocol sample
// per encoder sample, and writes every sample into a crash-safe bag (recorder_bag.h). Parameters:
// config/recorder.yaml; design and bag layout: docs/recorder.md.
#pragma once

#include <ros/ros.h>

#include <array>
#include <chrono>
#include <deque>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <yaml-cpp/yaml.h>

#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/analysis/evaluation/recording_summary.h"
#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/ros/recorder_bag.h"

namespace piezo::ros_nodes {

// Validated ~parameters (each documented with its unit in config/recorder.yaml).
struct RecorderOptions {
  std::string protocol;                 // ~protocol (not needed with ~resume when the bag exists)
  YAML::Node protocol_params{YAML::NodeType::Map};  // ~protocol_params (map) overriding config/protocols.yaml
  std::uint64_t seed = 1;               // ~seed
  double sample_rate_hz = 11.0;         // ~sample_rate_hz: protocol rate = encoder rate, one command per sample
  double duration_s = 0.0;              // ~duration_s: record only the first part of the protocol (0 = all)
  std::string out;                      // ~out: FILE.bag
  bool resume = false;                  // ~resume
  std::vector<std::string> axes{io::kAxisNames.begin(), io::kAxisNames.end()};  // ~axes
  double chunk_period_s = 60.0;         // ~chunk_period_s: wall time between bag chunk closes (crash-loss bound)
  double encoder_timeout_s = 3.0;       // ~encoder_timeout_s: wall time without encoder data = dead driver
  double startup_timeout_s = 30.0;      // ~startup_timeout_s: wall time to wait for the first encoder data
  double min_free_space_mb = 200.0;     // ~min_free_space_mb
  double voltage_tolerance_v = 0.01;    // ~voltage_tolerance_v: applied vs commanded, for synchronisation
  int max_wait_samples = 3;             // ~max_wait_samples: encoder samples to wait for a command to show
  double progress_period_s = 10.0;      // ~progress_period_s: wall time between progress log lines
  double approach_timeout_s = 30.0;     // ~approach_timeout_s: wall time to reach the first sample's voltages
  std::uint64_t stop_after_samples = 0; // ~stop_after_samples: stop like Ctrl-C after this many (0 = never)

  // Through the parameter layer (ros/params.h): type and range checked, throws std::invalid_argument naming the
  // parameter; unknown private parameters are warned about (and listed in *unknown when given).
  static RecorderOptions from_params(const ros::NodeHandle& pnh, std::vector<std::string>* unknown = nullptr);
  void validate() const;
};

class Recorder {
 public:
  enum class State { kWaiting, kApproach, kRunning, kDone };

  // nh: the manipulator namespace (topics `<axis>/command`, ...). Throws std::invalid_argument or
  // ros_io::RecorderBagError with one clear line.
  Recorder(ros::NodeHandle nh, RecorderOptions options);
  ~Recorder();

  // Ctrl-C / SIGTERM: stop sending, close and merge the bag, exit code 130.
  void request_stop(const std::string& why);
  // Test hook for a hard crash: stop at once without closing the open chunk.
  void abandon();

  State state() const { return state_; }
  bool done() const { return state_ == State::kDone; }
  int exit_code() const { return exit_code_; }  // 0 complete, 130 interrupted, 1 failure
  const std::string& failure() const { return failure_; }
  std::uint64_t next_sample() const { return next_; }
  std::uint64_t total_samples() const { return total_; }
  const std::string& bag_path() const { return options_.out; }
  const analysis::RecordingSummary& summary() const { return summary_; }
  std::uint64_t late_commands() const { return late_commands_; }
  // Device samples between recorded rows (0 when the recorder kept up with the encoder).
  std::uint64_t skipped_device_samples() const { return skipped_device_samples_; }
  // Rows whose simulated true position was not the reading's own (late or missing) and took the newest before it.
  std::uint64_t substituted_truths() const { return substituted_truths_; }
  // Reads `parameters_yaml` of a marker back into protocol, seed, rate, params, sample count and time base.
  static void parse_spec(const std::string& yaml, RecorderOptions& options, std::uint64_t& total, double& t0_s);

 private:
  struct AxisIo {
    std::string name;
    ros::Publisher command;
    ros::Subscriber encoder, voltage, truth;
    analysis::SequenceTracker tracker;
    std::deque<piezo_compensation::AxisVoltage> voltages;    // recent, matched by sequence
    std::deque<piezo_compensation::EncoderPosition> truths;  // recent, matched by sequence
    std::deque<piezo_compensation::EncoderPosition> readings;  // recent valid readings, matched by sequence
    std::optional<piezo_compensation::EncoderPosition> pending;  // this axis' reading of the row's device sample
    double commanded_v = 0.0;
  };

  void on_encoder(std::size_t axis, const piezo_compensation::EncoderPosition::ConstPtr& msg);
  void on_voltage(std::size_t axis, const piezo_compensation::AxisVoltage::ConstPtr& msg);
  void on_truth(std::size_t axis, const piezo_compensation::EncoderPosition::ConstPtr& msg);
  void on_watchdog(const ros::WallTimerEvent&);
  bool data_ready_to_start();    // kWaiting: data (and the truth, where there is one) on every axis
  void send_sample();            // commands of sample next_
  void send_sample_unchecked();
  void publish_commands(const protocols::ProtocolSample& s);  // every axis; the next row is a later sample
  void row_ready();              // pending holds one device sample: approach_step or complete_sample
  void approach_step();          // before recording: has the driver reached the first sample's voltages?
  void assemble_row();           // every axis has a reading of one device sample after the command → complete_sample
  enum class VoltageMatch { kAll, kLost, kWaiting };
  // the voltage report of each axis' pending reading (kLost: a later report shows one was lost; the newest is used)
  VoltageMatch match_voltages(std::vector<const piezo_compensation::AxisVoltage*>& volts) const;
  void complete_sample();        // all axes have a reading: write the row or wait for the next reading
  void write_marker(const protocols::ProtocolSample& s);
  void publish_progress(bool log);
  void finish(int exit_code, const std::string& why);
  ros::Time stamp_of(std::uint64_t sample) const;
  std::string spec_yaml() const;
  std::string topic(const std::string& axis, const std::string& what) const;

  ros::NodeHandle nh_;
  RecorderOptions options_;
  std::string ns_;  // bag topic prefix: the resolved namespace, "" for the root
  std::unique_ptr<protocols::Protocol> protocol_;
  std::unique_ptr<ros_io::ChunkedBag> bag_;
  std::vector<AxisIo> axes_;
  ros::Publisher phase_pub_, progress_pub_;
  ros::WallTimer watchdog_;
  State state_ = State::kWaiting;
  int exit_code_ = 0;
  std::string failure_;
  std::uint64_t next_ = 0, total_ = 0, first_of_session_ = 0, recorded_in_session_ = 0;
  double t0_s_ = 0.0;
  int waited_samples_ = 0;
  std::uint64_t late_commands_ = 0, skipped_device_samples_ = 0, substituted_truths_ = 0;
  bool truth_checked_ = false, with_truth_ = false, waiting_truth_ = false, truth_wait_expired_ = false;
  std::optional<std::uint32_t> last_row_sequence_;  // controller sequence of the last recorded row
  // device samples before this one were taken before the current command (controller sequence)
  std::optional<std::uint32_t> row_floor_sequence_;
  std::optional<protocols::ProtocolSample> last_marker_;
  using Clock = std::chrono::steady_clock;
  Clock::time_point last_encoder_wall_, started_wall_, approach_started_, last_progress_log_, last_progress_pub_;
  std::deque<std::pair<Clock::time_point, std::uint64_t>> rate_window_;  // for the ETA
  analysis::RecordingSummary summary_;
};

}  // namespace piezo::ros_nodes
