#include "piezo_compensation/ros/predictor.h"

#include <filesystem>

#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/ros/interfaces.h"
#include "piezo_compensation/ros/params.h"

#include <diagnostic_msgs/DiagnosticArray.h>
#include <diagnostic_updater/diagnostic_updater.h>
#include <geometry_msgs/TransformStamped.h>
#include <sensor_msgs/Temperature.h>
#include <std_msgs/Float64.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>
#include <tf2_msgs/TFMessage.h>
#include <tf2_ros/transform_broadcaster.h>
#include <visualization_msgs/MarkerArray.h>

#include <algorithm>
#include <fstream>
#include <iomanip>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/analysis/model_selection.h"
#include "piezo_compensation/compensation/ideal_line.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model_file.h"

namespace piezo::predictor {
namespace {

constexpr double kNmPerM = 1e9;
constexpr std::uint32_t kInputQueue = 200;

compensation::IdealLine line_for(const models::Model& m, const PredictorSettings& s) {
  compensation::IdealLineOptions o;
  o.voltage_min_v = s.axis.voltage_min_v;
  o.voltage_max_v = s.axis.voltage_max_v;
  o.hold_s = s.ideal_line_hold_s;
  o.sample_rate_hz = s.sample_rate_hz > 0 ? s.sample_rate_hz : m.meta.sample_rate_hz;
  return compensation::ideal_line_from_model(m, o);
}

}  // namespace

models::ModelPtr load_model_file(const std::string& path, const std::string& axis) {
  if (path.empty()) throw std::runtime_error("no model file given");
  if (!std::ifstream(path)) throw std::runtime_error(path + ": cannot open model file");
  models::ModelPtr m;
  try {
    m = models::load_model(path);
  } catch (const std::exception& e) {
    const std::string what = e.what();
    throw std::runtime_error(what.find(path) == std::string::npos ? path + ": " + what : what);
  }
  if (!m) throw std::runtime_error(path + ": model file gave no model");
  if (!axis.empty()) models::check_model_axis(*m, axis, path);  // before the identification warning: refused anyway
  // `piezo fit`'s identification check (docs/predictor.md): at start-up and at every ~reload_model
  const std::string unidentified = analysis::unidentified_model_warning(*m, path);
  if (!unidentified.empty()) ROS_WARN("%s", unidentified.c_str());
  try {
    compensation::InputFeeder check(*m, m->meta.axis, {});  // inputs the predictor can feed, right clock
  } catch (const std::exception& e) {
    throw std::runtime_error(path + ": " + e.what());
  }
  if (!(m->meta.sample_rate_hz > 0.0)) throw std::runtime_error(path + ": model has no positive sample_rate_hz");
  return m;
}

std::map<std::string, std::string> read_model_files(const ros::NodeHandle& pnh, const std::vector<std::string>& axes) {
  const std::string name = pnh.resolveName("model_file");
  std::map<std::string, std::string> files;
  XmlRpc::XmlRpcValue mf;
  if (!pnh.getParam("model_file", mf))
    throw std::invalid_argument("parameter " + name + " is required (a path, or {a: path, ...})");
  if (mf.getType() == XmlRpc::XmlRpcValue::TypeString) {
    for (const auto& a : axes) files[a] = static_cast<std::string>(mf);
    // a model is fitted for one axis (models::check_model_axis refuses it on the others)
    if (axes.size() > 1)
      ROS_WARN("parameter %s: one path for %zu axes is deprecated: give one model per axis (%s/<axis>; launch args "
               "model_file_a, model_file_b, model_file_c); each axis the file was not fitted for runs uncorrected",
               name.c_str(), axes.size(), name.c_str());
  } else if (mf.getType() == XmlRpc::XmlRpcValue::TypeStruct) {
    for (const auto& a : axes) {
      if (!mf.hasMember(a) || mf[a].getType() != XmlRpc::XmlRpcValue::TypeString)
        throw std::invalid_argument("parameter " + name + "/" + a + " is required for axis " + a + " (a path)");
      files[a] = static_cast<std::string>(mf[a]);
    }
  } else {
    throw std::invalid_argument("parameter " + name + " must be a path or a map {a: path, b: path, c: path}");
  }
  return files;
}

namespace {

std::vector<params::ParamDef> predictor_core_params(const PredictorSettings& d) {
  using namespace params;
  const std::vector<std::string> axes(io::kAxisNames.begin(), io::kAxisNames.end());
  return {
      texts("axes", d.axes, axes, 1, axes.size(), "axes to predict and compensate (subscribes <axis>/voltage, encoder, intended)"),
      structured("model_file", "", "string or map", "(required)",
                 "the model file of each axis: a map {a: path, b: path, c: path}, one model fitted on each axis' "
                 "recording (a model of another axis is refused: that axis runs uncorrected); one path for several "
                 "axes is deprecated"),
      flag("compensation", d.compensation, "start with the feedforward on (~set_compensation switches it)"),
      flag("forward_when_off", d.forward_when_off, "compensation off: still send the intent, uncorrected, to <axis>/command"),
      flag("command_on_sample", d.command_on_sample,
           "send the command after every encoder sample; false: only when an intent arrives (a lock-step commander paces)"),
      text("frame_prefix", d.frame_prefix, "tf frames <prefix>base, <prefix>tip_measured, <prefix>tip_predicted, <prefix>tip_intended"),
      numbers("drift_horizons_s", "s", d.drift_horizons_s, 0.0, 86400.0, 0, 8, "drift forecast look-ahead horizons"),
      number("drift_update_period_s", "s", d.drift_update_period_s, 0.0, 3600.0,
             "ROS time between drift forecasts per axis (0 = every encoder sample)"),
      flag("drift_async", d.drift_async, "run the forecasts in a worker thread (per-message processing stays short)"),
      number("sample_rate_hz", "Hz", d.sample_rate_hz, 0.0, 100000.0, "model step rate; 0 = the model file's"),
      number("ideal_line_hold_s", "s", d.ideal_line_hold_s, 0.0, 3600.0,
             "hold at the voltage limits that defines the ideal line from the model"),
      number("tf_period_s", "s", d.tf_period_s, 0.0, 60.0, "ROS time between tf and marker updates (while subscribed)"),
      number("marker_scale", "", d.marker_scale, 1e-3, 1e9, "markers drawn this many times life size"),
      number("fallback_gain_nm_per_v", "nm/V", d.fallback_gain_nm_per_v, -1e6, 1e6,
             "ideal line used when no model is usable (position intents, display)")
          .rule("non-zero"),
      text("hardware_id", d.hardware_id, "diagnostics hardware_id"),
      structured("aux_topics", "", "map", "{}",
                 "model input name → topic (std_msgs/Float64 or sensor_msgs/Temperature), e.g. {temperature_c: temperature}; "
                 "at most 64 entries"),
      number("aux_stale_after_s", "s", d.aux_stale_after_s, 1e-3, 3600.0, "an aux signal older than this feeds its fallback"),
      number("aux_recovery_s", "s", d.aux_recovery_s, 0.0, 3600.0, "a returning aux signal is ramped in over this time"),
      number("watch_noise_floor_nm", "nm", d.watch.noise_floor_nm, 0.0, 1e6,
             "residual watch: MAE of the encoder noise alone (0 = no watch)"),
      number("watch_window_s", "s", d.watch.window_s, 1e-3, 3600.0, "residual watch: rolling window"),
      number("watch_k", "", d.watch.k, 1.0, 1000.0, "residual watch: warn above this many times the noise floor"),
      number("watch_hold_s", "s", d.watch.hold_s, 0.0, 86400.0, "residual watch: ... for this long"),
      number("snapshot_duration_s", "s", d.snapshot_duration_s, 0.0, 86400.0,
             "how much the ~snapshot buffer keeps (0 = no ~snapshot service, reloads start cold)"),
      integer("snapshot_max_messages", "", d.snapshot_max_messages, 1000, 20000000,
              "per stream (axis voltage, encoder, base prediction, aux signal): the buffer's memory bound"),
      text("snapshot_dir", d.snapshot_dir,
           "directory of the ~snapshot bags (\"\" = $ROS_HOME/piezo_snapshots, else ~/.ros/piezo_snapshots)"),
  };
}

std::vector<params::ParamDef> predictor_axis_params(const PredictorSettings& d) {
  using namespace params;
  const compensation::AxisCompensatorConfig& a = d.axis;
  const compensation::HoldTrimOptions& t = a.hold_trim;
  return {
      number("voltage_min_v", "V", a.voltage_min_v, -1000.0, 1000.0, "lowest voltage the predictor commands")
          .rule("< voltage_max_v"),
      number("voltage_max_v", "V", a.voltage_max_v, -1000.0, 1000.0, "highest voltage the predictor commands"),
      number("fallback_max_step_v", "V", a.fallback_max_step_v, 1e-6, 100.0,
             "largest change per command while falling back to the uncorrected command"),
      number("inverse_tolerance_nm", "nm", a.inverse_tolerance_nm, 1e-9, 1e6,
             "the inverse stops when the model position is this close to the target"),
      number("position_margin_nm", "nm", a.position_margin_nm, 0.0, 1e9,
             "predictions beyond the ideal stroke ± this margin count as failures (0 = half the stroke)"),
      flag("position_feedback", a.position_feedback, "false: free run; true: one-step (the model remembers the encoder)"),
      flag("hold_trim", t.enabled, "trim holds with the encoder through the estimator (~set_hold_trim switches it)"),
      number("hold_trim_settle_s", "s", t.settle_s, 0.0, 3600.0, "no new intent for this long before the trim acts"),
      number("hold_trim_time_constant_s", "s", t.time_constant_s, 0.1, 86400.0,
             "integral time constant of the trim on (intended − fused)"),
      number("hold_trim_max_nm", "nm", t.max_nm, 0.0, 1e6, "bound on |trim| (0 = 2 % of the ideal stroke)"),
      number("hold_trim_slew_nm_per_s", "nm/s", t.slew_nm_per_s, 1e-6, 1e6, "largest change of the trim per second"),
      number("hold_trim_deadband_sigma", "fused 1σ", t.deadband_sigma, 0.0, 100.0,
             "the trim acts on the part of |intended − fused| beyond this many fused σ (0 = none)"),
      number("encoder_stale_after_s", "s", t.stale_after_s, 1e-3, 3600.0,
             "no valid reading for this long: the estimate only predicts and the trim holds"),
      number("start_estimate_s", "s", a.start_estimate_s, 0.0, 3600.0,
             "start-up state estimate from the first this many seconds (0 = off: the model starts at rest)"),
      text("resume_from", d.resume_from, "a bag of the run before: each axis' model resumes on it (\"\" = off)"),
      number("resume_max_gap_s", "s", d.resume.max_gap_s, 0.0, 30.0 * 86400.0,
             "longest time between the history's end and the first sample that still resumes"),
      number("resume_voltage_tolerance_v", "V", d.resume.voltage_tolerance_v, 0.0, 1000.0,
             "the first sample's voltage must be within this of the history's last"),
      text("resume_save_to", d.resume_save_to,
           "the snapshot buffer is saved here for the next start's resume_from (\"\" = off)")
          .rule("needs snapshot_duration_s > 0"),
      number("resume_save_period_s", "s", d.resume_save_period_s, 0.0, 86400.0,
             "ROS time between saves while running (0 = only at shutdown); always also at shutdown")
          .rule("0 or >= 0.1"),
  };
}

// The per-axis compensator's parameters, the hold trim, the start estimate and the resume.
void read_axis_settings(params::ParamReader& r, PredictorSettings& s) {
  s.axis.voltage_min_v = r.number("voltage_min_v");
  s.axis.voltage_max_v = r.number("voltage_max_v");
  if (!(s.axis.voltage_max_v > s.axis.voltage_min_v))
    throw std::invalid_argument("parameters " + r.resolved("voltage_min_v") + " and voltage_max_v need min < max");
  s.axis.fallback_max_step_v = r.number("fallback_max_step_v");
  s.axis.inverse_tolerance_nm = r.number("inverse_tolerance_nm");
  s.axis.position_margin_nm = r.number("position_margin_nm");
  s.axis.position_feedback = r.flag("position_feedback");
  if (r.handle().hasParam("reanchor_time_constant_s"))
    throw std::invalid_argument("parameter " + r.resolved("reanchor_time_constant_s") + " was removed: the hold trim "
                                "on the fused estimate (~hold_trim, docs/predictor.md) replaces it");
  compensation::HoldTrimOptions& t = s.axis.hold_trim;
  t.enabled = r.flag("hold_trim");
  t.settle_s = r.number("hold_trim_settle_s");
  t.time_constant_s = r.number("hold_trim_time_constant_s");
  t.max_nm = r.number("hold_trim_max_nm");
  t.slew_nm_per_s = r.number("hold_trim_slew_nm_per_s");
  t.deadband_sigma = r.number("hold_trim_deadband_sigma");
  t.stale_after_s = r.number("encoder_stale_after_s");
  s.axis.start_estimate_s = r.number("start_estimate_s");
  s.resume_from = r.text("resume_from");
  s.resume.max_gap_s = r.number("resume_max_gap_s");
  s.resume.voltage_tolerance_v = r.number("resume_voltage_tolerance_v");
  s.resume_save_to = r.text("resume_save_to");
  s.resume_save_period_s = r.number("resume_save_period_s");
  if (s.resume_save_period_s > 0.0 && s.resume_save_period_s < 0.1)
    throw std::invalid_argument("parameter " + r.resolved("resume_save_period_s") +
                                " must be 0 (only at shutdown) or at least 0.1 s (each save writes the whole buffer)");
  if (!s.resume_save_to.empty() && !(s.snapshot_duration_s > 0.0))
    throw std::invalid_argument("parameter " + r.resolved("resume_save_to") + " needs " +
                                r.resolved("snapshot_duration_s") + " > 0 (it saves the snapshot buffer)");
}

}  // namespace

const params::NodeInterface& predictor_interface() {
  using namespace params;
  static const NodeInterface t = [] {
    const PredictorSettings d;
    NodeInterface n;
    n.node = "piezo_predictor";
    n.summary = "prediction, drift forecast, feedforward-corrected commands, fused estimate and hold trim, tf, markers";
    n.params = predictor_core_params(d);
    const auto axis = predictor_axis_params(d);
    n.params.insert(n.params.end(), axis.begin(), axis.end());
    using D = TopicDef::Direction;
    n.topics = {
        {"<axis>/voltage", "piezo_compensation/AxisVoltage", D::kSubscribes, "the applied voltage (from the driver)"},
        {"<axis>/encoder", "piezo_compensation/EncoderPosition", D::kSubscribes, "the measured position (from the driver)"},
        {"<axis>/intended", "piezo_compensation/IntendedMotion", D::kSubscribes,
         "the operator's intent: an ideal-piezo voltage [V] or a target position [m]"},
        {"<axis>/command", "piezo_compensation/VoltageCommand", D::kPublishes, "the corrected (or forwarded) voltage [V], queue 1"},
        {"<axis>/prediction", "piezo_compensation/Prediction", D::kPublishes,
         "predicted and fused position, hold trim, drift over the horizons, corrected voltage, fallback and status"},
        {"<axis>/residual_mae", "std_msgs/Float64", D::kPublishes,
         "residual watch (watch_noise_floor_nm > 0): rolling free-run MAE [m], once a second"},
        {"markers", "visualization_msgs/MarkerArray", D::kPublishes, "tips and drift arrow at marker_scale, error text"},
        {"/tf", "tf2_msgs/TFMessage", D::kPublishes, "frames <prefix>tip_measured, tip_predicted, tip_intended under <prefix>base"},
        {"/diagnostics", "diagnostic_msgs/DiagnosticArray", D::kPublishes, "per axis: model, estimator, hold trim, watch, inputs"},
        {"<aux_topics value>", "std_msgs/Float64 or sensor_msgs/Temperature", D::kSubscribes,
         "each auxiliary model input mapped by aux_topics"},
    };
    n.services = {
        {"~set_compensation", "std_srvs/SetBool", "feedforward compensation on or off"},
        {"~set_hold_trim", "std_srvs/SetBool", "hold trim on or off (every axis)"},
        {"~reload_model", "std_srvs/Trigger", "read ~model_file again and swap every axis' model (all or nothing), warmed on the buffer"},
        {"~snapshot", "std_srvs/Trigger", "write the buffered last snapshot_duration_s as a bag (snapshot_duration_s > 0)"},
    };
    return n;
  }();
  return t;
}

PredictorSettings read_settings(const ros::NodeHandle& pnh) {
  params::ParamReader r(pnh, predictor_interface());
  PredictorSettings s;
  s.axes = r.texts("axes");
  r.structured("model_file");
  s.model_files = read_model_files(pnh, s.axes);
  s.compensation = r.flag("compensation");
  s.forward_when_off = r.flag("forward_when_off");
  s.command_on_sample = r.flag("command_on_sample");
  s.frame_prefix = r.text("frame_prefix");
  s.drift_horizons_s = r.numbers("drift_horizons_s");
  s.drift_update_period_s = r.number("drift_update_period_s");
  s.drift_async = r.flag("drift_async");
  s.sample_rate_hz = r.number("sample_rate_hz");
  s.ideal_line_hold_s = r.number("ideal_line_hold_s");
  s.tf_period_s = r.number("tf_period_s");
  s.marker_scale = r.number("marker_scale");
  s.fallback_gain_nm_per_v = r.number("fallback_gain_nm_per_v");
  if (s.fallback_gain_nm_per_v == 0.0)
    throw std::invalid_argument("parameter " + r.resolved("fallback_gain_nm_per_v") + " must be non-zero");
  s.hardware_id = r.text("hardware_id");
  r.structured("aux_topics");
  if (pnh.hasParam("aux_topics") && !pnh.getParam("aux_topics", s.aux_topics))
    throw std::invalid_argument("parameter " + r.resolved("aux_topics") +
                                " must be a map of input name to topic, e.g. {temperature_c: temperature}");
  if (s.aux_topics.size() > 64)
    throw std::invalid_argument("parameter " + r.resolved("aux_topics") + " has more than 64 entries");
  for (const auto& [name, topic] : s.aux_topics)
    if (name.empty() || topic.empty())
      throw std::invalid_argument("parameter " + r.resolved("aux_topics") + ": each entry maps an input name to a topic");
  s.aux_stale_after_s = r.number("aux_stale_after_s");
  s.aux_recovery_s = r.number("aux_recovery_s");
  s.watch.noise_floor_nm = r.number("watch_noise_floor_nm");
  s.watch.window_s = r.number("watch_window_s");
  s.watch.k = r.number("watch_k");
  s.watch.hold_s = r.number("watch_hold_s");
  s.snapshot_duration_s = r.number("snapshot_duration_s");
  s.snapshot_max_messages = r.integer("snapshot_max_messages");
  s.snapshot_dir = r.text("snapshot_dir");
  read_axis_settings(r, s);
  r.warn_unknown("piezo_predictor");
  return s;
}

// ---- PredictorAxis ----------------------------------------------------------------------------------------

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
    model = std::make_unique<UnavailableModel>();
    if (model_error_.empty()) model_error_ = "no model";
  }
  compensation::AxisCompensatorConfig cfg = s_.axis;
  cfg.sample_rate_hz = s_.sample_rate_hz > 0 ? s_.sample_rate_hz : model->meta.sample_rate_hz;
  if (!(cfg.sample_rate_hz > 0.0)) cfg.sample_rate_hz = 11.0;
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
      forecast_ = compensation::forecast_drift(comp_->model(), hold_v_, s_.drift_horizons_s,
                                               s_.sample_rate_hz > 0 ? s_.sample_rate_hz : comp_->model().meta.sample_rate_hz,
                                               next.empty() ? nullptr : next.data());
    }
  }
  p.drift.resize(s_.drift_horizons_s.size());
  for (std::size_t i = 0; i < p.drift.size(); ++i)
    p.drift[i] = forecast_.ok && i < forecast_.drift_nm.size() ? forecast_.drift_nm[i] / kNmPerM : std::nan("");
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

