// The piezo_predictor node's private parameters (table: predictor_interface(), src/ros/predictor_params.cpp;
// values: config/predictor.yaml) and the model files it loads.
#pragma once

#include <ros/ros.h>

#include <map>
#include <string>
#include <vector>

#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/residual_watch.h"
#include "piezo_compensation/compensation/resume.h"
#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/models/model.h"

namespace piezo::predictor {

// The step rate when neither ~sample_rate_hz nor a model gives one: the MM3E encoder's nominal rate.
constexpr double kFallbackSampleRateHz = 11.0;

struct PredictorSettings {
  std::vector<std::string> axes{io::kAxisNames.begin(), io::kAxisNames.end()};
  std::map<std::string, std::string> model_files;   // per axis
  // ~transport: where the commands go, set by the launch files: "real" (a controller: a model fitted on simulated
  // data is refused unless ~allow_simulated_model, compensation/model_check.h), "simulated" (the simulated device),
  // "replay" (a recorded bag played back: nothing is driven). The ~snapshot bag's data origin follows it.
  std::string transport = "real";
  bool allow_simulated_model = false;
  bool real_transport() const { return transport == "real"; }
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

// The rate a model steps at: ~sample_rate_hz, else the model's, else kFallbackSampleRateHz.
double step_rate_hz(const PredictorSettings& s, const models::Model& m);

// Reads and validates the private parameters; throws std::invalid_argument naming the parameter.
PredictorSettings read_settings(const ros::NodeHandle& pnh);
// ~model_file for `axes` (a path, or a map axis → path); read again by ~reload_model.
std::map<std::string, std::string> read_model_files(const ros::NodeHandle& pnh, const std::vector<std::string>& axes);

// Loads a model file and checks it can be driven by the compensator and, with `axis`, that it was fitted for that
// axis (compensation::load_compensator_model); warns when its identification check failed (`piezo fit`).
// Throws std::runtime_error with one line naming the file.
models::ModelPtr load_model_file(const std::string& path, const std::string& axis = "");
// load_model_file, then the transport rule (compensation::check_model_transport with ~transport and
// ~allow_simulated_model): a simulated model on a real transport throws, naming the file and the parameter.
models::ModelPtr load_axis_model(const std::string& path, const std::string& axis, const PredictorSettings& s,
                                 const std::string& allow_param);

}  // namespace piezo::predictor
