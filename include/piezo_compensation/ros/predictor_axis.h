// One predictor axis at message level, without a NodeHandle (src/ros/predictor_axis.cpp): the node, the replay
// measurement and the tests drive it.
#pragma once

#include <optional>

#include <limits>
#include <cmath>
#include <deque>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/IntendedMotion.h"
#include "piezo_compensation/Prediction.h"
#include "piezo_compensation/VoltageCommand.h"
#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/drift_forecast.h"
#include "piezo_compensation/compensation/live_inputs.h"
#include "piezo_compensation/compensation/residual_watch.h"
#include "piezo_compensation/io/sequence_pairer.h"
#include "piezo_compensation/ros/predictor_params.h"

namespace piezo::predictor {

using piezo_compensation::AxisVoltage;
using piezo_compensation::EncoderPosition;
using piezo_compensation::IntendedMotion;
using piezo_compensation::Prediction;
using piezo_compensation::VoltageCommand;

constexpr double kNmPerM = 1e9;  // messages carry metres, the models nanometres

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
  // The estimator's noise model and state now, for the forecast's σ; empty without an estimator.
  std::optional<compensation::EstimatorState> estimator_state() const;
  // The recorded history the model resumes on at this axis' first sample (~resume_from), read when first asked for:
  // `history` returns it, or null with `why` set when it cannot be read. Unset: the model starts at rest.
  using ResumeSource = std::function<const io::Dataset*(std::string& why)>;
  void set_resume_source(ResumeSource history) { resume_source_ = std::move(history); }
  // "" until the first sample with a resume source; then what was done ("resumed on …") or why not.
  const std::string& resume_status() const { return resume_status_; }
  // `warm`: the model was streamed over the recent samples and keeps that state (else it starts at rest).
  void reload(const std::string& model_name, models::ModelPtr model, bool warm = false);
  void set_hold_trim(bool on) { comp_->set_hold_trim(on); }
  void set_tracking_trim(bool on) { comp_->set_tracking_trim(on); }
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

}  // namespace piezo::predictor
