// The piezo_predictor node: per axis, free-runs a model at the encoder rate, publishes the prediction, the drift
// forecast and the feedforward-corrected voltage, and (compensation on) commands the driver. Parameters, topics
// and the ideal-line definition: docs/predictor.md, config/predictor.yaml.
#pragma once

#include <ros/ros.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>
#include <topic_tools/shape_shifter.h>

#include <chrono>
#include <limits>
#include <cmath>
#include <condition_variable>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/IntendedMotion.h"
#include "piezo_compensation/Prediction.h"
#include "piezo_compensation/VoltageCommand.h"
#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/drift_forecast.h"
#include "piezo_compensation/compensation/live_inputs.h"
#include "piezo_compensation/compensation/residual_watch.h"
#include "piezo_compensation/compensation/resume.h"
#include "piezo_compensation/compensation/snapshot_buffer.h"
#include "piezo_compensation/io/sequence_pairer.h"

namespace diagnostic_updater {
class Updater;
class DiagnosticStatusWrapper;
}  // namespace diagnostic_updater
namespace tf2_ros {
class TransformBroadcaster;
}

namespace piezo::predictor {

using piezo_compensation::AxisVoltage;
using piezo_compensation::EncoderPosition;
using piezo_compensation::IntendedMotion;
using piezo_compensation::Prediction;
using piezo_compensation::VoltageCommand;

// Stand-in when a model file cannot be loaded: every prediction is NaN, so the axis runs on the uncorrected
// command with bounded steps and says why, instead of the node refusing to move the piezo.
class UnavailableModel : public models::Model {
 public:
  std::string kind() const override { return "unavailable"; }
  void reset(double, double) override {}
  double predict(const models::ModelInput&) const override { return std::nan(""); }
  void commit(const models::ModelInput&, double) override {}
  models::ModelPtr clone() const override { return std::make_unique<UnavailableModel>(*this); }
  bool uses_position_history() const override { return false; }
  YAML::Node to_yaml() const override { return YAML::Node(); }
  std::size_t num_parameters() const override { return 0; }
};

// Loads a model file (models/model_file.h) and checks it can be driven by the compensator and, with `axis`, that it
// was fitted for that axis (models::check_model_axis). Throws std::runtime_error with one line naming the file.
models::ModelPtr load_model_file(const std::string& path, const std::string& axis = "");

struct PredictorSettings {
  std::vector<std::string> axes{io::kAxisNames.begin(), io::kAxisNames.end()};
  std::map<std::string, std::string> model_files;   // per axis
  bool compensation = true;
  bool forward_when_off = true;      // compensation off: still pass the intent on to the driver, uncorrected
  bool command_on_sample = true;     // false: command only when an intent arrives (a lock-step commander paces)
  std::string frame_prefix;          // frames <prefix>base, <prefix>tip_measured, ...
  std::vector<double> drift_horizons_s{1.0, 60.0, 1800.0};
  double drift_update_period_s = 1.0;  // ROS time between forecasts per axis (0 = every sample)
  bool drift_async = true;           // forecast in a worker thread (keeps per-message processing short)
  double sample_rate_hz = 0.0;       // 0 = the model file's rate
  double ideal_line_hold_s = 60.0;
  double tf_period_s = 0.05;         // ROS time between tf/marker updates
  double marker_scale = 1e4;         // markers drawn this many times larger than life (1 µm → 1 cm)
  double fallback_gain_nm_per_v = 12.5;  // ideal line when no model is usable (position intents, display)
  std::string hardware_id = "piezo_predictor";
  std::map<std::string, std::string> aux_topics;  // model input name → topic (std_msgs/Float64 or sensor_msgs/Temperature)
  double aux_stale_after_s = 5.0;                 // an aux signal older than this feeds its fallback
  double aux_recovery_s = 10.0;                   // ramp from the fallback back to the fresh signal
  compensation::ResidualWatchOptions watch;       // noise_floor_nm 0 = no residual watch
  double snapshot_duration_s = 1800.0;            // ~snapshot keeps this much (0 = no snapshot service)
  int snapshot_max_messages = 1000000;            // per stream: the buffer's memory bound
  std::string snapshot_dir;                       // "" = $ROS_HOME/piezo_snapshots (~/.ros/piezo_snapshots)
  // ~resume_from: a ~snapshot bag of the run before; each axis' model resumes on it at its first sample
  // (compensation/resume.h) instead of starting at rest. "" = off.
  std::string resume_from;
  compensation::ResumeOptions resume;             // ~resume_max_gap_s, ~resume_voltage_tolerance_v
  // ~resume_save_to: the snapshot buffer written here every ~resume_save_period_s (ROS time; 0 = only at shutdown)
  // and when the node shuts down, for the next start's ~resume_from. "" = off.
  std::string resume_save_to;
  double resume_save_period_s = 60.0;
  compensation::AxisCompensatorConfig axis;
};

// Reads and validates the private parameters; throws std::invalid_argument naming the parameter.
PredictorSettings read_settings(const ros::NodeHandle& pnh);
// ~model_file for `axes` (a path, or a map axis → path); read again by ~reload_model.
std::map<std::string, std::string> read_model_files(const ros::NodeHandle& pnh, const std::vector<std::string>& axes);

// ~snapshot (src/ros/predictor_snapshot.cpp). The directory ("" = the default under $ROS_HOME or ~/.ros).
std::string snapshot_directory(const std::string& configured);
// A new bag path in `dir` named by the newest reading's stamp (UTC); creates `dir`; throws std::runtime_error
// when it is not a writable directory.
std::string snapshot_path(const std::string& dir, double end_stamp_s);
// Writes the snapshot under namespace `ns` in the bag layout of ros/data_file.h; throws std::runtime_error.
void write_snapshot_bag(const std::string& path, const std::string& ns, const compensation::Snapshot& s,
                        const std::string& frame_id);
// Streams `model` (free-run, from rest at the first row) over the snapshot, read through the one bag reader, so a
// reloaded model starts with the state of a model that had been running (low-pass and lag terms, creep).
// Returns "" or why it could not (the caller then starts the model at rest). With `running` (the model running
// now) and an augmented `model` on the same base, the base's state and the offset are then taken from the running
// model (compensation/base_handover.h), its recorded predictions matched to the rows by sequence number (a sample
// another axis lost has no row); `handover` says what was done.
std::string warm_model(models::Model& model, const std::string& axis, const compensation::Snapshot& s,
                       const std::string& ns, const models::Model* running = nullptr, std::string* handover = nullptr);

// One axis at message level, without a NodeHandle: the node, the replay measurement and the tests drive it.
class PredictorAxis {
 public:
  // `model` null: run without a model (fallback), with `model_error` as the reason.
  PredictorAxis(std::string axis, std::string model_name, models::ModelPtr model, const PredictorSettings& s,
                const std::string& model_error = "");