// ---- PredictorNode ----------------------------------------------------------------------------------------

struct PredictorNode::Axis {
  std::unique_ptr<PredictorAxis> logic;
  ros::Subscriber sub_voltage, sub_encoder, sub_intended;
  ros::Publisher pub_prediction, pub_command, pub_watch;
  std::deque<double> processing_us;  // recent per-message processing times
};

PredictorNode::PredictorNode(ros::NodeHandle nh, ros::NodeHandle pnh)
    : nh_(nh), pnh_(pnh), s_(read_settings(pnh)) {
  compensation_ = s_.compensation;
  for (const auto& name : s_.axes) add_axis(name);
  subscribe_aux();
  const params::NodeInterface& iface = predictor_interface();
  markers_pub_ = nh_.advertise<visualization_msgs::MarkerArray>(iface.topic_name<visualization_msgs::MarkerArray>("markers"), 2);
  tf_ = std::make_unique<tf2_ros::TransformBroadcaster>();
  tf_probe_ = nh_.advertise<tf2_msgs::TFMessage>(iface.topic_name<tf2_msgs::TFMessage>("/tf"), 100);
  srv_compensation_ = pnh_.advertiseService(iface.service_name<std_srvs::SetBool>("~set_compensation"), &PredictorNode::on_set_compensation, this);
  srv_hold_trim_ = pnh_.advertiseService(iface.service_name<std_srvs::SetBool>("~set_hold_trim"), &PredictorNode::on_set_hold_trim, this);
  srv_reload_ = pnh_.advertiseService(iface.service_name<std_srvs::Trigger>("~reload_model"), &PredictorNode::on_reload, this);
  if (s_.snapshot_duration_s > 0.0) {
    setup_snapshot();
    srv_snapshot_ = pnh_.advertiseService(iface.service_name<std_srvs::Trigger>("~snapshot"), &PredictorNode::on_snapshot, this);
  }
  // Resuming from the file this run saves to: the history is read now, before this run's saves replace it; else at
  // the first sample (a ~snapshot of the run before may be written after the node started).
  std::error_code ec;
  if (!s_.resume_from.empty() &&
      std::filesystem::weakly_canonical(s_.resume_from, ec) == std::filesystem::weakly_canonical(s_.resume_save_to, ec)) {
    std::string why;
    resume_history(why);  // a file not there yet is "no history" for this run, not this run's own first save
  }
  if (!s_.resume_save_to.empty() && s_.resume_save_period_s > 0.0)
    resume_save_timer_ = nh_.createTimer(ros::Duration(s_.resume_save_period_s),
                                         [this](const ros::TimerEvent&) { save_resume("periodic"); });
  setup_diagnostics_and_watch();
  if (s_.drift_async) worker_ = std::thread([this] { forecast_worker(); });
}

