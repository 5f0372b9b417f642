// The predictor's /diagnostics (per axis: model, estimator, hold trim, watch, inputs; the snapshot buffer) and the
// residual watch's <axis>/residual_mae.
#include "piezo_compensation/ros/predictor.h"

#include <diagnostic_msgs/DiagnosticArray.h>
#include <diagnostic_updater/diagnostic_updater.h>
#include <std_msgs/Float64.h>

#include <algorithm>

#include "piezo_compensation/ros/interfaces.h"

namespace piezo::predictor {

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
  const compensation::TrackingTrim& tt = cc.tracking_trim();
  st.add("tracking trim", std::string(compensation::tracking_state_name(tt.state())) +
                              (tt.enabled() ? "" : " (~tracking_trim off)"));
  if (tt.enabled()) {
    st.add("tracking trim [nm]", tt.trim_nm());
    st.add("tracking trim bound [nm]", tt.options().max_nm);
    st.add("tracking trim fallback reason", tt.reason().empty() ? std::string("none") : tt.reason());
    st.add("tracking trim fallbacks", tt.fallbacks());
  }
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