  struct Output;
  // Voltage and encoder of one sample are paired by sequence number under the one pairing rule
  // (io/sequence_pairer.h: lost, late and reordered frames, restarts). Each call returns the samples it completed.
  std::vector<Output> on_voltage(const AxisVoltage& msg, bool compensate, const ros::Time& now);
  std::vector<Output> on_encoder(const EncoderPosition& msg, bool compensate, const ros::Time& now);
  // Returns false (with `error`) when the intent is malformed; it is then ignored.
  bool on_intended(const IntendedMotion& msg, std::string& error);

  struct Output {
    Prediction prediction;
    bool send = false;        // a command for the driver
    VoltageCommand command;
    bool forecast_due = false;  // caller should start a drift forecast (async mode)
    // the sample and the running model's base part of its prediction (NaN: none), for the ~snapshot buffer
    std::uint32_t sequence = 0;
    double stamp_s = 0.0;
    double base_predicted_nm = std::numeric_limits<double>::quiet_NaN();
  };
  // Command right now from the current state (used when a new intent arrives between samples).
  bool command_now(bool compensate, VoltageCommand& out, const ros::Time& now);

  // Samples waiting for another axis' value: processed when it has come (call after any axis' message).
  std::vector<Output> poll(bool compensate, const ros::Time& now);
  // The manipulator's live inputs (other axes, aux topics), shared by the node's axes; must outlive this.
  void set_live_inputs(const compensation::LiveInputs* live) { live_ = live ? live : &own_live_; }
  const compensation::InputFeeder& inputs() const { return *feeder_; }
  std::string input_status() const;  // the inputs in fallback and why ("" when none)
  const compensation::ResidualWatch* watch() const { return watch_.get(); }