void PredictorNode::add_axis(const std::string& name) {
  auto a = std::make_unique<Axis>();
  const std::string& path = s_.model_files.at(name);
  models::ModelPtr m;
  std::string error;
  try {
    m = load_model_file(path, name);
  } catch (const std::exception& e) {
    // Keep the axis movable: uncorrected commands with bounded steps, reported in diagnostics.
    error = e.what();
    ROS_ERROR("axis %s: ~model_file/%s: %s; running uncorrected (fallback) until ~reload_model succeeds",
              name.c_str(), name.c_str(), e.what());
  }
  a->logic = std::make_unique<PredictorAxis>(name, path, std::move(m), s_, error);
  a->logic->set_live_inputs(&live_);
  if (!s_.resume_from.empty())
    a->logic->set_resume_source([this](std::string& why) { return resume_history(why); });
  const auto& line = a->logic->compensator().ideal_line();
  ROS_INFO("axis %s: model %s (%s), ideal line %.4f nm/V, offset %.2f nm", name.c_str(), path.c_str(),
           a->logic->compensator().model().kind().c_str(), line.gain_nm_per_v, line.offset_nm);
  Axis* ap = a.get();
  const params::NodeInterface& iface = predictor_interface();
  a->pub_prediction = nh_.advertise<Prediction>(iface.topic_name<Prediction>("<axis>/prediction", name), 20);
  a->pub_command = nh_.advertise<VoltageCommand>(iface.topic_name<VoltageCommand>("<axis>/command", name), 1);
  // Sensor topics keep every sample through a stall of the host (kInputQueue samples: 18 s at 11 Hz, 0.45 s of
  // wall time at 40 x simulated time); a dropped one would be a gap in the snapshot and in the model's clock.
  a->sub_voltage = nh_.subscribe<AxisVoltage>(iface.topic_name<AxisVoltage>("<axis>/voltage", name), kInputQueue, [this, ap](const AxisVoltage::ConstPtr& m) {
    on_voltage(*ap, m);
  }, ros::VoidConstPtr(), ros::TransportHints().tcpNoDelay());
  a->sub_encoder = nh_.subscribe<EncoderPosition>(iface.topic_name<EncoderPosition>("<axis>/encoder", name), kInputQueue, [this, ap](const EncoderPosition::ConstPtr& m) {
    on_encoder(*ap, m);
  }, ros::VoidConstPtr(), ros::TransportHints().tcpNoDelay());
  a->sub_intended = nh_.subscribe<IntendedMotion>(iface.topic_name<IntendedMotion>("<axis>/intended", name), 10, [this, ap](const IntendedMotion::ConstPtr& m) {
    on_intended(*ap, m);
  });
  axes_.push_back(std::move(a));
}

