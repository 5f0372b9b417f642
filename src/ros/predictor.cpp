// The piezo_predictor node shell: its axes, topics and services, the message callbacks and the drift-forecast worker
// thread (the other jobs: include/piezo_compensation/ros/predictor.h).
#include "piezo_compensation/ros/predictor.h"

#include <diagnostic_updater/diagnostic_updater.h>
#include <sensor_msgs/Temperature.h>
#include <std_msgs/Float64.h>
#include <tf2_msgs/TFMessage.h>
#include <tf2_ros/transform_broadcaster.h>
#include <visualization_msgs/MarkerArray.h>

#include <algorithm>
#include <chrono>
#include <filesystem>

#include "piezo_compensation/ros/interfaces.h"

namespace piezo::predictor {

namespace {

// Sensor topics keep every sample through a stall of the host (kInputQueue samples: 18 s at 11 Hz, 0.45 s of wall
// time at 40 x simulated time); a dropped one would be a gap in the snapshot and in the model's clock.
constexpr std::uint32_t kInputQueue = 200;

}  // namespace

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
  srv_tracking_trim_ = pnh_.advertiseService(iface.service_name<std_srvs::SetBool>("~set_tracking_trim"), &PredictorNode::on_set_tracking_trim, this);
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
    m = load_for_axis(path, name);
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

bool PredictorNode::on_set_tracking_trim(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res) {
  res.message = std::string("tracking trim ") + (req.data ? "on" : "off");
  for (auto& a : axes_) {
    a->logic->set_tracking_trim(req.data);
    const auto* f = a->logic->compensator().estimator();
    if (req.data && !(f && f->fusing())) res.message += "; " + a->logic->axis() + " stays model-only (" +
                                                        a->logic->compensator().estimator_status() + ")";
  }
  res.success = true;
  ROS_INFO("%s", res.message.c_str());
  return true;
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
    jobs_[a.logic->axis()] = {std::move(clone), a.logic->hold_voltage_v(), a.logic->compensator().next_inputs(),
                              a.logic->estimator_state()};
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
    compensation::DriftForecast f = compensation::forecast_drift(*job.model, job.hold_v, s_.drift_horizons_s,
                                                                 step_rate_hz(s_, *job.model),
                                                                 job.inputs.empty() ? nullptr : job.inputs.data(),
                                                                 job.estimator ? &*job.estimator : nullptr);
    lk.lock();
    results_[node.key()] = std::move(f);
  }
}

}  // namespace piezo::predictor