  void set_forecast(const compensation::DriftForecast& f);
  // The recorded history the model resumes on at this axis' first sample (~resume_from), read when first asked for:
  // `history` returns it, or null with `why` set when it cannot be read. Unset: the model starts at rest.
  using ResumeSource = std::function<const io::Dataset*(std::string& why)>;
  void set_resume_source(ResumeSource history) { resume_source_ = std::move(history); }
  // "" until the first sample with a resume source; then what was done ("resumed on …") or why not.
  const std::string& resume_status() const { return resume_status_; }
  // `warm`: the model was streamed over the recent samples and keeps that state (else it starts at rest).
  void reload(const std::string& model_name, models::ModelPtr model, bool warm = false);
  void set_hold_trim(bool on) { comp_->set_hold_trim(on); }
  const std::string& model_error() const { return model_error_; }

  const std::string& axis() const { return axis_; }
  const compensation::AxisCompensator& compensator() const { return *comp_; }
  double hold_voltage_v() const { return hold_v_; }
  double measured_nm() const { return measured_nm_; }
  double predicted_nm() const { return predicted_nm_; }
  double intended_nm() const { return intended_nm_; }
  double drift_longest_nm() const;
  bool has_measurement() const { return have_measured_; }
  const std::string& model_name() const { return model_name_; }
  const std::string& last_status() const { return last_status_; }
  std::size_t encoder_messages() const { return encoder_messages_; }
  std::size_t rejected_messages() const { return rejected_; }
  const io::PairerCounters& pairing() const { return pairer_.counters(); }
  bool fallback_now() const { return fallback_now_; }

 private:
  // One complete sample: advance the model, compute the command. `compensate` is the node's switch.
  Output process(const io::PairedSample& sample, const double* inputs, bool compensate, const ros::Time& now);
  void fill_command(Output& out, const compensation::SampleUpdate& u, double applied, bool compensate,
                    const ros::Time& now);
  void fill_drift(Output& out, const ros::Time& now);
  std::unique_ptr<compensation::InputFeeder> make_feeder(const models::Model& m) const;
  std::vector<Output> complete(const std::vector<io::PairedSample>& samples, bool compensate, const ros::Time& now);

  std::string axis_, model_name_;
  std::unique_ptr<compensation::AxisCompensator> comp_;
  const PredictorSettings& s_;
  io::SequencePairer pairer_;
  compensation::LiveInputs own_live_;                 // when the node gives none (one axis, no aux topics)
  const compensation::LiveInputs* live_ = &own_live_;
  std::unique_ptr<compensation::InputFeeder> feeder_;
  std::deque<io::PairedSample> waiting_;              // paired, waiting for another axis' value
  std::unique_ptr<compensation::ResidualWatch> watch_;  // null: no ~watch_noise_floor_nm
  static constexpr std::size_t kMaxWaiting = 3;
  bool have_measured_ = false;
  double measured_nm_ = std::nan(""), predicted_nm_ = std::nan(""), intended_nm_ = std::nan("");
  double hold_v_ = 0.0;
  compensation::DriftForecast forecast_;
  ros::Time last_forecast_;
  bool fallback_now_ = false;
  std::string last_status_, model_error_;
  std::size_t encoder_messages_ = 0, rejected_ = 0;
  bool start_logged_ = false;  // the start-up state estimate's line was logged
  ResumeSource resume_source_;
  std::string resume_status_;
  void resume_at(const io::PairedSample& sample);  // the first sample with a resume source
};

class PredictorNode {
 public:
  PredictorNode(ros::NodeHandle nh, ros::NodeHandle pnh);  // throws std::invalid_argument / runtime_error
  ~PredictorNode();