// The whole buffer (not cut to a gap-free stretch, as ~snapshot's bag is: the resume runs across lost samples as the
// running model did), written as .part and renamed, so a reader never sees half a file.
void PredictorNode::save_resume(const char* when) {
  if (!snapshot_) return;
  try {
    const compensation::Snapshot snap = snapshot_->take();
    const std::filesystem::path dir = std::filesystem::path(s_.resume_save_to).parent_path();
    if (!dir.empty()) std::filesystem::create_directories(dir);
    write_snapshot_bag(s_.resume_save_to, nh_.getNamespace(), snap, s_.frame_prefix + "base");
    ROS_DEBUG("resume history saved (%s): %s, %.1f s", when, s_.resume_save_to.c_str(), snap.end_s - snap.begin_s);
  } catch (const std::exception& e) {
    ROS_WARN_THROTTLE(60.0, "~resume_save_to: nothing saved (%s): %s", when, e.what());
  }
}

const io::Dataset* PredictorNode::resume_history(std::string& why) {
  if (!resume_read_) {
    resume_read_ = true;
    const std::string& path = s_.resume_from;
    try {
      // a ~snapshot bag of this manipulator (its namespace), read as the reload's warm-up reads it (across lost
      // samples, as the running model ran); its rows are on the ROS clock of the live samples
      ros_io::BagOptions bo;
      bo.ns = nh_.getNamespace();
      io::Dataset d = ros_io::read_bag(path, bo);
      if (d.time_clock != "ros")
        throw io::DataError(path + ": its time column is not ROS time (a ~snapshot bag is)");
      resume_history_ = std::move(d);
    } catch (const std::exception& e) {
      resume_error_ = std::string("~resume_from: ") + e.what();
    }
  }
  why = resume_error_;
  return resume_history_ ? &*resume_history_ : nullptr;
}

