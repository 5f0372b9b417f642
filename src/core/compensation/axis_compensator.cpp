#include "piezo_compensation/compensation/axis_compensator.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/estimation/forecast.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/util/format.h"

namespace piezo::compensation {

AxisCompensator::AxisCompensator(models::ModelPtr model, const IdealLine& line, const AxisCompensatorConfig& config)
    : model_(std::move(model)), line_(line), config_(config), trim_(config.hold_trim, 1.0 / config.sample_rate_hz),
      tracking_(config.tracking_trim, 1.0 / config.sample_rate_hz) {
  if (!model_) throw std::invalid_argument("AxisCompensator: no model");
  if (!(config_.voltage_max_v > config_.voltage_min_v)) throw std::invalid_argument("AxisCompensator: empty voltage limits");
  if (!(config_.fallback_max_step_v > 0.0)) throw std::invalid_argument("AxisCompensator: fallback_max_step_v must be > 0");
  if (!(config_.sample_rate_hz > 0.0)) throw std::invalid_argument("AxisCompensator: sample_rate_hz must be > 0");
  if (!(config_.start_estimate_s >= 0.0) || !std::isfinite(config_.start_estimate_s))
    throw std::invalid_argument("AxisCompensator: start_estimate_s must be a finite time >= 0 s");
  check_model(*model_);
  set_period_for(*model_);
  set_inputs_for(*model_);
  const double stroke_nm = std::abs(line_.position_nm(config_.voltage_max_v) - line_.position_nm(config_.voltage_min_v));
  if (config_.hold_trim.max_nm <= 0.0) trim_.set_max_nm(0.02 * stroke_nm);  // 2 % of the ideal stroke
  if (config_.tracking_trim.max_nm <= 0.0) tracking_.set_max_nm(0.02 * stroke_nm);
  set_estimator_for(*model_);
}

void AxisCompensator::set_estimator_for(const models::Model& model) {
  filter_.reset();
  if (!model.meta.estimator || model.meta.estimator.IsNull()) {
    estimator_status_ = "model-only: the model file has no estimator noise model (piezo fit writes one)";
    return;
  }
  const estimation::NoiseModel nm = estimation::NoiseModel::from_yaml(model.meta.estimator, "model " + model.kind());
  filter_ = std::make_unique<estimation::ErrorFilter>(nm, 1.0 / config_.sample_rate_hz);
  estimator_status_ = nm.describe();
}

double AxisCompensator::sensor_part(const models::ModelInput& in) const {
  if (!sensor_terms_) return 0.0;
  const double s = augmented_->sensor_part_nm(in);
  return std::isfinite(s) ? s : 0.0;
}

// The estimator's reading model: the reading is the stage position plus what the sensor terms expect the encoder
// to add (u.sensor_nm); the fused estimate is the stage's.
void AxisCompensator::track(double predicted_nm, double measured_nm, bool measured_valid, bool ok, SampleUpdate& u) {
  u.fused_nm = predicted_nm;
  if (filter_) {
    filter_->step(predicted_nm, measured_nm, measured_valid, u.sensor_nm);
    u.fused_nm = filter_->fused_nm();
    u.fused_sigma_nm = filter_->sigma_nm();
  }
  trim_.step(has_intent_ ? intended_nm_ : u.fused_nm, u.fused_nm, u.fused_sigma_nm, filter_ && filter_->fusing(),
             filter_ ? filter_->samples_since_reading() : 0, ok && last_command_active_, has_intent_);
  step_tracking(u, ok);
}

// The tracking trim aims at the model's error forecast half its period ahead; once the hold trim acts, it takes the
// tracking trim's value (their sum is the correction, so it does not jump).
void AxisCompensator::step_tracking(const SampleUpdate& u, bool ok) {
  if (!handed_over_ && trim_.state() == TrimState::kActive && tracking_.enabled()) {
    trim_.take_over(tracking_.hand_over());
    handed_over_ = true;
  }
  TrackingInput in;
  in.fusing = filter_ && filter_->fusing();
  in.has_intent = has_intent_;
  in.holding = handed_over_;
  in.model_ok = ok && last_command_active_;
  in.sigma_nm = u.fused_sigma_nm;
  if (filter_) {
    if (tracking_.enabled()) {  // the forecast is read only by an enabled trim; the encoder checks run regardless
      estimation::ForecastPath rest;
      rest.steps = static_cast<std::size_t>(std::lround(0.5 * tracking_.options().period_s * config_.sample_rate_hz));
      in.error_forecast_nm = estimation::forecast_error(filter_->noise_model(), 1.0 / config_.sample_rate_hz,
                                                        filter_->state(), rest, false).mean_nm;
    }
    in.since_reading_samples = filter_->samples_since_reading();
    in.refused_readings = filter_->rejected_readings() + filter_->stale_readings();
  }
  tracking_.step(in);
}

// A new intent: the hold trim's correction goes back to the tracking trim when it is on (the sum does not jump),
// else it is cancelled as before a move.
void AxisCompensator::on_new_intent() {
  tracking_.on_new_intent(trim_.trim_nm());
  trim_.on_new_intent();
  handed_over_ = false;
}

void AxisCompensator::check_model(const models::Model& model) {
  const std::vector<std::string> names = model.aux_inputs();
  for (const auto& n : names)
    if (n.empty()) throw std::invalid_argument("model '" + model.kind() + "' reads an input without a name");
}

void AxisCompensator::set_period_for(models::Model& model) const {
  try {
    model.set_step_s(1.0 / config_.sample_rate_hz);
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument("AxisCompensator: sample_rate_hz " + util::fmt(config_.sample_rate_hz, 4) +
                                " Hz: " + e.what());
  }
}

void AxisCompensator::set_step_s(double dt_s) {
  if (model_->runs_at_any_rate()) model_->set_step_s(dt_s);
}

void AxisCompensator::set_inputs_for(const models::Model& model) {
  augmented_ = dynamic_cast<models::AugmentedModel*>(model_.get());
  if (augmented_) augmented_->set_stage_position(true);  // the feedforward positions the stage, not the readings
  sensor_terms_ = augmented_ && augmented_->has_sensor_terms();
  const std::vector<std::string> names = model.aux_inputs();
  aux_now_.assign(names.size(), std::numeric_limits<double>::quiet_NaN());
  time_index_.clear();
  for (std::size_t k = 0; k < names.size(); ++k)
    if (names[k] == "time_s") time_index_.push_back(k);
}

std::vector<double> AxisCompensator::next_inputs() const {
  // the command is for the next sample: time runs on one period, the other inputs are held
  std::vector<double> next = aux_now_;
  for (std::size_t k : time_index_) next[k] += 1.0 / config_.sample_rate_hz;
  return next;
}

void AxisCompensator::set_intended_voltage(double voltage_v) {
  if (!std::isfinite(voltage_v)) throw std::invalid_argument("intended voltage is not finite");
  const double target = line_.position_nm(voltage_v);
  if (!has_intent_ || target != intended_nm_) on_new_intent();
  intended_nm_ = target;
  has_intent_ = true;
}

void AxisCompensator::set_intended_position_nm(double position_nm) {
  if (!std::isfinite(position_nm)) throw std::invalid_argument("intended position is not finite");
  if (!has_intent_ || position_nm != intended_nm_) on_new_intent();
  intended_nm_ = position_nm;
  has_intent_ = true;
}

bool AxisCompensator::in_range(double position_nm) const {
  const double a = line_.position_nm(config_.voltage_min_v), b = line_.position_nm(config_.voltage_max_v);
  const double margin = config_.position_margin_nm > 0.0 ? config_.position_margin_nm : 0.5 * std::abs(b - a);
  return position_nm >= std::min(a, b) - margin && position_nm <= std::max(a, b) + margin;
}

SampleUpdate AxisCompensator::on_sample(double applied_v, double measured_nm, bool measured_valid, const double* inputs) {
  SampleUpdate u;
  measured_valid = measured_valid && std::isfinite(measured_nm);
  if (!aux_now_.empty()) {
    if (!inputs) {
      u.ok = false;
      u.predicted_nm = last_predicted_nm_;
      u.status = "the model's inputs were not given; sample skipped";
      ++prediction_failures_;
      return u;
    }
    std::copy(inputs, inputs + aux_now_.size(), aux_now_.begin());
  }
  if (!std::isfinite(applied_v)) {
    // Nothing sensible to feed the model; keep the state and say so.
    u.ok = false;
    u.predicted_nm = last_predicted_nm_;
    u.status = "applied voltage is not finite; sample skipped";
    ++prediction_failures_;
    return u;
  }
  ++samples_;
  if (!started_) {
    const double x0 = measured_valid ? measured_nm : line_.position_nm(applied_v);
    model_->reset(applied_v, x0);
    started_ = true;
    last_applied_v_ = applied_v;
    last_predicted_nm_ = x0;
    u.predicted_nm = x0;
    if (filter_) filter_->reset();
    record_start_row(applied_v, measured_nm, measured_valid);
    track(x0, measured_nm, measured_valid, true, u);
    return u;
  }
  record_start_row(applied_v, measured_nm, measured_valid);
  const models::ModelInput in{applied_v, aux_now_.empty() ? nullptr : aux_now_.data()};
  const double p = model_->predict(in);  // the stage position (set_inputs_for)
  u.base_predicted_nm = augmented_ ? augmented_->base_prediction(in) : p;
  u.sensor_nm = sensor_part(in);
  last_applied_v_ = applied_v;
  if (!std::isfinite(p) || !in_range(p)) {
    std::ostringstream s;
    s << "model prediction " << (std::isfinite(p) ? "out of range" : "not finite") << " (" << p
      << " nm); model restarted at rest at the " << (measured_valid ? "measured" : "last predicted") << " position";
    u.ok = false;
    u.status = s.str();
    ++prediction_failures_;
    const double x0 = measured_valid ? measured_nm : last_predicted_nm_;
    model_->reset(applied_v, x0);
    last_predicted_nm_ = x0;
    u.predicted_nm = x0;
    if (filter_) filter_->reset();  // the model restarts at the measurement: a cold start for the filter too
    track(x0, measured_nm, measured_valid, false, u);
    return u;
  }
  // one-step: the reading less what the sensor adds to it is the stage position the model is committed with
  model_->commit(in, config_.position_feedback && measured_valid ? measured_nm - u.sensor_nm : p);
  last_predicted_nm_ = p;
  u.predicted_nm = p;
  track(p, measured_nm, measured_valid, true, u);
  return u;
}

namespace {
const char* kStartAxis = "start";  // the window's one axis; the model's inputs are aux columns of their own names
}  // namespace

// The window's rows (the model's inputs as aux columns, time from its time_s input when it reads one); at the first
// row past it (the estimate needs a row after the window) the estimate runs, before this row is predicted.
void AxisCompensator::record_start_row(double applied_v, double measured_nm, bool measured_valid) {
  if (config_.start_estimate_s <= 0.0 || start_done_) return;
  const std::vector<std::string> names = model_->aux_inputs();
  if (window_.axes.empty()) {
    window_.source = "the predictor's first " + std::to_string(config_.start_estimate_s) + " s";
    window_.add_axis(kStartAxis);
    for (const auto& n : names) window_.aux.push_back(io::AuxSignal{n, {}});
  }
  const double t = time_index_.empty() ? static_cast<double>(window_.size()) / config_.sample_rate_hz
                                       : aux_now_[time_index_[0]];
  window_.time_s.push_back(t);
  window_.axes[0].voltage_v.push_back(applied_v);
  window_.axes[0].position_nm.push_back(measured_valid ? measured_nm : std::numeric_limits<double>::quiet_NaN());
  for (std::size_t k = 0; k < names.size(); ++k) window_.aux[k].values.push_back(aux_now_[k]);
  if (t - window_.time_s[0] >= config_.start_estimate_s) start_from_window(applied_v);
}

// The model restarts in the estimated state and replays the window in its own mode (free run or feedback), so it
// stands where a model with that history would stand now; the estimator starts from the offset and its σ.
void AxisCompensator::start_from_window(double applied_v) {
  models::StartOptions so;
  so.window_s = config_.start_estimate_s;
  so.voltage_min_v = std::isfinite(config_.start_voltage_min_v) ? config_.start_voltage_min_v : config_.voltage_min_v;
  so.voltage_max_v = std::isfinite(config_.start_voltage_max_v) ? config_.start_voltage_max_v : config_.voltage_max_v;
  start_done_ = true;
  try {
    start_estimate_ = models::estimate_start(*model_, window_, kStartAxis, so);
  } catch (const std::exception& e) {  // a lost reading in the window: run on from the cold start, and say so
    start_status_ = std::string("no start estimate: ") + e.what();
    window_ = io::Dataset();
    return;
  }
  start_status_ = start_estimate_->describe();
  start_estimate_->window_weight = {};  // only a one-step stream of the window reads them (models/model_stream.h)
  models::prepare_start(*model_, window_, kStartAxis, start_estimate_->history);
  models::InputResolver inputs(window_, model_->aux_inputs(), kStartAxis);
  const io::AxisSeries& ax = window_.axes[0];
  for (std::size_t i = 0; i + 1 < window_.size(); ++i) {
    const models::ModelInput in{ax.voltage_v[i], inputs.at(i)};
    const double p = model_->predict(in);
    model_->commit(in, config_.position_feedback && std::isfinite(ax.position_nm[i]) ? ax.position_nm[i] - sensor_part(in) : p);
    last_predicted_nm_ = p;
  }
  last_applied_v_ = applied_v;
  if (filter_) filter_->reset(start_estimate_->offset_nm, start_estimate_->offset_sigma_nm);
  window_ = io::Dataset();
}

CommandUpdate AxisCompensator::command(bool compensate) {
  CommandUpdate c;
  const double nan = std::numeric_limits<double>::quiet_NaN();
  c.intended_nm = has_intent_ ? intended_nm_ : line_.position_nm(last_applied_v_);
  c.commanded_v = std::clamp(line_.voltage_v(c.intended_nm), config_.voltage_min_v, config_.voltage_max_v);
  c.corrected_v = nan;
  c.predicted_at_send_nm = nan;
  const std::vector<double> next = next_inputs();
  if (!compensate) {
    c.send_v = c.commanded_v;
  } else if (!started_) {
    c.fallback = true;
    c.status = "no encoder sample yet: model not started";
  } else {
    InverseOptions o;
    o.voltage_min_v = config_.voltage_min_v;
    o.voltage_max_v = config_.voltage_max_v;
    o.tolerance_nm = config_.inverse_tolerance_nm;
    // The hold trim moves the target so that the fused estimate, not the model alone, reaches the intent.
    const InverseResult inv =
        invert(*model_, c.intended_nm + trim_.trim_nm() + tracking_.trim_nm(), o, next.empty() ? nullptr : next.data());
    if (inv.ok) {
      c.corrected_v = c.send_v = inv.voltage_v;
      c.compensation_active = true;
      c.predicted_at_send_nm = inv.predicted_nm;
    } else {
      c.fallback = true;
      c.status = inv.error;
      c.corrected_v = inv.voltage_v;
    }
  }
  if (c.fallback) {
    ++command_fallbacks_;
    // Bounded step from the voltage the axis holds now, so a failing model never makes the tip jump.
    const double base = has_sent_ ? last_sent_v_ : last_applied_v_;
    const double step = std::clamp(c.commanded_v - base, -config_.fallback_max_step_v, config_.fallback_max_step_v);
    c.send_v = std::clamp(base + step, config_.voltage_min_v, config_.voltage_max_v);
  }
  if (started_ && !c.compensation_active) {
    const double p = model_->predict(models::ModelInput{c.send_v, next.empty() ? nullptr : next.data()});
    c.predicted_at_send_nm = std::isfinite(p) ? p : nan;
  }
  last_sent_v_ = c.send_v;
  has_sent_ = true;
  last_command_active_ = c.compensation_active;
  return c;
}

void AxisCompensator::start_resumed(models::ModelPtr model, double last_applied_v, double predicted_nm,
                                    const std::string& status, const estimation::FilterState* filter) {
  if (started_) throw std::logic_error("AxisCompensator: start_resumed after the first sample");
  if (!model) throw std::invalid_argument("AxisCompensator: no model");
  if (!std::isfinite(last_applied_v) || !std::isfinite(predicted_nm))
    throw std::invalid_argument("AxisCompensator: start_resumed with a non-finite voltage or position");
  check_model(*model);
  set_period_for(*model);
  model_ = std::move(model);
  set_inputs_for(*model_);
  set_estimator_for(*model_);
  if (filter_ && filter) filter_->set_state(*filter);
  started_ = true;
  resumed_ = true;
  last_applied_v_ = last_applied_v;
  last_predicted_nm_ = predicted_nm;
  start_done_ = true;
  if (config_.start_estimate_s > 0.0) start_status_ = "no start estimate: " + status;
}

void AxisCompensator::replace_model(models::ModelPtr model, const IdealLine& line, bool warm) {
  if (!model) throw std::invalid_argument("AxisCompensator: no model");
  check_model(*model);
  set_period_for(*model);
  model_ = std::move(model);
  set_inputs_for(*model_);
  line_ = line;
  if (started_ && !warm) model_->reset(last_applied_v_, last_predicted_nm_);
  if (config_.start_estimate_s > 0.0 && !start_done_ && !window_.empty()) {
    // The window's inputs were the old model's; the new one starts as any replaced model does.
    start_done_ = true;
    start_status_ = "no start estimate: the model was replaced during the start window";
    window_ = io::Dataset();
  }
  set_estimator_for(*model_);
  trim_.on_new_intent();  // the trims were for the old model's error
  tracking_.on_new_intent(0.0);
  handed_over_ = false;
}

}  // namespace piezo::compensation
