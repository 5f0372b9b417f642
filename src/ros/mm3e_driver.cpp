#include "piezo_compensation/ros/mm3e_driver.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/ros/interfaces.h"
#include "piezo_compensation/ros/mm3e_params.h"
#include "piezo_compensation/ros/nanocontrol_params.h"

namespace piezo::mm3e {

using piezo_compensation::AxisVoltage;
using piezo_compensation::EncoderPosition;
using piezo_compensation::VoltageCommand;

namespace {
std::string hex(std::uint32_t v) {
  char b[16];
  std::snprintf(b, sizeof b, "0x%X", v);
  return b;
}
}  // namespace

const params::NodeInterface& driver_interface() {
  using namespace params;
  static const NodeInterface t = [] {
    NodeInterface n;
    n.node = "mm3e_driver";
    n.summary = "one manipulator's CAN bus or NanoControl serial port: voltage commands out (clamped, slew-limited, "
                "watchdog), reports in";
    n.params = transport_params(47100, 47101);
    const std::vector<ParamDef> rest = {
        text("frame_prefix", "", "header frame_id of every message is <prefix>base"),
        text("hardware_id", "", "diagnostics hardware_id; \"\" = mm3e@<interface or udp port>/node 0x<base_node_id>"),
        flag("stamp_with_receive_time", true,
             "stamp reports with the kernel receive time (SO_TIMESTAMP); false = ROS time at reception"),
        number("min_voltage_v", "V", -80.0, -can::kVoltageCeilingV, can::kVoltageCeilingV, "lowest voltage ever sent")
            .rule("< max_voltage_v"),
        number("max_voltage_v", "V", 80.0, -can::kVoltageCeilingV, can::kVoltageCeilingV, "highest voltage ever sent"),
        number("slew_rate_v_per_s", "V/s", 200.0, 1e-3, can::kSlewRateCeilingVPerS,
               "largest rate of change of the applied voltage"),
        number("command_timeout_s", "s", 0.5, 1e-3, 3600.0,
               "no command for this long: hold the last applied voltage (never 0 V)"),
        number("max_step_dt_s", "s", 0.1, 1e-4, can::kStepDtCeilingS, "longest interval one output step may cover"),
        number("max_frame_step_v", "V", 5.0, 1e-3, can::kFrameStepCeilingV,
               "hard cap on the change one frame may carry, whatever the clock did"),
        number("max_unconfirmed_v", "V", 10.0, 1e-3, 2 * can::kFrameStepCeilingV,
               "how far the set point may run ahead of the last voltage report that matched")
            .rule(">= max_frame_step_v"),
        number("max_stamp_ahead_s", "s", 0.5, 1e-3, 60.0, "a command stamped further ahead of now is refused"),
        number("report_tolerance_v", "V", 0.5, 1e-3, 10.0,
               "a voltage report this far from every recently written value does not match"),
        number("report_lag_s", "s", 0.5, 1e-3, 10.0, "how long written values may still show in a report"),
        integer("report_mismatch_count", "", 3, 1, 100,
                "reports in a row that match nothing written: the axis is held, ERROR, ~recover clears"),
        number("encoder_timeout_s", "s", 0.5, 1e-3, 3600.0, "wall time without an encoder frame before an axis is silent"),
        number("silence_reconnect_s", "s", 2.0, 1e-3, 3600.0,
               "wall time without any device frame before the transport is reopened")
            .rule("sync_mode: > 1.25 × sync_idle_s"),
        number("reconnect_min_s", "s", 0.1, 1e-3, 60.0, "first reconnect delay (doubles per failure)"),
        number("reconnect_max_s", "s", 5.0, 1e-3, 3600.0, "longest reconnect delay").rule(">= reconnect_min_s"),
        integer("receive_poll_ms", "ms", 20, 1, 1000, "receive thread wake-up period"),
        number("output_rate_hz", "Hz", 200.0, 1.0, 10000.0, "rate of the slew ramp and watchdog tick"),
        number("diagnostic_period_s", "s", 1.0, 0.05, 60.0, "diagnostics publishing period (wall)"),
        flag("sync_mode", false,
             "synchronous mode: the device samples on this node's SYNC, sent once every commanded axis has its "
             "command (simulated device over udp only)"),
        number("sync_idle_s", "s", 0.5, 0.001, 60.0, "sync_mode: with no complete set of commands for this long (wall), SYNC anyway"),
        integer("sync_max_in_flight", "SYNCs", 0, 0, 1000,
                "sync_mode: a complete set of commands waits while this many SYNCs have no reading (0: no bound)")
            .rule("> 0 needs sync_mode"),
    };
    n.params.insert(n.params.end(), rest.begin(), rest.end());
    const auto serial = nanocontrol_driver_params();
    n.params.insert(n.params.end(), serial.begin(), serial.end());
    const auto protocol = protocol_params();
    n.params.insert(n.params.end(), protocol.begin(), protocol.end());
    using D = TopicDef::Direction;
    n.topics = {
        {"<axis>/voltage", "piezo_compensation/AxisVoltage", D::kPublishes,
         "voltage the controller applied [V], stamped with the CAN receive time, with its sample sequence"},
        {"<axis>/encoder", "piezo_compensation/EncoderPosition", D::kPublishes, "measured position [m], stamped, sequence"},
        {"<axis>/command", "piezo_compensation/VoltageCommand", D::kSubscribes, "voltage to apply [V] (queue 1)"},
        {"/diagnostics", "diagnostic_msgs/DiagnosticArray", D::kPublishes,
         "bus and per-axis status; with nanocontrol also the serial link (refusals, timeouts, breakdown, reading σ)"},
    };
    n.services = {
        {"~halt", "std_srvs/Trigger", "hold every axis at its applied voltage and refuse commands until ~recover"},
        {"~recover", "std_srvs/Trigger", "clear a halt or a held axis (report mismatch) and accept commands again"},
    };
    return n;
  }();
  return t;
}

namespace {
// The command limits, the encoder timeout and the reconnect policy. Ranges stop at the compile-time ceilings of
// can/command_limiter.h (docs/driver.md).
void read_limits(params::ParamReader& r, const ros::NodeHandle& pnh, can::DriverConfig& config) {
  auto& lim = config.limits;
  lim.min_voltage_v = r.number("min_voltage_v");
  lim.max_voltage_v = r.number("max_voltage_v");
  if (lim.min_voltage_v >= lim.max_voltage_v)
    throw std::invalid_argument("parameter " + pnh.resolveName("min_voltage_v") + " must be below max_voltage_v");
  lim.slew_rate_v_per_s = r.number("slew_rate_v_per_s");
  lim.command_timeout_s = r.number("command_timeout_s");
  lim.max_step_dt_s = r.number("max_step_dt_s");
  lim.max_frame_step_v = r.number("max_frame_step_v");
  lim.max_unconfirmed_v = r.number("max_unconfirmed_v");
  if (lim.max_unconfirmed_v < lim.max_frame_step_v)
    throw std::invalid_argument("parameter " + pnh.resolveName("max_unconfirmed_v") + " must be at least max_frame_step_v");
  lim.max_stamp_ahead_s = r.number("max_stamp_ahead_s");
  lim.report_tolerance_v = r.number("report_tolerance_v");
  lim.report_lag_s = r.number("report_lag_s");
  lim.report_mismatch_count = r.integer("report_mismatch_count");
  config.encoder_timeout_s = r.number("encoder_timeout_s");
  config.silence_reconnect_s = r.number("silence_reconnect_s");
  config.reconnect_min_s = r.number("reconnect_min_s");
  config.reconnect_max_s = r.number("reconnect_max_s");
  if (config.reconnect_max_s < config.reconnect_min_s)
    throw std::invalid_argument("parameter " + pnh.resolveName("reconnect_max_s") + " must be at least reconnect_min_s");
  config.receive_poll_ms = r.integer("receive_poll_ms");
}
}  // namespace

void DriverNode::read_sync_mode(params::ParamReader& r, can::DriverConfig& config) {
  sync_mode_ = r.flag("sync_mode");
  sync_idle_s_ = r.number("sync_idle_s");
  const int max_in_flight = r.integer("sync_max_in_flight");
  if (max_in_flight > 0 && !sync_mode_)  // as mm3e_sim refuses sync_max_time_scale without sync_mode
    throw std::invalid_argument("parameter " + pnh_.resolveName("sync_max_in_flight") + " = " +
                                std::to_string(max_in_flight) + ": bounds the SYNCs in flight, so it needs sync_mode");
  sync_gate_ = can::SyncGate(max_in_flight);
  if (sync_mode_ && 1.25 * sync_idle_s_ >= config.silence_reconnect_s)
    throw std::invalid_argument("parameter " + pnh_.resolveName("sync_idle_s") + " = " + std::to_string(sync_idle_s_) +
                                " s: an idle device would be silent longer than silence_reconnect_s = " +
                                std::to_string(config.silence_reconnect_s) + " s and be reconnected over and over");
  if (!sync_mode_) return;
  // one frame per SYNC, time counted in samples: the cap per frame is the slew step of one sample
  auto& lim = config.limits;
  lim.lockstep = true;
  const double per_sample_v = lim.slew_rate_v_per_s / config.protocol.encoder_rate_hz;
  lim.max_frame_step_v = std::max(lim.max_frame_step_v, std::min(per_sample_v, 2 * can::kVoltageCeilingV));
  lim.max_unconfirmed_v = std::max(lim.max_unconfirmed_v, 2 * lim.max_frame_step_v);
  lim.max_step_dt_s = std::max(lim.max_step_dt_s, 1.0 / config.protocol.encoder_rate_hz);
  // the sample's set points go out with its SYNC: one datagram per sample instead of one per frame
  config.hold_until_sync = true;
}

can::DriverCallbacks DriverNode::core_callbacks() {
  can::DriverCallbacks cb;
  cb.on_voltage = [this](const can::VoltageReport& v, std::uint32_t seq, double t) {
    AxisVoltage msg;
    msg.header.stamp = stamp_for(v.axis, seq, t);
    msg.header.frame_id = frame_id_;
    msg.axis = can::kAxisNames[v.axis];
    msg.sequence = seq;
    msg.voltage = v.voltage_v;
    voltage_pub_[v.axis].publish(msg);
  };
  cb.on_encoder = [this](const can::EncoderReport& e, std::uint32_t seq, double t) {
    EncoderPosition msg;
    msg.header.stamp = stamp_for(e.axis, seq, t);
    msg.header.frame_id = frame_id_;
    msg.axis = can::kAxisNames[e.axis];
    msg.sequence = seq;
    msg.position = e.position_m;
    msg.valid = e.valid;
    encoder_pub_[e.axis].publish(msg);
    if (sync_mode_) {
      std::lock_guard<std::mutex> lock(sync_mutex_);
      if (sync_gate_.on_reading(e.axis)) sync_locked();
    }
  };
  cb.on_event = [](const std::string& text, bool error) {
    if (error)
      ROS_ERROR_STREAM("mm3e_driver: " << text);
    else
      ROS_INFO_STREAM("mm3e_driver: " << text);
  };
  return cb;
}

void DriverNode::advertise(const params::NodeInterface& iface) {
  for (int i = 0; i < can::kAxisCount; ++i) {
    const std::string axis = can::kAxisNames[i];
    voltage_pub_[i] = nh_.advertise<AxisVoltage>(iface.topic_name<AxisVoltage>("<axis>/voltage", axis), 20);
    encoder_pub_[i] = nh_.advertise<EncoderPosition>(iface.topic_name<EncoderPosition>("<axis>/encoder", axis), 20);
    command_sub_[i] = nh_.subscribe<VoltageCommand>(iface.topic_name<VoltageCommand>("<axis>/command", axis), 1,
                                                    [this, i](const VoltageCommand::ConstPtr& m) { on_command(i, m); },
                                                    ros::VoidConstPtr(), ros::TransportHints().tcpNoDelay());
  }
  halt_srv_ = pnh_.advertiseService(iface.service_name<std_srvs::Trigger>("~halt"), &DriverNode::on_halt, this);
  recover_srv_ = pnh_.advertiseService(iface.service_name<std_srvs::Trigger>("~recover"), &DriverNode::on_recover, this);
}

void DriverNode::add_diagnostics(const std::string& hardware_id) {
  updater_.setHardwareID(hardware_id);
  updater_.add("bus", this, &DriverNode::diagnose_bus);
  if (link_monitor_)
    updater_.add("nanocontrol", [this](diagnostic_updater::DiagnosticStatusWrapper& s) {
      const nanocontrol::LinkMonitor::Snapshot snap = link_monitor_->snapshot();
      diagnose_link(snap, last_link_counters_, s);
      last_link_counters_ = snap.counters;
    });
  for (int i = 0; i < can::kAxisCount; ++i)
    updater_.add(std::string("axis ") + can::kAxisNames[i],
                 [this, i](diagnostic_updater::DiagnosticStatusWrapper& s) { diagnose_axis(i, s); });
  last_diag_ = ros::WallTime::now();
}

void DriverNode::start_timers(double output_rate_hz, double diagnostic_period_s) {
  if (sync_mode_) {
    last_sync_wall_ = ros::WallTime::now();
    sync_idle_timer_ = nh_.createWallTimer(ros::WallDuration(sync_idle_s_ / 4), [this](const ros::WallTimerEvent&) {
      check_commanders();
      std::lock_guard<std::mutex> lock(sync_mutex_);
      if ((ros::WallTime::now() - last_sync_wall_).toSec() >= sync_idle_s_) {
        sync_gate_.idle();
        sync_locked();
      }
    });
  } else {
    tick_timer_ = nh_.createTimer(ros::Duration(1.0 / output_rate_hz), &DriverNode::on_tick, this);
  }
  diag_timer_ = nh_.createWallTimer(ros::WallDuration(diagnostic_period_s), [this](const ros::WallTimerEvent&) {
    updater_.force_update();
  });
}

DriverNode::DriverNode(ros::NodeHandle nh, ros::NodeHandle pnh) : nh_(nh), pnh_(pnh), updater_(nh, pnh) {
  const params::NodeInterface& iface = driver_interface();
  params::ParamReader r(pnh_, iface);
  can::DriverConfig config;
  config.protocol = read_protocol(r);
  read_limits(r, pnh_, config);
  const auto& lim = config.limits;
  const double output_rate_hz = r.number("output_rate_hz");
  const double diagnostic_period_s = r.number("diagnostic_period_s");
  stamp_with_receive_time_ = r.flag("stamp_with_receive_time");
  read_sync_mode(r, config);
  encoder_timeout_s_ = config.encoder_timeout_s;
  sample_period_s_ = 1.0 / config.protocol.encoder_rate_hz;
  heartbeat_period_s_ = config.protocol.heartbeat_period_s;
  const TransportParams transport = read_transport(r);
  // The real controller samples on its own clock: counting slew time in SYNCs would turn V/s into V/command.
  if (sync_mode_ && transport.kind != "udp")
    throw std::invalid_argument("parameter " + pnh_.resolveName("sync_mode") +
                                " is for the simulated device over udp only; it is refused on " + transport.kind +
                                " (the slew limit would count commands, not seconds)");
  const bool serial = transport.kind == "nanocontrol";
  const nanocontrol::LinkOptions link = read_link_options(r, lim.min_voltage_v, lim.max_voltage_v, serial);
  if (serial) {
    // the set points and reports go through the NanoControl adapter below DriverCore; its frames stay in-process
    config.protocol = nanocontrol::frame_protocol();
    sample_period_s_ = 1.0 / config.protocol.encoder_rate_hz;
    heartbeat_period_s_ = config.protocol.heartbeat_period_s;
  }
  const std::string prefix = r.text("frame_prefix");
  frame_id_ = prefix + "base";
  std::string hardware_id = r.text("hardware_id");
  if (hardware_id.empty())
    hardware_id = serial ? "nanocontrol@" + link.port
                         : "mm3e@" + transport.describe() + "/node " + hex(config.protocol.base_node_id);
  r.warn_unknown("mm3e_driver");

  const can::DriverCallbacks cb = core_callbacks();
  const can::Codec codec(config.protocol);
  if (serial) {
    link_monitor_ = std::make_shared<nanocontrol::LinkMonitor>();
    auto monitor = link_monitor_;
    core_ = std::make_unique<can::DriverCore>(
        config, [link, monitor] { return nanocontrol::make_transport(link, monitor); }, cb);
  } else {
    core_ = std::make_unique<can::DriverCore>(config, transport_factory(transport, codec.driver_filters()), cb);
  }
  advertise(iface);
  add_diagnostics(hardware_id);
  core_->start();
  start_timers(output_rate_hz, diagnostic_period_s);
  ROS_INFO_STREAM("mm3e_driver: " << hardware_id << ", limits [" << lim.min_voltage_v << ", " << lim.max_voltage_v
                                  << "] V, slew " << lim.slew_rate_v_per_s << " V/s, command timeout "
                                  << lim.command_timeout_s << " s"
                                  << (sync_mode_ ? "; synchronous mode: the controller samples on SYNC" : ""));
}

DriverNode::~DriverNode() {
  tick_timer_.stop();
  sync_idle_timer_.stop();
  diag_timer_.stop();
  if (core_) core_->stop();
}

ros::Time DriverNode::stamp_for(int axis, std::uint32_t sequence, double receive_time_s) {
  if (!ros::Time::isSimTime()) {
    if (stamp_with_receive_time_ && receive_time_s > 0) return ros::Time(receive_time_s);
    return ros::Time::now();
  }
  // Kernel receive time is wall-clock; under sim time /clock arrives in coarse steps (a simulated device that
  // does not own the clock sends samples in bursts), so ROS time at reception can be off by several samples.
  // Stamps follow the controller's sequence at the encoder period instead. They may run ahead of a coarse clock
  // for a while; they are re-anchored to ROS time when they fall behind it by more than 1.5 periods, run more
  // than 5 s ahead, or the sequence steps back (start, gaps, device restart).
  const double now = ros::Time::now().toSec();
  std::lock_guard<std::mutex> lock(anchor_mutex_);
  Anchor& a = anchors_[axis];
  const std::int32_t steps = static_cast<std::int32_t>(sequence - a.sequence);
  const double expected = a.stamp_s + steps * sample_period_s_;
  if (!a.set || steps < 0 || expected < now - 1.5 * sample_period_s_ || expected > now + 5.0) {
    a = Anchor{true, sequence, now};
    return ros::Time(now);
  }
  return ros::Time(expected);
}

void DriverNode::check_commanders() {
  for (int i = 0; i < can::kAxisCount; ++i) {
    const bool many = command_sub_[i].getNumPublishers() > 1;
    if (many != multiple_commanders_[i]) {
      multiple_commanders_[i] = many;
      core_->set_multiple_commanders(i, many);
      if (many)
        ROS_ERROR_STREAM("mm3e_driver: " << command_sub_[i].getNumPublishers() << " publishers on "
                                         << command_sub_[i].getTopic()
                                         << ": holding axis " << can::kAxisNames[i] << " until one remains");
      else
        ROS_WARN_STREAM("mm3e_driver: one commander again on " << command_sub_[i].getTopic());
    }
  }
}

void DriverNode::on_command(int axis, const VoltageCommand::ConstPtr& msg) {
  check_commanders();
  can::CommandOutcome out;
  if (sync_mode_) {
    std::lock_guard<std::mutex> lock(sync_mutex_);
    out = core_->command(axis, msg->voltage, bus_time_s_, bus_time_s_);
    std::array<bool, can::kAxisCount> has_commander{};
    for (int i = 0; i < can::kAxisCount; ++i) has_commander[i] = command_sub_[i].getNumPublishers() > 0;
    if (sync_gate_.on_command(axis, has_commander)) sync_locked();
  } else {
    const double now = ros::Time::now().toSec();
    const double stamp = msg->header.stamp.isZero() ? std::nan("") : msg->header.stamp.toSec();
    out = core_->command(axis, msg->voltage, now, stamp);
  }
  switch (out) {
    case can::CommandOutcome::kRejectedNonFinite:
      ROS_WARN_STREAM_THROTTLE(1.0, "mm3e_driver: axis " << can::kAxisNames[axis] << ": rejected non-finite command "
                                                         << msg->voltage << "; holding");
      break;
    case can::CommandOutcome::kClamped:
      ROS_WARN_STREAM_THROTTLE(1.0, "mm3e_driver: axis " << can::kAxisNames[axis] << ": command " << msg->voltage
                                                         << " V clamped to the limits");
      break;
    case can::CommandOutcome::kRejectedHeld:
    case can::CommandOutcome::kRejectedNoBaseline:
    case can::CommandOutcome::kRejectedFutureStamp:
      ROS_WARN_STREAM_THROTTLE(2.0, "mm3e_driver: axis " << can::kAxisNames[axis] << ": command "
                                                         << can::to_string(out));
      break;
    case can::CommandOutcome::kAccepted: break;
  }
}

void DriverNode::on_tick(const ros::TimerEvent&) {
  check_commanders();
  core_->tick(ros::Time::now().toSec());
}

void DriverNode::sync_locked() {
  // ramps of axes without a command this sample, and the watchdog, move on by one period first
  core_->tick(bus_time_s_);
  const bool sent = core_->sync();
  if (sent)
    bus_time_s_ += sample_period_s_;
  else
    ROS_WARN_STREAM_THROTTLE(2.0, "mm3e_driver: SYNC not sent (bus down); the controller is not sampling");
  sync_gate_.synced(sent);
  last_sync_wall_ = ros::WallTime::now();
}

bool DriverNode::on_halt(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  core_->halt();
  res.success = true;
  res.message = "halted: every axis holds its applied voltage; commands refused until ~recover";
  ROS_WARN_STREAM("mm3e_driver: " << res.message);
  return true;
}

bool DriverNode::on_recover(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  core_->recover();
  res.success = true;
  res.message = "recovering: halt and device faults cleared, transport reopening (state in diagnostics)";
  ROS_INFO_STREAM("mm3e_driver: " << res.message);
  return true;
}

void DriverNode::diagnose_bus(diagnostic_updater::DiagnosticStatusWrapper& stat) {
  const can::BusStatus b = core_->bus_status();
  using diagnostic_msgs::DiagnosticStatus;
  switch (b.state) {
    case can::BusState::kActive:
      stat.summary(DiagnosticStatus::OK, "active");
      break;
    case can::BusState::kConnected:
      stat.summary(DiagnosticStatus::WARN, "connected, no frame from the device yet");
      break;
    case can::BusState::kErrorPassive:
      stat.summary(DiagnosticStatus::WARN, "error passive: " + b.last_error);
      break;
    case can::BusState::kBusOff:
      stat.summary(DiagnosticStatus::ERROR, "bus-off: " + b.last_error);
      break;
    case can::BusState::kDisconnected:
      stat.summary(DiagnosticStatus::ERROR, "disconnected: " + b.last_error);
      break;
  }
  if (b.heartbeat_seen && b.device_state != can::DeviceState::kOperational && b.state == can::BusState::kActive)
    stat.mergeSummary(DiagnosticStatus::WARN, std::string("device ") + can::to_string(b.device_state));
  // in synchronous mode the heartbeat period is simulated time: an idle device sends one every 11 SYNCs or so
  if (b.state == can::BusState::kActive && !sync_mode_ &&
      (!b.heartbeat_seen || b.heartbeat_age_s > 3.0 * heartbeat_period_s_))
    stat.mergeSummary(DiagnosticStatus::WARN, "no heartbeat from the controller");
  stat.add("state", can::to_string(b.state));
  stat.add("transport", b.transport);
  stat.add("last error", b.last_error);
  stat.add("last error frame", b.last_error_frame);
  stat.add("error frames", b.error_frames);
  stat.add("bus-off events", b.bus_off_events);
  stat.add("malformed frames", b.malformed_frames);
  stat.add("unknown frames", b.unknown_frames);
  stat.add("send failures", b.send_failures);
  stat.add("connects", b.connects);
  stat.add("connect failures", b.connect_failures);
  if (sync_mode_) stat.add("SYNC frames sent", b.syncs_sent);
  stat.add("next reconnect in [s]", b.next_reconnect_in_s);
  stat.add("device state", b.heartbeat_seen ? can::to_string(b.device_state) : "no heartbeat");
  stat.add("device fault flags", hex(b.device_fault_flags));
  stat.add("heartbeat age [s]", b.heartbeat_age_s);
}

void DriverNode::diagnose_axis(int i, diagnostic_updater::DiagnosticStatusWrapper& stat) {
  const can::AxisStatus s = core_->axis_status(i);
  const ros::WallTime now = ros::WallTime::now();
  const double dt = std::max(1e-3, (now - last_diag_).toSec());
  // Rates are per wall second since the previous update of this axis.
  const double enc_hz = (s.encoder_frames - last_encoder_frames_[i]) / dt;
  const double volt_hz = (s.voltage_frames - last_voltage_frames_[i]) / dt;
  const double sent_hz = (s.frames_sent - last_sent_[i]) / dt;
  last_encoder_frames_[i] = s.encoder_frames;
  last_voltage_frames_[i] = s.voltage_frames;
  last_sent_[i] = s.frames_sent;
  if (i == can::kAxisCount - 1) last_diag_ = now;
  using diagnostic_msgs::DiagnosticStatus;
  stat.summary(DiagnosticStatus::OK, "ok");
  if (s.encoder_age_s < 0)
    stat.mergeSummary(DiagnosticStatus::WARN, "no encoder frame yet");
  else if (s.encoder_age_s > (sync_mode_ ? std::max(encoder_timeout_s_, 2.0 * sync_idle_s_) : encoder_timeout_s_))
    stat.mergeSummary(DiagnosticStatus::ERROR, "encoder silent");
  if (!s.encoder_valid) stat.mergeSummary(DiagnosticStatus::ERROR, "encoder reading flagged invalid");
  if (s.amplifier_fault) stat.mergeSummary(DiagnosticStatus::ERROR, "amplifier fault");
  if (s.device_fault) stat.mergeSummary(DiagnosticStatus::ERROR, s.fault);
  if (s.paused && !s.device_fault) stat.mergeSummary(DiagnosticStatus::WARN, "report did not match: ramp paused");
  if (s.multiple_commanders) stat.mergeSummary(DiagnosticStatus::ERROR, "more than one commander: holding");
  if (s.halted) stat.mergeSummary(DiagnosticStatus::WARN, "halted");
  if (s.timed_out) stat.mergeSummary(DiagnosticStatus::WARN, "command timeout: holding");
  stat.add("encoder rate [Hz]", enc_hz);
  stat.add("voltage report rate [Hz]", volt_hz);
  stat.add("command frame rate [Hz]", sent_hz);
  stat.add("encoder frames", s.encoder_frames);
  stat.add("encoder dropped", s.encoder_dropped);
  stat.add("encoder out of order", s.encoder_out_of_order);
  stat.add("voltage dropped", s.voltage_dropped);
  stat.add("voltage out of order", s.voltage_out_of_order);
  stat.add("encoder age [s]", s.encoder_age_s);
  stat.add("applied voltage [V]", s.applied_v);
  stat.add("target voltage [V]", s.target_v);
  stat.add("reported voltage [V]", s.reported_v);
  stat.add("position [m]", s.position_m);
  stat.add("commands", s.commands);
  stat.add("clamped", s.clamped);
  stat.add("rejected non-finite", s.rejected_non_finite);
  stat.add("rejected held", s.rejected_held);
  stat.add("rejected no baseline", s.rejected_no_baseline);
  stat.add("rejected no link", s.rejected_no_link);
  stat.add("rejected future stamp", s.rejected_future_stamp);
  stat.add("frames refused by the transport", s.frames_refused);
  stat.add("report mismatches", s.report_mismatches);
  stat.add("device faults", s.device_faults);
  stat.add("device fault", s.fault);
  stat.add("timeouts", s.timeouts);
  stat.add("timed out", s.timed_out);
  stat.add("halted", s.halted);
  stat.add("multiple commanders", s.multiple_commanders);
}

}  // namespace piezo::mm3e