void PredictorNode::subscribe_aux() {
  // Aux signals: each model input name mapped to a topic of either type (the type is taken from the publisher).
  for (const auto& [name, topic] : s_.aux_topics) {
    const std::string input = name;
    aux_subs_.push_back(nh_.subscribe<topic_tools::ShapeShifter>(
        topic, kInputQueue, [this, input](const topic_tools::ShapeShifter::ConstPtr& m) { on_aux(input, m); }));
  }
  for (const auto& a : axes_)
    for (const auto& src : a->logic->inputs().sources())
      if (src.kind == models::InputSource::Kind::kAux && !s_.aux_topics.count(src.name)) {
        ROS_WARN("axis %s: the model reads '%s', which ~aux_topics maps to no topic: it runs on its fallback",
                 a->logic->axis().c_str(), src.name.c_str());
      } else if (src.kind == models::InputSource::Kind::kAxisFused &&
                 std::none_of(axes_.begin(), axes_.end(), [&](const auto& b) { return b->logic->axis() == src.axis; })) {
        ROS_WARN("axis %s: the model reads '%s', but this predictor runs no model for axis %s: it runs on its fallback",
                 a->logic->axis().c_str(), src.name.c_str(), src.axis.c_str());
      }
}

bool PredictorNode::on_set_compensation(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res) {
  compensation_ = req.data;
  res.success = true;
  res.message = std::string("compensation ") + (compensation_ ? "on" : "off");
  ROS_INFO("%s", res.message.c_str());
  return true;
}

bool PredictorNode::on_set_hold_trim(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res) {
  res.message = std::string("hold trim ") + (req.data ? "on" : "off");
  for (auto& a : axes_) {
    a->logic->set_hold_trim(req.data);
    const auto* f = a->logic->compensator().estimator();
    if (req.data && !(f && f->fusing())) res.message += "; " + a->logic->axis() + " stays model-only (" +
                                                        a->logic->compensator().estimator_status() + ")";
  }
  res.success = true;
  ROS_INFO("%s", res.message.c_str());
  return true;
}

// ~reload_model: ~model_file is read again (an operator points it at the augmented model `piezo residual` wrote).
// All or nothing: a broken file leaves every axis on its current model.
bool PredictorNode::on_reload(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  std::map<std::string, std::string> files;
  std::string timing;
  try {
    files = read_model_files(pnh_, s_.axes);
    res.message = reload_models(files, timing);
  } catch (const std::exception& e) {
    res.success = false;
    res.message = std::string("reload failed, models unchanged: ") + e.what();
    ROS_ERROR("%s", res.message.c_str());
    return true;
  }
  s_.model_files = files;
  res.success = true;
  std::string warmth = res.message;
  res.message = "models reloaded:";
  for (const auto& [axis, path] : files) res.message += " " + axis + " " + path;
  res.message += warmth + timing;
  ROS_INFO("%s", res.message.c_str());
  return true;
}

// Loads every axis' file, warms each new model on the buffered samples and swaps them in; returns what was done
// per axis ("; c: warm, on the buffered ..."). Throws (nothing swapped) when a file cannot be loaded.
std::string PredictorNode::reload_models(const std::map<std::string, std::string>& files, std::string& timing) {
  const auto t_start = std::chrono::steady_clock::now();
  const auto secs = [](auto a, auto b) { return std::chrono::duration<double>(b - a).count(); };
  std::vector<models::ModelPtr> fresh;
  for (const auto& a : axes_) fresh.push_back(load_model_file(files.at(a->logic->axis()), a->logic->axis()));
  // Warm start on the buffered samples: a model with slow terms (a 300 s low-pass, creep) started at rest
  // would carry a transient of minutes that the offline score of the same model never saw.
  std::vector<std::string> cold(axes_.size());
  std::optional<compensation::Snapshot> recent;
  std::string no_recent = "no ~snapshot buffer (~snapshot_duration_s 0)";
  if (snapshot_) {
    try {
      recent = snapshot_->take();
    } catch (const std::exception& e) {
      no_recent = e.what();
    }
  }
  // An augmented model on the running base (`piezo residual` keeps a model file's weights) continues
  // from the running base, which has seen the true history, not from the window's start.
  std::vector<std::string> handover(axes_.size());
  const auto t_loaded = std::chrono::steady_clock::now();
  for (std::size_t i = 0; i < axes_.size(); ++i)
    cold[i] = recent ? warm_model(*fresh[i], axes_[i]->logic->axis(), *recent, nh_.getNamespace(),
                                  &axes_[i]->logic->compensator().model(), &handover[i])
                     : no_recent;
  const auto t_warm = std::chrono::steady_clock::now();
  for (std::size_t i = 0; i < axes_.size(); ++i)
    axes_[i]->logic->reload(files.at(axes_[i]->logic->axis()), std::move(fresh[i]), cold[i].empty());
  const auto t_done = std::chrono::steady_clock::now();
  std::ostringstream took;
  took << std::fixed << std::setprecision(2) << "; took " << secs(t_start, t_done) << " s (load "
       << secs(t_start, t_loaded) << ", warm-up " << secs(t_loaded, t_warm) << ", ideal line "
       << secs(t_warm, t_done) << ")";
  timing = took.str();
  std::string message;
  if (recent && !recent->gaps.empty()) {
    // the running model skipped the same samples: the warm-up runs across the gaps as it did
    message += "; the window has " + compensation::describe_gaps(*recent) +
               ": warmed across the gap(s) as the running model ran";
  }
  for (std::size_t i = 0; i < axes_.size(); ++i)
    message += "; " + axes_[i]->logic->axis() + ": " + warmth(axes_[i]->logic->axis(), cold[i], handover[i], recent);
  return message;
}

std::string PredictorNode::warmth(const std::string& axis, const std::string& cold, const std::string& handover,
                                  const std::optional<compensation::Snapshot>& recent) const {
  if (!cold.empty()) return "cold start (" + cold + ")";
  // the span buffered, not the window: a node up for less than ~snapshot_duration_s (or a ring at
  // ~snapshot_max_messages) holds less, and the reply says so rather than read as a short window
  const double span_s = recent->end_s - recent->begin_s;
  const double window_s = snapshot_->options().duration_s;
  std::ostringstream os;
  os << std::fixed << std::setprecision(1) << "warm, on the buffered " << span_s << " s ("
     << recent->axes.at(axis).readings.size() << " readings";
  if (span_s < window_s - 2.0 * recent->period_s - recent->max_restamp_s) os << ", less than the " << window_s << " s window";
  os << ")";
  return os.str() + (handover.empty() ? "" : ", " + handover);
}

void PredictorNode::setup_snapshot() {
  compensation::SnapshotOptions so;
  so.duration_s = s_.snapshot_duration_s;
  so.max_messages = static_cast<std::size_t>(s_.snapshot_max_messages);
  so.expected_rate_hz = 0.0;  // the fastest axis' sample rate (~sample_rate_hz, else its model's, else 11 Hz)
  for (const auto& a : axes_) {
    so.axes.push_back(a->logic->axis());
    const double model_hz = a->logic->compensator().model().meta.sample_rate_hz;
    so.expected_rate_hz = std::max(so.expected_rate_hz, s_.sample_rate_hz > 0 ? s_.sample_rate_hz
                                                                               : model_hz > 0 ? model_hz : 11.0);
  }
  if (!(so.expected_rate_hz > 0.0)) so.expected_rate_hz = 11.0;
  for (const auto& [name, topic] : s_.aux_topics) so.aux.push_back(name);
  snapshot_ = std::make_unique<compensation::SnapshotBuffer>(so);
}

