#include "piezo_compensation/ros/predictor_axis.h"

#include <algorithm>
#include <stdexcept>

#include "piezo_compensation/compensation/ideal_line.h"
#include "piezo_compensation/compensation/model_check.h"

namespace piezo::predictor {

namespace {

compensation::IdealLine line_for(const models::Model& m, const PredictorSettings& s) {
  compensation::IdealLineOptions o;
  o.voltage_min_v = s.axis.voltage_min_v;
  o.voltage_max_v = s.axis.voltage_max_v;
  o.hold_s = s.ideal_line_hold_s;
  o.sample_rate_hz = step_rate_hz(s, m);
  return compensation::ideal_line_from_model(m, o);
}

}  // namespace

PredictorAxis::PredictorAxis(std::string axis, std::string model_name, models::ModelPtr model,
                             const PredictorSettings& s, const std::string& model_error)
    : axis_(std::move(axis)), model_name_(std::move(model_name)), s_(s), model_error_(model_error) {
  compensation::IdealLine line{s_.fallback_gain_nm_per_v, 0.0};
  if (model) {
    try {
      line = line_for(*model, s_);
    } catch (const std::exception& e) {
      model_error_ = model_name_ + ": " + e.what();
      model.reset();
    }
  }
  if (!model) {
    model = std::make_unique<compensation::UnavailableModel>();
    if (model_error_.empty()) model_error_ = "no model";
  }
  compensation::AxisCompensatorConfig cfg = s_.axis;
  cfg.sample_rate_hz = step_rate_hz(s_, *model);
  feeder_ = make_feeder(*model);
  comp_ = std::make_unique<compensation::AxisCompensator>(std::move(model), line, cfg);
  if (s_.watch.noise_floor_nm > 0.0) watch_ = std::make_unique<compensation::ResidualWatch>(s_.watch);
}

std::unique_ptr<compensation::InputFeeder> PredictorAxis::make_feeder(const models::Model& m) const {
  compensation::AuxFeedOptions o;
  o.stale_after_s = s_.aux_stale_after_s;
  o.recovery_s = s_.aux_recovery_s;
  return std::make_unique<compensation::InputFeeder>(m, axis_, o);
}

void PredictorAxis::reload(const std::string& model_name, models::ModelPtr model, bool warm) {
  const compensation::IdealLine line = line_for(*model, s_);
  auto feeder = make_feeder(*model);
  comp_->replace_model(std::move(model), line, warm);
  feeder_ = std::move(feeder);
  if (watch_) watch_->clear();  // the new model is judged on its own samples
  model_name_ = model_name;
  model_error_.clear();
}

std::vector<PredictorAxis::Output> PredictorAxis::on_voltage(const AxisVoltage& msg, bool compensate,
                                                            const ros::Time& now) {
  if (!std::isfinite(msg.voltage)) {
    ++rejected_;
    last_status_ = "non-finite applied voltage ignored";
    return {};
  }
  return complete(pairer_.add_voltage(msg.sequence, msg.voltage, msg.header.stamp.toSec()), compensate, now);
}

std::vector<PredictorAxis::Output> PredictorAxis::on_encoder(const EncoderPosition& msg, bool compensate,
                                                            const ros::Time& now) {
  return complete(pairer_.add_reading(msg.sequence, msg.position * kNmPerM, msg.valid, msg.header.stamp.toSec()),
                  compensate, now);
}

std::vector<PredictorAxis::Output> PredictorAxis::complete(const std::vector<io::PairedSample>& samples,
                                                          bool compensate, const ros::Time& now) {
  waiting_.insert(waiting_.end(), samples.begin(), samples.end());
  return poll(compensate, now);
}

std::vector<PredictorAxis::Output> PredictorAxis::poll(bool compensate, const ros::Time& now) {
  std::vector<Output> outs;
  std::vector<double> in(feeder_->size());
  while (!waiting_.empty()) {
    // another axis' value for this sample may still be on its way: the one pairing rule decides (max 3 waiting)
    const bool give_up = waiting_.size() > kMaxWaiting;
    if (!feeder_->fill(*live_, waiting_.front(), now.toSec(), give_up, in.data())) break;
    outs.push_back(process(waiting_.front(), in.empty() ? nullptr : in.data(), compensate, now));
    waiting_.pop_front();
  }
  return outs;
}

bool PredictorAxis::on_intended(const IntendedMotion& msg, std::string& error) {
  try {
    if (msg.mode == IntendedMotion::VOLTAGE) {
      comp_->set_intended_voltage(msg.voltage);
    } else if (msg.mode == IntendedMotion::POSITION) {
      comp_->set_intended_position_nm(msg.target_position * kNmPerM);
    } else {
      throw std::invalid_argument("unknown mode " + std::to_string(msg.mode));
    }
  } catch (const std::exception& e) {
    ++rejected_;
    error = std::string("intended motion rejected: ") + e.what();
    return false;
  }
  return true;
}

bool PredictorAxis::command_now(bool compensate, VoltageCommand& out, const ros::Time& now) {
  if (!comp_->has_intent() || !comp_->started() || (!compensate && !s_.forward_when_off)) return false;
  const compensation::CommandUpdate c = comp_->command(compensate);
  out.header.stamp = now;
  out.voltage = c.send_v;
  hold_v_ = c.send_v;
  return true;
}

PredictorAxis::Output PredictorAxis::process(const io::PairedSample& sample, const double* inputs, bool compensate,
                                             const ros::Time& now) {
  Output out;
  ++encoder_messages_;
  const double applied = sample.voltage_v;
  const bool valid = sample.measured;
  if (valid) {
    measured_nm_ = sample.position_nm;
    have_measured_ = true;
  }
  if (resume_source_ && resume_status_.empty() && !comp_->started()) resume_at(sample);
  const compensation::SampleUpdate u =
      comp_->on_sample(applied, valid ? sample.position_nm : std::nan(""), valid, inputs);
  predicted_nm_ = u.predicted_nm;
  if (!start_logged_ && !comp_->start_estimate_status().empty()) {
    start_logged_ = true;
    ROS_INFO("axis %s: %s", axis_.c_str(), comp_->start_estimate_status().c_str());
  }
  out.sequence = sample.sequence;
  out.stamp_s = sample.stamp_s;
  if (u.ok) out.base_predicted_nm = u.base_predicted_nm;
  // free-run residual for the watch (one-step mode remembers the encoder: no free-run figure to watch)
  if (watch_ && u.ok && valid && !s_.axis.position_feedback && model_error_.empty())
    watch_->add(sample.stamp_s > 0.0 ? sample.stamp_s : now.toSec(), sample.position_nm - u.predicted_nm - u.sensor_nm);
  hold_v_ = applied;

  Prediction& p = out.prediction;
  p.header.stamp = sample.stamp_s > 0.0 ? ros::Time(sample.stamp_s) : now;
  p.header.frame_id = s_.frame_prefix + "base";
  p.axis = axis_;
  p.model = model_name_;
  p.measured_position = valid ? sample.position_nm / kNmPerM : std::nan("");
  p.predicted_position = u.predicted_nm / kNmPerM;
  p.fused_position = u.fused_nm / kNmPerM;
  p.fused_position_sigma = u.fused_sigma_nm / kNmPerM;
  p.drift_horizons = s_.drift_horizons_s;
  fill_command(out, u, applied, compensate, now);
  fill_drift(out, now);
  return out;
}

// The model resumes on the run before's history (~resume_from), held to this sample's stamp at its voltage; if it
// cannot (the file, or the history is not this stage's run before), it starts at rest as without, and says why.
void PredictorAxis::resume_at(const io::PairedSample& sample) {
  std::string why;
  const io::Dataset* history = resume_source_(why);
  if (!model_error_.empty()) {
    resume_status_ = "not resumed: no model (" + model_error_ + ")";
  } else if (!history) {
    resume_status_ = "not resumed: " + why;
  } else {
    compensation::ResumeOptions o = s_.resume;
    o.mode = s_.axis.position_feedback ? models::PredictionMode::kOneStep : models::PredictionMode::kFreeRun;
    compensation::Resume r =
        compensation::resume_model(comp_->model(), *history, axis_, sample.stamp_s, sample.voltage_v, o);
    resume_status_ = r.status;
    if (r.resumed)
      comp_->start_resumed(std::move(r.model), r.last_voltage_v, r.predicted_nm, r.status, r.filter ? &*r.filter : nullptr);
  }
  if (comp_->resumed()) ROS_INFO("axis %s: %s", axis_.c_str(), resume_status_.c_str());
  else ROS_WARN("axis %s: %s; the model starts at rest", axis_.c_str(), resume_status_.c_str());
}

// The command part of a sample's output: the corrected voltage (and, when compensating, the command), the intended
// position, the hold trim, fallback and status.
void PredictorAxis::fill_command(Output& out, const compensation::SampleUpdate& u, double applied, bool compensate,
                                 const ros::Time& now) {
  Prediction& p = out.prediction;
  const bool sending = comp_->has_intent() && (compensate || s_.forward_when_off);
  compensation::CommandUpdate c;
  if (comp_->has_intent()) {
    c = comp_->command(compensate);
    if (sending) {
      out.send = s_.command_on_sample;
      out.command.header.stamp = now;
      out.command.voltage = c.send_v;
      hold_v_ = c.send_v;
    }
    intended_nm_ = c.intended_nm;
  } else {
    c.commanded_v = applied;
    c.corrected_v = std::nan("");
    intended_nm_ = comp_->ideal_line().position_nm(applied);
  }
  p.intended_position = intended_nm_ / kNmPerM;
  p.hold_trim = comp_->hold_trim().trim_nm() / kNmPerM;
  p.hold_trim_state = compensation::trim_state_name(comp_->hold_trim().state());
  p.tracking_trim = comp_->tracking_trim().trim_nm() / kNmPerM;
  p.tracking_trim_state = compensation::tracking_state_name(comp_->tracking_trim().state());
  p.commanded_voltage = c.commanded_v;
  p.corrected_voltage = c.corrected_v;
  p.compensation_active = sending && c.compensation_active;
  fallback_now_ = !u.ok || c.fallback;
  p.fallback = fallback_now_;
  p.status = !u.ok ? u.status : c.status;
  if (p.status.empty() && feeder_->any_fallback()) p.status = input_status();
  if (fallback_now_ && !model_error_.empty()) p.status = "model unavailable: " + model_error_;
  if (fallback_now_) last_status_ = p.status;
}

// Drift over the horizons for the voltage that will be held next (due once per drift_update_period_s; computed
// here, or by the node's worker when drift_async).
void PredictorAxis::fill_drift(Output& out, const ros::Time& now) {
  Prediction& p = out.prediction;
  if (s_.drift_update_period_s <= 0.0 || last_forecast_.isZero() ||
      (now - last_forecast_).toSec() >= s_.drift_update_period_s || now < last_forecast_) {
    last_forecast_ = now;
    if (s_.drift_async) {
      out.forecast_due = true;
    } else {
      const std::vector<double> next = comp_->next_inputs();
      const auto est = estimator_state();
      forecast_ = compensation::forecast_drift(comp_->model(), hold_v_, s_.drift_horizons_s, step_rate_hz(s_, comp_->model()),
                                               next.empty() ? nullptr : next.data(), est ? &*est : nullptr);
    }
  }
  p.drift.resize(s_.drift_horizons_s.size());
  for (std::size_t i = 0; i < p.drift.size(); ++i)
    p.drift[i] = forecast_.ok && i < forecast_.drift_nm.size() ? forecast_.drift_nm[i] / kNmPerM : std::nan("");
  p.forecast_drift.resize(p.drift.size());
  p.forecast_drift_sigma.resize(p.drift.size());
  for (std::size_t i = 0; i < p.drift.size(); ++i) {
    const bool has = forecast_.ok && i < forecast_.forecast_drift_nm.size();
    p.forecast_drift[i] = has ? forecast_.forecast_drift_nm[i] / kNmPerM : std::nan("");
    p.forecast_drift_sigma[i] = has ? forecast_.forecast_sigma_nm[i] / kNmPerM : std::nan("");
  }
}

std::optional<compensation::EstimatorState> PredictorAxis::estimator_state() const {
  const estimation::ErrorFilter* f = comp_->estimator();
  if (!f) return std::nullopt;
  return compensation::EstimatorState{f->noise_model(), f->state()};
}

std::string PredictorAxis::input_status() const {
  std::string s;
  for (const auto& st : feeder_->states())
    if (st.fallback) s += (s.empty() ? "input fallback: " : "; ") + st.status;
  return s;
}

void PredictorAxis::set_forecast(const compensation::DriftForecast& f) { forecast_ = f; }

double PredictorAxis::drift_longest_nm() const {
  if (!forecast_.ok || forecast_.drift_nm.empty()) return std::nan("");
  const auto it = std::max_element(forecast_.horizons_s.begin(), forecast_.horizons_s.end());
  return forecast_.drift_nm[static_cast<std::size_t>(it - forecast_.horizons_s.begin())];
}

}  // namespace piezo::predictor
