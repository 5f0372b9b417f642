// One axis of the feedforward compensator, ROS-free: advances the model at the encoder rate (free run), turns
// the operator's intent into a target on the ideal line, inverts the model for the corrected voltage, and falls
// back to the uncorrected command with a bounded step when the model fails. The predictor node, the bag-replay
// measurement and the tests all drive this same class.
#pragma once

#include <limits>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "piezo_compensation/compensation/hold_trim.h"
#include "piezo_compensation/compensation/ideal_line.h"
#include "piezo_compensation/compensation/inverse.h"
#include "piezo_compensation/compensation/tracking_trim.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/start_state.h"
#include "piezo_compensation/estimation/error_filter.h"

namespace piezo::compensation {

struct AxisCompensatorConfig {
  double voltage_min_v = -80.0;
  double voltage_max_v = 80.0;
  double fallback_max_step_v = 1.0;      // largest change of the sent voltage per command while falling back
  double inverse_tolerance_nm = 0.01;
  double position_margin_nm = 0.0;       // predictions outside the ideal stroke ± this margin count as failures
                                         // (0 = half the ideal stroke)
  bool position_feedback = false;        // false: free run (model remembers its own predictions);
                                         // true: one-step (model remembers the encoder readings)
  double sample_rate_hz = 11.0;          // the sample period of the estimator and the hold trim
  // Hold trim on the fused estimate (compensation/hold_trim.h); acts only when the model file carries an
  // estimator noise model and the axis' readings can inform it (estimation/error_filter.h).
  HoldTrimOptions hold_trim;
  // Tracking trim while the axis moves (compensation/tracking_trim.h), handed to the hold trim when it settles.
  TrackingTrimOptions tracking_trim;
  // > 0: after the first start_estimate_s seconds the model's state is re-chosen from them (models/start_state.h:
  // the synthetic pre-history that fits them best, turning points within the voltage limits), replayed over them,
  // and the estimator starts from that estimate's offset and σ instead of its cold-start σ. 0 = off.
  double start_estimate_s = 0.0;
  // The voltage range the start estimate's synthetic histories turn within; NaN: voltage_min_v, voltage_max_v.
  double start_voltage_min_v = std::numeric_limits<double>::quiet_NaN();
  double start_voltage_max_v = std::numeric_limits<double>::quiet_NaN();
};

// Result of one encoder sample.
struct SampleUpdate {
  // Model position for the applied voltage, history up to the previous sample: the stage position (an augmented
  // model's sensor terms, acts_on: readings, left out; they go to the estimator's reading model, sensor_nm).
  double predicted_nm = 0.0;
  double sensor_nm = 0.0;      // what the model's sensor terms expect the encoder to add to this reading
  // Model and encoder fused (estimation/error_filter.h): the position and its 1σ; the prediction and NaN when the
  // model file has no estimator noise model.
  double fused_nm = 0.0;
  double fused_sigma_nm = std::numeric_limits<double>::quiet_NaN();
  // The base model's part of it (an augmented model's base; the whole prediction otherwise); NaN when the sample
  // gave no prediction. Kept with the ~snapshot so a reloaded model on the same base can take the base's state.
  double base_predicted_nm = std::numeric_limits<double>::quiet_NaN();
  bool ok = true;              // false: the prediction failed (the model was reset at the measurement)
  std::string status;          // why, when !ok
};

// Command for the next sample.
struct CommandUpdate {
  double intended_nm = 0.0;         // target on the ideal line
  double commanded_v = 0.0;         // uncorrected: the intent as a voltage on the ideal line
  double corrected_v = 0.0;         // model inverse (NaN when it failed)
  double send_v = 0.0;              // what goes to the driver
  bool compensation_active = false; // send_v is the corrected voltage
  bool fallback = false;            // compensation was wanted but the model failed
  std::string status;               // why, when fallback
  double predicted_at_send_nm = 0.0;  // model position for send_v (NaN when it failed)
};

class AxisCompensator {
 public:
  AxisCompensator(models::ModelPtr model, const IdealLine& line, const AxisCompensatorConfig& config);

  // Intent: a voltage on the ideal piezo, or a target position directly.
  void set_intended_voltage(double voltage_v);
  void set_intended_position_nm(double position_nm);
  bool has_intent() const { return has_intent_; }

  // One encoder sample: the voltage applied over the step and the encoder reading (NaN/invalid → not used).
  // The first sample starts the model at rest at (applied_v, measured) or (applied_v, ideal) without a reading.
  // `inputs`: values of model().aux_inputs() at this sample (required when the model reads any); the command
  // for the next sample uses them held, with time_s one period on.
  SampleUpdate on_sample(double applied_v, double measured_nm, bool measured_valid, const double* inputs = nullptr);
  // The model advances one period of config.sample_rate_hz per sample (a kind with time constants in seconds runs
  // at that rate whatever rate it was fitted at; a kind that steps once per sample of its training rate refuses
  // another with its reason, std::invalid_argument). set_step_s(dt) makes the following samples advance dt
  // instead (a jittered recording's own row step, compensation/track.h); the estimator and the trims keep the
  // nominal period.
  void set_step_s(double dt_s);
  // The inputs the next command and a drift forecast use (empty when the model reads none).
  std::vector<double> next_inputs() const;