bool PredictorNode::on_snapshot(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  try {
    // the offline tools refuse a time column with missing samples: a stretch without one is written
    const auto& so = snapshot_->options();
    const compensation::SnapshotStretch cut =
        compensation::gap_free_stretch(snapshot_->take(), so.prefer_recent_fraction, so.min_fraction);
    const compensation::Snapshot& snap = cut.snapshot;
    const std::string path = snapshot_path(snapshot_directory(s_.snapshot_dir), snap.end_s);
    write_snapshot_bag(path, nh_.getNamespace(), snap, s_.frame_prefix + "base");
    std::size_t readings = 0;
    for (const auto& [axis, a] : snap.axes) readings += a.readings.size();
    std::ostringstream os;
    os << path << " (" << std::fixed << std::setprecision(1) << snap.end_s - snap.begin_s << " s, "
       << snap.axes.size() << " axes, " << readings << " readings, " << snap.aux.size() << " aux signals, "
       << std::setprecision(4) << snap.period_s * 1e3 << " ms sample clock, receive stamps within "
       << snap.max_restamp_s * 1e3 << " ms of it";
    if (snap.invalid_readings > 0) os << ", " << snap.invalid_readings << " invalid readings left out";
    os << ")";
    if (!cut.message.empty()) os << "; " << cut.message;
    res.success = true;
    res.message = os.str();
    if (cut.message.empty()) ROS_INFO("snapshot: %s", res.message.c_str());
    else ROS_WARN("snapshot: %s", res.message.c_str());
  } catch (const std::exception& e) {
    res.success = false;
    res.message = std::string("no snapshot written: ") + e.what();
    ROS_ERROR("%s", res.message.c_str());
  }
  return true;
}

void PredictorNode::setup_diagnostics_and_watch() {
  diag_ = std::make_unique<diagnostic_updater::Updater>(nh_, pnh_);
  diag_->setHardwareID(s_.hardware_id);
  for (auto& a : axes_) {
    Axis* ap = a.get();
    diag_->add("axis " + a->logic->axis(), [this, ap](diagnostic_updater::DiagnosticStatusWrapper& st) { diagnose(*ap, st); });
  }
  if (snapshot_) {
    diag_->add("snapshot buffer", [this](diagnostic_updater::DiagnosticStatusWrapper& st) {
      // a ring that outgrew its start-up allocation re-allocated in a message callback
      const std::size_t grown = snapshot_->grown();
      if (grown > 0)
        st.summary(diagnostic_msgs::DiagnosticStatus::WARN,
                   "a snapshot ring grew " + std::to_string(grown) + " time(s) (an allocation in the message callback): "
                   "a stream came faster than the rate the rings were sized for (~sample_rate_hz or the model's)");
      else
        st.summary(diagnostic_msgs::DiagnosticStatus::OK, "rings within their start-up allocation");
      st.add("rings grown", grown);
      st.add("capacity [messages]", snapshot_->capacity());
      st.add("held [messages]", snapshot_->messages());
      st.add("sized for [Hz]", snapshot_->options().expected_rate_hz);
      st.add("duration [s]", snapshot_->options().duration_s);
    });
  }
  diag_probe_ = nh_.advertise<diagnostic_msgs::DiagnosticArray>(
      predictor_interface().topic_name<diagnostic_msgs::DiagnosticArray>("/diagnostics"), 1);
  diag_timer_ = nh_.createTimer(ros::Duration(1.0), [this](const ros::TimerEvent&) {
    if (diag_probe_.getNumSubscribers() > 0) diag_->update();
  });
  if (s_.watch.noise_floor_nm > 0.0) {
    // rolling free-run MAE per axis [m] (SI), once a second
    for (auto& a : axes_)
      a->pub_watch = nh_.advertise<std_msgs::Float64>(
          predictor_interface().topic_name<std_msgs::Float64>("<axis>/residual_mae", a->logic->axis()), 2);
    watch_timer_ = nh_.createTimer(ros::Duration(1.0), [this](const ros::TimerEvent&) {
      for (auto& a : axes_) {
        const auto* w = a->logic->watch();
        if (!w || !std::isfinite(w->rolling_mae_nm())) continue;
        std_msgs::Float64 m;
        m.data = w->rolling_mae_nm() / kNmPerM;
        a->pub_watch.publish(m);
      }
    });
  }
}

PredictorNode::~PredictorNode() {
  if (!s_.resume_save_to.empty()) save_resume("at shutdown");
  {
    std::lock_guard<std::mutex> lk(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  if (worker_.joinable()) worker_.join();
}

void PredictorNode::on_aux(const std::string& input, const topic_tools::ShapeShifter::ConstPtr& m) {
  double value = std::nan("");
  ros::Time stamp;
  const std::string& type = m->getDataType();
  if (type == "std_msgs/Float64") {
    value = m->instantiate<std_msgs::Float64>()->data;
  } else if (type == "sensor_msgs/Temperature") {
    auto t = m->instantiate<sensor_msgs::Temperature>();
    value = t->temperature;
    stamp = t->header.stamp;
  } else {
    ROS_ERROR_THROTTLE(5.0, "~aux_topics/%s: topic has type %s; expected std_msgs/Float64 or sensor_msgs/Temperature",
                       input.c_str(), type.c_str());
    return;
  }
  if (!std::isfinite(value)) {
    ROS_WARN_THROTTLE(5.0, "~aux_topics/%s: non-finite value ignored", input.c_str());
    return;
  }
  const ros::Time now = ros::Time::now();
  // a sample takes the value stamped at or before its own stamp: the sensor's stamp when it has one; staleness
  // counts from that stamp too, never from the future
  const double stamp_s = (stamp.isZero() ? now : stamp).toSec();
  live_.add_aux(input, value, stamp_s, std::min(stamp_s, now.toSec()));
  if (snapshot_) snapshot_->add_aux(input, value, stamp_s);
}

void PredictorNode::poll_others(const Axis& except, const ros::Time& now) {
  for (auto& b : axes_) {
    if (b.get() == &except) continue;
    auto outs = b->logic->poll(compensation_, now);
    if (!outs.empty()) emit(*b, outs, now);
  }
}

void PredictorNode::on_voltage(Axis& a, const AxisVoltage::ConstPtr& msg) {
  const auto t0 = std::chrono::steady_clock::now();
  const ros::Time now = ros::Time::now();
  if (std::isfinite(msg->voltage)) live_.add_voltage(a.logic->axis(), msg->sequence, msg->voltage);
  if (snapshot_) snapshot_->add_voltage(a.logic->axis(), msg->sequence, msg->voltage, msg->header.stamp.toSec());
  auto outs = a.logic->on_voltage(*msg, compensation_, now);
  if (!outs.empty()) emit(a, outs, now);
  poll_others(a, now);
  const double us = std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - t0).count();
  if (!outs.empty()) a.processing_us.push_back(us);
  if (a.processing_us.size() > 2000) a.processing_us.pop_front();
}

void PredictorNode::on_intended(Axis& a, const IntendedMotion::ConstPtr& msg) {
  std::string error;
  if (!a.logic->on_intended(*msg, error)) {
    ROS_ERROR_THROTTLE(1.0, "axis %s: %s", a.logic->axis().c_str(), error.c_str());
    return;
  }
  VoltageCommand cmd;
  if (a.logic->command_now(compensation_, cmd, ros::Time::now())) a.pub_command.publish(cmd);
}

void PredictorNode::on_encoder(Axis& a, const EncoderPosition::ConstPtr& msg) {
  const auto t0 = std::chrono::steady_clock::now();
  const ros::Time now = ros::Time::now();
  if (s_.drift_async) {
    std::lock_guard<std::mutex> lk(mutex_);
    auto it = results_.find(a.logic->axis());
    if (it != results_.end()) {
      a.logic->set_forecast(it->second);
      results_.erase(it);
    }
  }
  if (msg->valid && std::isfinite(msg->position))
    live_.add_reading(a.logic->axis(), msg->sequence, msg->position * kNmPerM);
  if (snapshot_)
    snapshot_->add_reading(a.logic->axis(), msg->sequence, msg->position * kNmPerM, msg->valid,
                           msg->header.stamp.toSec());
  auto outs = a.logic->on_encoder(*msg, compensation_, now);
  if (!outs.empty()) emit(a, outs, now);
  poll_others(a, now);
  const double us = std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - t0).count();
  if (!outs.empty()) a.processing_us.push_back(us);
  if (a.processing_us.size() > 2000) a.processing_us.pop_front();
}

