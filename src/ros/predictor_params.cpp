#include "piezo_compensation/ros/predictor_params.h"

#include <stdexcept>

#include "piezo_compensation/analysis/selection/model_selection.h"
#include "piezo_compensation/compensation/model_check.h"
#include "piezo_compensation/ros/interfaces.h"
#include "piezo_compensation/ros/params.h"

namespace piezo::predictor {

double step_rate_hz(const PredictorSettings& s, const models::Model& m) {
  if (s.sample_rate_hz > 0.0) return s.sample_rate_hz;
  return m.meta.sample_rate_hz > 0.0 ? m.meta.sample_rate_hz : kFallbackSampleRateHz;
}

models::ModelPtr load_model_file(const std::string& path, const std::string& axis) {
  models::ModelPtr m = compensation::load_compensator_model(path, axis);
  // `piezo fit`'s identification check (docs/predictor.md): at start-up and at every ~reload_model
  const std::string unidentified = analysis::unidentified_model_warning(*m, path);
  if (!unidentified.empty()) ROS_WARN("%s", unidentified.c_str());
  return m;
}

models::ModelPtr load_axis_model(const std::string& path, const std::string& axis, const PredictorSettings& s,
                                 const std::string& allow_param) {
  models::ModelPtr m = load_model_file(path, axis);
  const compensation::TransportCheck c =
      compensation::check_model_transport(m->meta, s.real_transport(), s.allow_simulated_model, path, allow_param);
  if (!c.error.empty()) throw std::runtime_error(c.error);
  if (!c.warning.empty()) ROS_WARN("axis %s: %s", axis.c_str(), c.warning.c_str());
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
      text("transport", d.transport,
           "where the commands go (the launch files set it): real (a controller: a model fitted on simulated data is "
           "refused unless allow_simulated_model), simulated (the simulated device) or replay (a bag played back)")
          .rule("real, simulated or replay"),
      flag("allow_simulated_model", d.allow_simulated_model,
           "transport real: run a model fitted on simulated data anyway (it compensates the simulator's physics)"),
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
  const compensation::TrackingTrimOptions& k = a.tracking_trim;
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
      flag("tracking_trim", k.enabled, "correct the feedforward from the fused estimate while the axis moves"),
      number("tracking_trim_period_s", "s", k.period_s, 0.01, 3600.0,
             "the trim takes its aim (the model's error, forecast half a period ahead) once per period"),
      number("tracking_trim_max_nm", "nm", k.max_nm, 0.0, 1e6, "bound on |tracking trim| (0 = 2 % of the ideal stroke)"),
      number("tracking_trim_slew_nm_per_s", "nm/s", k.slew_nm_per_s, 1e-6, 1e6,
             "largest change of the tracking trim per second"),
      number("tracking_trim_deadband_sigma", "fused 1σ", k.deadband_sigma, 0.0, 100.0,
             "the tracking trim acts on the part of the model's error beyond this many fused σ (0 = none)"),
      number("tracking_trim_glitch_window_s", "s", k.glitch_window_s, 0.01, 3600.0,
             "readings refused by the estimator are counted over this long"),
      integer("tracking_trim_glitch_count", "readings", static_cast<int>(k.glitch_count), 1, 100000,
              "this many refused readings within the window: the encoder is glitching, feedforward only"),
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
  compensation::TrackingTrimOptions& k = s.axis.tracking_trim;
  k.enabled = r.flag("tracking_trim");
  k.period_s = r.number("tracking_trim_period_s");
  k.max_nm = r.number("tracking_trim_max_nm");
  k.slew_nm_per_s = r.number("tracking_trim_slew_nm_per_s");
  k.deadband_sigma = r.number("tracking_trim_deadband_sigma");
  k.glitch_window_s = r.number("tracking_trim_glitch_window_s");
  k.glitch_count = static_cast<std::size_t>(r.integer("tracking_trim_glitch_count"));
  k.stale_after_s = t.stale_after_s;
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
        {"~set_tracking_trim", "std_srvs/SetBool", "tracking trim on or off (every axis)"},
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
  s.transport = r.text("transport");
  if (s.transport != "real" && s.transport != "simulated" && s.transport != "replay")
    throw std::invalid_argument("parameter " + r.resolved("transport") + " must be real, simulated or replay, not '" +
                                s.transport + "'");
  s.allow_simulated_model = r.flag("allow_simulated_model");
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

}  // namespace piezo::predictor
