// The piezo_predictor node: per axis, free-runs a model at the encoder rate, publishes the prediction, the drift
// forecast and the feedforward-corrected voltage, and (compensation on) commands the driver. Parameters, topics
// and the ideal-line definition: docs/predictor.md, config/predictor.yaml. The node is split by job: parameters
// (predictor_params), one axis (predictor_axis), reload and resume (predictor_reload), the snapshot
// (predictor_snapshot), diagnostics (predictor_diagnostics), tf and markers (predictor_visualisation).
#pragma once

#include <ros/ros.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>
#include <topic_tools/shape_shifter.h>

#include <condition_variable>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "piezo_compensation/compensation/live_inputs.h"
#include "piezo_compensation/compensation/snapshot_buffer.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/ros/predictor_axis.h"
#include "piezo_compensation/ros/predictor_params.h"

namespace diagnostic_updater {
class Updater;
class DiagnosticStatusWrapper;
}  // namespace diagnostic_updater
namespace tf2_ros {
class TransformBroadcaster;
}

namespace piezo::predictor {

// ~snapshot (src/ros/predictor_snapshot.cpp). The directory ("" = the default under $ROS_HOME or ~/.ros).
std::string snapshot_directory(const std::string& configured);
// A new bag path in `dir` named by the newest reading's stamp (UTC); creates `dir`; throws std::runtime_error
// when it is not a writable directory.
std::string snapshot_path(const std::string& dir, double end_stamp_s);
// Writes the snapshot under namespace `ns` in the bag layout of ros/data_file.h, with its data origin (`origin`:
// io::kOriginSimulated or kOriginRecorded; "" = none); throws std::runtime_error.
void write_snapshot_bag(const std::string& path, const std::string& ns, const compensation::Snapshot& s,
                        const std::string& frame_id, const std::string& origin = "");

class PredictorNode {
 public:
  PredictorNode(ros::NodeHandle nh, ros::NodeHandle pnh);  // throws std::invalid_argument / runtime_error
  ~PredictorNode();

 private:
  struct Axis {
    std::unique_ptr<PredictorAxis> logic;
    ros::Subscriber sub_voltage, sub_encoder, sub_intended;
    ros::Publisher pub_prediction, pub_command, pub_watch;
    std::deque<double> processing_us;  // recent per-message processing times
  };
  void add_axis(const std::string& name);
  void subscribe_aux();
  void setup_snapshot();
  void setup_diagnostics_and_watch();
  bool on_set_compensation(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res);
  bool on_set_hold_trim(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res);
  bool on_set_tracking_trim(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res);
  bool on_reload(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  bool on_snapshot(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  std::string reload_models(const std::map<std::string, std::string>& files, std::string& timing);
  models::ModelPtr load_for_axis(const std::string& path, const std::string& axis) const;
  const char* data_origin() const;  // of what this node hears (~transport): io::kOriginRecorded, kOriginSimulated or ""
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
  ros::ServiceServer srv_compensation_, srv_hold_trim_, srv_tracking_trim_, srv_reload_, srv_snapshot_;
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
  // diagnostics are not built at all (under lock-step sim time, many times a wall second).
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
    std::optional<compensation::EstimatorState> estimator;  // for the forecast's σ
  };
  std::map<std::string, ForecastJob> jobs_;   // per axis
  std::map<std::string, compensation::DriftForecast> results_;
  bool stop_ = false;
  std::thread worker_;
};

}  // namespace piezo::predictor