void PredictorNode::emit(Axis& a, std::vector<PredictorAxis::Output>& outs, const ros::Time& now) {
  for (auto& out : outs) {
    // another axis' model may read this axis' fused position (models::InputSource::Kind::kAxisFused)
    if (std::isfinite(out.prediction.fused_position))
      live_.add_fused(a.logic->axis(), out.sequence, out.prediction.fused_position * kNmPerM);
    if (snapshot_ && std::isfinite(out.base_predicted_nm) && out.stamp_s > 0.0)
      snapshot_->add_prediction(a.logic->axis(), out.sequence, out.base_predicted_nm, out.stamp_s);
    if (out.send) a.pub_command.publish(out.command);
    a.pub_prediction.publish(out.prediction);
    if (out.forecast_due) start_forecast(a);
    if (out.prediction.fallback)
      ROS_WARN_THROTTLE(2.0, "axis %s: fallback: %s", a.logic->axis().c_str(), out.prediction.status.c_str());
  }
  if (last_tf_.isZero() || (now - last_tf_).toSec() >= s_.tf_period_s || now < last_tf_) {
    last_tf_ = now;
    if (tf_probe_.getNumSubscribers() > 0 || markers_pub_.getNumSubscribers() > 0)
      publish_tf_and_markers(outs.back().prediction.header.stamp);
  }
}

void PredictorNode::start_forecast(Axis& a) {
  auto clone = a.logic->compensator().model().clone();
  {
    std::lock_guard<std::mutex> lk(mutex_);
    jobs_[a.logic->axis()] = {std::move(clone), a.logic->hold_voltage_v(), a.logic->compensator().next_inputs()};
  }
  cv_.notify_one();
}

void PredictorNode::forecast_worker() {
  std::unique_lock<std::mutex> lk(mutex_);
  for (;;) {
    cv_.wait(lk, [this] { return stop_ || !jobs_.empty(); });
    if (stop_) return;
    auto node = jobs_.extract(jobs_.begin());
    lk.unlock();
    const ForecastJob& job = node.mapped();
    const double rate = s_.sample_rate_hz > 0 ? s_.sample_rate_hz : job.model->meta.sample_rate_hz;
    compensation::DriftForecast f = compensation::forecast_drift(*job.model, job.hold_v, s_.drift_horizons_s, rate,
                                                                 job.inputs.empty() ? nullptr : job.inputs.data());
    lk.lock();
    results_[node.key()] = std::move(f);
  }
}

void PredictorNode::publish_tf_and_markers(const ros::Time& stamp) {
  // Axis a → x, b → y, c → z of <prefix>base.
  double measured[3] = {0, 0, 0}, predicted[3] = {0, 0, 0}, intended[3] = {0, 0, 0}, drift[3] = {0, 0, 0};
  std::ostringstream text;
  text << std::fixed << std::setprecision(0);
  for (const auto& a : axes_) {
    const PredictorAxis& l = *a->logic;
    const int i = io::axis_index_or_none(l.axis());
    if (i < 0 || !l.compensator().started()) continue;
    measured[i] = l.has_measurement() ? l.measured_nm() : std::nan("");
    predicted[i] = l.predicted_nm();
    intended[i] = l.intended_nm();
    const double d = l.drift_longest_nm();
    drift[i] = std::isfinite(d) ? d : 0.0;
    text << l.axis() << ": err " << (predicted[i] - intended[i]) << " nm, meas-pred "
         << (l.has_measurement() ? measured[i] - predicted[i] : 0.0) << " nm, drift " << drift[i] << " nm"
         << (l.fallback_now() ? " FALLBACK" : "") << "\n";
  }
  const std::string base = s_.frame_prefix + "base";
  auto tfm = [&](const std::string& child, const double* x) {
    geometry_msgs::TransformStamped t;
    t.header.stamp = stamp;
    t.header.frame_id = base;
    t.child_frame_id = s_.frame_prefix + child;
    t.transform.translation.x = std::isfinite(x[0]) ? x[0] / kNmPerM : 0.0;
    t.transform.translation.y = std::isfinite(x[1]) ? x[1] / kNmPerM : 0.0;
    t.transform.translation.z = std::isfinite(x[2]) ? x[2] / kNmPerM : 0.0;
    t.transform.rotation.w = 1.0;
    return t;
  };
  tf_->sendTransform(std::vector<geometry_msgs::TransformStamped>{
      tfm("tip_measured", measured), tfm("tip_predicted", predicted), tfm("tip_intended", intended)});
  publish_markers(stamp, measured, predicted, intended, drift, text.str());
}