  // Voltage to send for the next sample. compensate=false gives the uncorrected command (no model use).
  // Without an intent the hold target is the last applied voltage's ideal position.
  CommandUpdate command(bool compensate);

  // Replace the model (reload); the new model starts at rest at the last applied voltage and predicted position,
  // or, with `warm`, keeps the state it has (the caller streamed it over the recent samples).
  void replace_model(models::ModelPtr model, const IdealLine& line, bool warm = false);

  // Start from a resumed model (compensation/resume.h: the state its recorded history left, held to now) instead of
  // at rest at the first sample: call before the first sample; that sample then predicts from this state. No start
  // estimate is made (with start_estimate_s > 0, start_estimate_status() says why: `status`). `filter`: the
  // estimator's resumed state (compensation/resume.h), else it starts cold. Throws std::logic_error once started.
  void start_resumed(models::ModelPtr model, double last_applied_v, double predicted_nm, const std::string& status,
                     const estimation::FilterState* filter = nullptr);
  bool resumed() const { return resumed_; }

  const models::Model& model() const { return *model_; }
  const IdealLine& ideal_line() const { return line_; }
  bool started() const { return started_; }
  double last_applied_v() const { return last_applied_v_; }
  double last_predicted_nm() const { return last_predicted_nm_; }
  double last_sent_v() const { return last_sent_v_; }
  // The estimator (null when the model file has no `estimator:` block) and the hold trim.
  const estimation::ErrorFilter* estimator() const { return filter_.get(); }
  const std::string& estimator_status() const { return estimator_status_; }
  const HoldTrim& hold_trim() const { return trim_; }
  void set_hold_trim(bool on) { trim_.set_enabled(on); }
  const TrackingTrim& tracking_trim() const { return tracking_; }
  void set_tracking_trim(bool on) { tracking_.set_enabled(on); }
  std::size_t samples() const { return samples_; }
  std::size_t prediction_failures() const { return prediction_failures_; }
  std::size_t command_fallbacks() const { return command_fallbacks_; }
  // The start-up state estimate once made (config start_estimate_s > 0), else null.
  const models::StartEstimate* start_estimate() const { return start_estimate_ ? &*start_estimate_ : nullptr; }
  // Empty until the window is complete; then the estimate's one line or why none was made.
  const std::string& start_estimate_status() const { return start_status_; }

 private:
  static void check_model(const models::Model& model);  // throws for models the compensator cannot feed
  void set_period_for(models::Model& model) const;       // the nominal period (or throws why the kind refuses it)
  void set_estimator_for(const models::Model& model);    // the filter from the model file's noise model
  void track(double predicted_nm, double measured_nm, bool measured_valid, bool ok, SampleUpdate& u);
  double sensor_part(const models::ModelInput& in) const;  // 0 without sensor terms
  void set_inputs_for(const models::Model& model);
  std::vector<double> aux_now_;                         // the model's inputs at the last sample
  std::vector<std::size_t> time_index_;                 // which of them is time_s
  bool in_range(double position_nm) const;
  void record_start_row(double applied_v, double measured_nm, bool measured_valid);
  void start_from_window(double applied_v);

  io::Dataset window_;                                  // the first start_estimate_s seconds, until estimated
  std::optional<models::StartEstimate> start_estimate_;
  std::string start_status_;
  bool start_done_ = false;
  bool resumed_ = false;

  models::ModelPtr model_;
  // model_ when it is augmented (for its base's part; set to give the stage position: its sensor terms go to the
  // estimator's reading model, never into the feedforward)
  models::AugmentedModel* augmented_ = nullptr;
  bool sensor_terms_ = false;
  IdealLine line_;
  AxisCompensatorConfig config_;
  bool started_ = false;
  bool has_intent_ = false;
  double intended_nm_ = 0.0;
  double last_applied_v_ = 0.0;
  double last_predicted_nm_ = 0.0;
  double last_sent_v_ = 0.0;
  std::unique_ptr<estimation::ErrorFilter> filter_;
  std::string estimator_status_;
  HoldTrim trim_;
  TrackingTrim tracking_;
  bool handed_over_ = false;  // the hold trim has the tracking trim's value (until the next intent)
  void on_new_intent();
  void step_tracking(const SampleUpdate& u, bool ok);
  bool last_command_active_ = false;
  bool has_sent_ = false;
  std::size_t samples_ = 0, prediction_failures_ = 0, command_fallbacks_ = 0;
};

}  // namespace piezo::compensation