 private:
  struct Axis;
  void add_axis(const std::string& name);
  void subscribe_aux();
  void setup_snapshot();
  void setup_diagnostics_and_watch();
  bool on_set_compensation(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res);
  bool on_set_hold_trim(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res);
  bool on_reload(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  bool on_snapshot(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  std::string reload_models(const std::map<std::string, std::string>& files, std::string& timing);
  std::string warmth(const std::string& axis, const std::string& cold, const std::string& handover,
                     const std::optional<compensation::Snapshot>& recent) const;
  void on_voltage(Axis& a, const AxisVoltage::ConstPtr& msg);
  void on_encoder(Axis& a, const EncoderPosition::ConstPtr& msg);
  void emit(Axis& a, std::vector<PredictorAxis::Output>& outs, const ros::Time& now);
  void on_intended(Axis& a, const IntendedMotion::ConstPtr& msg);
  void on_aux(const std::string& input, const topic_tools::ShapeShifter::ConstPtr& msg);
  void poll_others(const Axis& except, const ros::Time& now);
  void start_forecast(Axis& a);
  void forecast_worker();
  void publish_tf_and_markers(const ros::Time& stamp);
  void publish_markers(const ros::Time& stamp, const double* measured, const double* predicted, const double* intended,
                       const double* drift, const std::string& text);
  void diagnose(Axis& a, diagnostic_updater::DiagnosticStatusWrapper& stat);

  ros::NodeHandle nh_, pnh_;
  PredictorSettings s_;
  bool compensation_ = true;
  std::vector<std::unique_ptr<Axis>> axes_;
  compensation::LiveInputs live_;   // other axes' reports and readings, aux signals
  std::vector<ros::Subscriber> aux_subs_;
  ros::ServiceServer srv_compensation_, srv_hold_trim_, srv_reload_, srv_snapshot_;
  std::unique_ptr<compensation::SnapshotBuffer> snapshot_;  // null: ~snapshot_duration_s 0
  // ~resume_from, read when the node starts if it is ~resume_save_to's file (before this run's saves replace it), else
  // at the first axis' first sample (a ~snapshot of the run before may be written after the node started); every
  // axis resumes on the one read.
  const io::Dataset* resume_history(std::string& why);
  std::optional<io::Dataset> resume_history_;
  void save_resume(const char* when);  // ~resume_save_to; logs, never throws
  ros::Timer resume_save_timer_;
  std::string resume_error_;
  bool resume_read_ = false;
  ros::Publisher markers_pub_;
  std::unique_ptr<tf2_ros::TransformBroadcaster> tf_;
  // Handles on /tf and /diagnostics (the broadcaster's and the updater's publications, shared in this process),
  // only to ask whether anyone listens: with nobody there, the per-sample tf + markers and the per-ROS-second
  // diagnostics are not built at all (under lock-step sim time that is ~1 600 and ~140 times a wall second).
  ros::Publisher tf_probe_, diag_probe_;
  std::unique_ptr<diagnostic_updater::Updater> diag_;
  ros::Timer diag_timer_;
  ros::Time last_tf_;

  // Drift forecasts run here so a 30-min look-ahead never delays a message.
  std::mutex mutex_;
  std::condition_variable cv_;
  ros::Timer watch_timer_;
  struct ForecastJob {
    models::ModelPtr model;  // clone
    double hold_v = 0.0;
    std::vector<double> inputs;
  };
  std::map<std::string, ForecastJob> jobs_;   // per axis
  std::map<std::string, compensation::DriftForecast> results_;
  bool stop_ = false;
  std::thread worker_;
};

}  // namespace piezo::predictor