// Markers at marker_scale: nanometre motion is invisible at rviz's smallest view distance.
void PredictorNode::publish_markers(const ros::Time& stamp, const double* measured, const double* predicted,
                                    const double* intended, const double* drift, const std::string& text) {
  const std::string base = s_.frame_prefix + "base";
  const double k = s_.marker_scale / kNmPerM;
  visualization_msgs::MarkerArray arr;
  auto marker = [&](int id, int type, const char* ns) {
    visualization_msgs::Marker m;
    m.header.stamp = stamp;
    m.header.frame_id = base;
    m.ns = ns;
    m.id = id;
    m.type = type;
    m.action = visualization_msgs::Marker::ADD;
    m.pose.orientation.w = 1.0;
    m.color.a = 1.0;
    return m;
  };
  auto point = [&](const double* x) {
    geometry_msgs::Point p;
    p.x = std::isfinite(x[0]) ? x[0] * k : 0.0;
    p.y = std::isfinite(x[1]) ? x[1] * k : 0.0;
    p.z = std::isfinite(x[2]) ? x[2] * k : 0.0;
    return p;
  };
  const double r = 100.0 * k;  // spheres of 100 nm (scaled)
  struct Tip { const char* ns; const double* x; float rgb[3]; };
  const Tip tips[] = {{"tip_measured", measured, {0.2f, 0.4f, 1.0f}},
                      {"tip_predicted", predicted, {1.0f, 0.5f, 0.0f}},
                      {"tip_intended", intended, {0.1f, 0.8f, 0.1f}}};
  int id = 0;
  for (const auto& t : tips) {
    auto m = marker(id++, visualization_msgs::Marker::SPHERE, t.ns);
    m.pose.position = point(t.x);
    m.scale.x = m.scale.y = m.scale.z = r;
    m.color.r = t.rgb[0], m.color.g = t.rgb[1], m.color.b = t.rgb[2];
    arr.markers.push_back(m);
  }
  auto arrow = marker(id++, visualization_msgs::Marker::ARROW, "drift");
  const double end[3] = {predicted[0] + drift[0], predicted[1] + drift[1], predicted[2] + drift[2]};
  arrow.points = {point(predicted), point(end)};
  arrow.scale.x = r * 0.3, arrow.scale.y = r * 0.7, arrow.scale.z = r * 0.7;
  arrow.color.r = 1.0, arrow.color.g = 0.1, arrow.color.b = 0.1;
  arr.markers.push_back(arrow);
  auto label = marker(id++, visualization_msgs::Marker::TEXT_VIEW_FACING, "error_text");
  label.pose.position = point(predicted);
  label.pose.position.z += 6.0 * r;
  label.scale.z = r * 0.8;
  label.color.r = label.color.g = label.color.b = 1.0;
  label.text = text;
  arr.markers.push_back(label);
  markers_pub_.publish(arr);
}

void PredictorNode::diagnose(Axis& a, diagnostic_updater::DiagnosticStatusWrapper& st) {
  const PredictorAxis& l = *a.logic;
  std::vector<double> t(a.processing_us.begin(), a.processing_us.end());
  std::sort(t.begin(), t.end());
  const double p99 = t.empty() ? 0.0 : t[std::min(t.size() - 1, static_cast<std::size_t>(0.99 * t.size()))];
  if (!l.model_error().empty())
    st.summary(diagnostic_msgs::DiagnosticStatus::ERROR, "model unavailable, uncorrected commands: " + l.model_error());
  else if (!l.compensator().started())
    st.summary(diagnostic_msgs::DiagnosticStatus::WARN, "no encoder sample yet");
  else if (l.fallback_now())
    st.summary(diagnostic_msgs::DiagnosticStatus::WARN, "fallback to uncorrected command: " + l.last_status());
  else if (l.watch() && l.watch()->warning())
    st.summary(diagnostic_msgs::DiagnosticStatus::WARN, l.watch()->message(l.axis()));
  else if (l.inputs().any_fallback())
    st.summary(diagnostic_msgs::DiagnosticStatus::WARN, l.input_status() +
                                                            " (that term runs on its fallback; check the topic)");
  else
    st.summary(diagnostic_msgs::DiagnosticStatus::OK, compensation_ ? "compensating" : "predicting (compensation off)");
  st.add("model", l.model_name());
  st.add("model kind", l.compensator().model().kind());
  st.add("compensation", compensation_ ? "on" : "off");
  st.add("encoder messages", l.encoder_messages());
  st.add("rejected messages", l.rejected_messages());
  // pairing under the one rule (io/sequence_pairer.h)
  st.add("lost voltage reports", l.pairing().lost_voltages);
  st.add("lost encoder readings", l.pairing().lost_readings);
  st.add("late encoder readings", l.pairing().late_readings);
  st.add("controller restarts", l.pairing().restarts);
  st.add("prediction failures", l.compensator().prediction_failures());
  st.add("command fallbacks", l.compensator().command_fallbacks());
  st.add("last fallback reason", l.last_status());
  st.add("ideal gain [nm/V]", l.compensator().ideal_line().gain_nm_per_v);
  // the estimator and the hold trim: what the fused estimate is made of and what the trim is doing
  const compensation::AxisCompensator& cc = l.compensator();
  st.add("estimator", cc.estimator_status());
  if (!s_.resume_from.empty())
    st.add("resume", l.resume_status().empty() ? std::string("waiting for the first sample") : l.resume_status());
  if (s_.axis.start_estimate_s > 0)
    st.add("start estimate", cc.start_estimate_status().empty() ? std::string("waiting for the first ~start_estimate_s")
                                                                : cc.start_estimate_status());
  if (cc.estimator() && cc.estimator()->fusing()) {
    st.add("fused 1σ [nm]", cc.estimator()->sigma_nm());
    st.add("estimated model error [nm]", cc.estimator()->error_nm());
    st.add("samples since a reading", cc.estimator()->samples_since_reading());
    st.add("zero known", cc.estimator()->zero_known() ? std::string("yes") : std::string("no: the model's error is "
                                                                                       "not pinned yet (move the axis)"));
    st.add("stale encoder readings", cc.estimator()->stale_readings());
  }
  st.add("hold trim", std::string(compensation::trim_state_name(cc.hold_trim().state())) +
                          (cc.hold_trim().enabled() ? "" : " (~hold_trim off)"));
  st.add("hold trim [nm]", cc.hold_trim().trim_nm());
  st.add("hold trim bound [nm]", cc.hold_trim().options().max_nm);
  st.add("settled for [s]", cc.hold_trim().settled_s());
  st.add("processing p99 [us]", p99);
  if (l.watch()) {
    st.add("rolling free-run MAE [nm]", l.watch()->rolling_mae_nm());
    st.add("watch threshold [nm]", l.watch()->threshold_nm());
    st.add("above threshold for [s]", l.watch()->above_for_s());
  }
  const auto& srcs = l.inputs().sources();
  for (std::size_t k = 0; k < srcs.size(); ++k) {
    const auto& in = l.inputs().states()[k];
    st.add("input " + srcs[k].name, in.fallback ? "FALLBACK: " + in.status : "fed " + std::to_string(in.fed));
    st.add("input " + srcs[k].name + " fallback samples", in.fallback_samples);
  }
}

}  // namespace piezo::predictor
