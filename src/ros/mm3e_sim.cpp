#include "piezo_compensation/ros/mm3e_sim.h"

#include <linux/can/error.h>
#include <rosgraph_msgs/Clock.h>
#include <sensor_msgs/Temperature.h>

#include <chrono>
#include <cmath>
#include <sstream>

#include <yaml-cpp/yaml.h>

#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/can/lockstep.h"
#include "piezo_compensation/ros/interfaces.h"
#include "piezo_compensation/ros/mm3e_params.h"
#include "piezo_compensation/ros/mm3e_sim_nanocontrol.h"
#include "piezo_compensation/ros/nanocontrol_params.h"
#include "piezo_compensation/sim/simulator_config.h"

namespace piezo::mm3e {

namespace {
double wall_now_s() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

// ~simulator_config: a simulator YAML (config/simulator.yaml shape) or a stage file (config/stages/*.yaml), whose
// `simulator:` block is the device's physics (the foreign stages of the hold-trim tests and demo).
sim::SimulatorConfig load_device_physics(const std::string& path) {
  YAML::Node root;
  try {
    root = YAML::LoadFile(path);
  } catch (const YAML::Exception& e) {
    throw std::invalid_argument(path + ": cannot read simulator config: " + e.what());
  }
  if (root.IsMap() && root["simulator"] && root["protocol"])
    return sim::simulator_config_from_yaml(root["simulator"], path + ": simulator");
  return sim::load_simulator_config(path);
}
}  // namespace

const params::NodeInterface& sim_interface() {
  using namespace params;
  static const NodeInterface t = [] {
    NodeInterface n;
    n.node = "mm3e_sim";
    n.summary = "the simulated MM3E controller on the same CAN protocol, or a simulated NanoControl on a "
                "pseudo-terminal; optional owner of /clock (CAN only)";
    n.params = transport_params(47101, 47100);
    const std::vector<ParamDef> rest = {
        text("frame_prefix", "", "header frame_id of true_position is <prefix>base"),
        number("min_voltage_v", "V", -80.0, -1000.0, 1000.0, "the amplifier's lower limit: set points below are clamped")
            .rule("< max_voltage_v"),
        number("max_voltage_v", "V", 80.0, -1000.0, 1000.0, "the amplifier's upper limit"),
        number("initial_voltage_v", "V", 0.0, -1000.0, 1000.0, "voltage on every axis at power-up")
            .rule("within [min_voltage_v, max_voltage_v]"),
        number("time_scale", "", 1.0, 0.01, 1000.0, "simulated seconds per wall second").rule("≠ 1 needs publish_clock"),
        flag("publish_clock", false, "publish /clock: the device owns simulated time (needs /use_sim_time)"),
        flag("sync_mode", false,
             "sample on the driver's SYNC frame instead of the clock: simulated time moves one encoder period per "
             "SYNC (needs publish_clock)"),
        number("sync_max_time_scale", "", 0.0, 0.0, 1000.0,
               "sync_mode: at most this many simulated seconds per wall second (0: no ceiling)")
            .rule("> 0 needs sync_mode"),
        number("clock_rate_hz", "Hz", 200.0, 1.0, 5000.0, "/clock publishing rate (wall) when publish_clock"),
        number("fault_silence_s", "s", 1.0, 0.0, 600.0, "after ~inject_bus_off the device sends nothing for this long (wall)"),
        integer("seed", "", 1, 0, 2147483647, "simulator random seed (deterministic noise)"),
        text("simulator_config", "",
             "the device's physics: a simulator YAML (config/simulator.yaml shape) or a stage file "
             "(config/stages/*.yaml: its simulator: block); \"\" = built-in defaults"),
        texts("effects", {}, {}, 0, 16,
              "extra simulator effects to enable: thermal_drift, cross_axis, encoder_periodic, rate_dependent, "
              "periodic_disturbance, ..."),
    };
    n.params.insert(n.params.end(), rest.begin(), rest.end());
    const auto serial = nanocontrol_sim_params();
    n.params.insert(n.params.end(), serial.begin(), serial.end());
    const auto protocol = protocol_params();
    n.params.insert(n.params.end(), protocol.begin(), protocol.end());
    using D = TopicDef::Direction;
    n.topics = {
        {"<axis>/true_position", "piezo_compensation/EncoderPosition", D::kPublishes,
         "noise-free position [m] of each sample, for evaluation"},
        {"temperature", "sensor_msgs/Temperature", D::kPublishes,
         "the simulated sensor's temperature [°C] (the thermal_drift effect; ambient while it is off)"},
        {"/clock", "rosgraph_msgs/Clock", D::kPublishes, "simulated time, with publish_clock"},
        {"<axis>/device_set_point", "piezo_compensation/AxisVoltage", D::kPublishes,
         "nanocontrol: every set point the simulated controller took [V], as it took it"},
    };
    n.services = {
        {"~inject_bus_off", "std_srvs/Trigger", "the device goes silent for fault_silence_s (a bus-off)"},
        {"~inject_garbage", "std_srvs/Trigger", "send malformed frames"},
        {"~inject_restart", "std_srvs/Trigger", "restart the controller (sequence numbers restart)"},
        {"~inject_stuck_amplifier", "std_srvs/SetBool", "the amplifier ignores set points (true) or follows again"},
        {"~set_thermal_drift", "std_srvs/SetBool", "switch the thermal_drift effect on or off mid-run"},
        {"~inject_closed_port", "std_srvs/SetBool", "the device's UDP port refuses frames (true) or takes them again"},
        {"~inject_error_reply", "std_srvs/Trigger", "nanocontrol: the next set point is refused with an e reply"},
        {"~inject_breakdown", "std_srvs/Trigger", "nanocontrol: the next command is answered i (piezo voltage breakdown)"},
        {"~inject_lost_reply", "std_srvs/Trigger", "nanocontrol: the next command is carried out and never answered"},
        {"~inject_garbled_reply", "std_srvs/Trigger", "nanocontrol: the next command is answered with bytes that are no reply"},
        {"~inject_partial_reply", "std_srvs/Trigger", "nanocontrol: the next command is answered with half a line, no CR"},
        {"~inject_port_lost", "std_srvs/SetBool",
         "nanocontrol: the pseudo-terminal vanishes (true: the driver sees EIO, ~port is removed) or comes back"},
    };
    return n;
  }();
  return t;
}

SimNode::SimNode(ros::NodeHandle nh, ros::NodeHandle pnh) : nh_(nh), pnh_(pnh) {
  const params::NodeInterface& iface = sim_interface();
  params::ParamReader r(pnh_, iface);
  can::DeviceConfig config;
  config.protocol = read_protocol(r);
  config.min_voltage_v = r.number("min_voltage_v");
  config.max_voltage_v = r.number("max_voltage_v");
  if (config.min_voltage_v >= config.max_voltage_v)
    throw std::invalid_argument("parameter " + pnh_.resolveName("min_voltage_v") + " must be below max_voltage_v");
  const double initial = r.number("initial_voltage_v");
  if (initial < config.min_voltage_v || initial > config.max_voltage_v)
    throw std::invalid_argument("parameter " + pnh_.resolveName("initial_voltage_v") +
                                " must be within [min_voltage_v, max_voltage_v]");
  config.initial_voltage_v = {initial, initial, initial};
  time_scale_ = r.number("time_scale");
  publish_clock_ = r.flag("publish_clock");
  if (time_scale_ != 1.0 && !publish_clock_)
    throw std::invalid_argument("parameter " + pnh_.resolveName("time_scale") +
                                " != 1 needs ~publish_clock: true (the device owns simulated time)");
  if (publish_clock_ && !ros::Time::isSimTime())
    throw std::invalid_argument("parameter " + pnh_.resolveName("publish_clock") +
                                " is true but /use_sim_time is not set: set it before the nodes start");
  sync_mode_ = r.flag("sync_mode");
  if (sync_mode_ && !publish_clock_)
    throw std::invalid_argument("parameter " + pnh_.resolveName("sync_mode") +
                                " needs ~publish_clock: true (simulated time advances one period per SYNC)");
  sync_max_time_scale_ = r.number("sync_max_time_scale");
  if (sync_max_time_scale_ > 0.0 && !sync_mode_)
    throw std::invalid_argument("parameter " + pnh_.resolveName("sync_max_time_scale") +
                                " only applies with ~sync_mode: true (without it ~time_scale sets the pace)");
  clock_rate_hz_ = r.number("clock_rate_hz");
  fault_silence_s_ = r.number("fault_silence_s");
  const int seed = r.integer("seed");
  const std::string sim_config_path = r.text("simulator_config");
  frame_id_ = r.text("frame_prefix") + "base";
  const TransportParams transport = read_transport(r);
  const std::string link_path = r.text("port");
  const nanocontrol::SimDeviceConfig serial_device = read_sim_device(r, initial);
  const double reply_delay_s = r.number("reply_delay_s");
  const bool serial = transport.kind == "nanocontrol";
  if (serial && publish_clock_)  // the NanoControl answers in real time; nothing there counts samples
    throw std::invalid_argument("parameter " + pnh_.resolveName("publish_clock") +
                                " is for the CAN device; the simulated NanoControl runs in real time");

  sim::SimulatorConfig sim_config = sim_config_path.empty() ? sim::default_simulator_config()
                                                            : load_device_physics(sim_config_path);
  for (const std::string& effect : r.texts("effects")) {
    try {
      sim::enable_effect(sim_config, effect);
    } catch (const std::invalid_argument& e) {
      throw std::invalid_argument("parameter " + pnh_.resolveName("effects") + ": " + e.what());
    }
  }
  r.warn_unknown("mm3e_sim");
  simulator_ = std::make_unique<sim::ManipulatorSimulator>(sim_config, static_cast<std::uint64_t>(seed));
  if (serial) {
    NanoControlSim::Options o{link_path, serial_device, reply_delay_s, frame_id_};
    nano_ = std::make_unique<NanoControlSim>(nh_, pnh_, iface, o, *simulator_, mutex_);
    thermal_srv_ = pnh_.advertiseService(iface.service_name<std_srvs::SetBool>("~set_thermal_drift"), &SimNode::on_thermal, this);
    ROS_INFO_STREAM("mm3e_sim: simulated NanoControl on " << nano_->describe() << ", reply after " << reply_delay_s
                                                          << " s");
    return;
  }
  sim::ManipulatorSimulator* s = simulator_.get();
  device_ = std::make_unique<can::DeviceCore>(
      config, [s](const std::array<double, 3>& v, double dt) { return s->step(v, dt); });
  transport_ = transport_factory(transport, device_->codec().device_filters())();
  transport_name_ = transport_->describe();
  transport_->open();  // the device is a test fixture: a missing interface is a start-up error here

  for (int i = 0; i < can::kAxisCount; ++i)
    truth_pub_[i] = nh_.advertise<piezo_compensation::EncoderPosition>(
        iface.topic_name<piezo_compensation::EncoderPosition>("<axis>/true_position", can::kAxisNames[i]), 20);
  // aux signals of the simulated effects, on the topics the predictor's ~aux_topics map (sensor_msgs/Temperature).
  // Always published: the thermal drift can be switched on mid-run (~set_thermal_drift); while it is off the
  // sensor reads the ambient temperature.
  temperature_pub_ = nh_.advertise<sensor_msgs::Temperature>(iface.topic_name<sensor_msgs::Temperature>("temperature"), 20);
  if (publish_clock_) clock_pub_ = nh_.advertise<rosgraph_msgs::Clock>(iface.topic_name<rosgraph_msgs::Clock>("/clock"), 10);
  bus_off_srv_ = pnh_.advertiseService(iface.service_name<std_srvs::Trigger>("~inject_bus_off"), &SimNode::on_bus_off, this);
  garbage_srv_ = pnh_.advertiseService(iface.service_name<std_srvs::Trigger>("~inject_garbage"), &SimNode::on_garbage, this);
  restart_srv_ = pnh_.advertiseService(iface.service_name<std_srvs::Trigger>("~inject_restart"), &SimNode::on_restart, this);
  stuck_srv_ = pnh_.advertiseService(iface.service_name<std_srvs::SetBool>("~inject_stuck_amplifier"), &SimNode::on_stuck, this);
  thermal_srv_ = pnh_.advertiseService(iface.service_name<std_srvs::SetBool>("~set_thermal_drift"), &SimNode::on_thermal, this);
  closed_port_srv_ = pnh_.advertiseService(iface.service_name<std_srvs::SetBool>("~inject_closed_port"), &SimNode::on_closed_port, this);
  ROS_INFO_STREAM("mm3e_sim: controller on " << transport_name_ << ", encoder " << config.protocol.encoder_rate_hz
                                             << " Hz, "
                                             << (sync_mode_ ? std::string("synchronous: one sample per SYNC")
                                                            : "time scale " + std::to_string(time_scale_))
                                             << (publish_clock_ ? ", publishing /clock" : ""));
  thread_ = std::thread([this] { run(); });
}

SimNode::~SimNode() {
  running_ = false;
  if (thread_.joinable()) thread_.join();
  nano_.reset();
}

void SimNode::send_all(const std::vector<can_frame>& frames) {
  if (frames.empty() || wall_now_s() < silent_until_wall_s_ || !transport_->is_open()) return;
  // One sample's reports together (UDP: one datagram, not 6-7; SocketCAN: frame by frame). A refused frame is
  // dropped, as by a controller whose transmit queue is full, and the rest go on: after a refused datagram its
  // first frame counts as the dropped one and the others are sent again.
  std::size_t done = 0;
  while (done < frames.size()) {
    try {
      const std::size_t n = transport_->send_batch(frames.data() + done, frames.size() - done);
      done += n == frames.size() - done ? n : n + 1;  // skip the refused frame (or datagram's first), go on
    } catch (const can::TransportError& e) {
      ROS_ERROR_STREAM_THROTTLE(1.0, "mm3e_sim: " << e.what());
      ++done;
    }
  }
}

void SimNode::step_once(double t_s) {
  // The clock owner ticks exactly at each sample, so receivers stamping with ROS time get sample times.
  if (publish_clock_) publish_clock(t_s);
  const can::DeviceCore::Output out = device_->step();
  send_all(out.frames);
  for (int i = 0; i < can::kAxisCount; ++i) {
    piezo_compensation::EncoderPosition msg;
    msg.header.stamp = ros::Time(t_s);
    msg.header.frame_id = frame_id_;
    msg.axis = can::kAxisNames[i];
    msg.sequence = sequence_;
    msg.position = out.sample.axes[i].true_position_nm * 1e-9;
    msg.valid = true;
    truth_pub_[i].publish(msg);
  }
  {
    sensor_msgs::Temperature t;
    t.header.stamp = ros::Time(t_s);
    t.header.frame_id = frame_id_;
    t.temperature = out.sample.temperature_c;
    t.variance = 0.0;
    temperature_pub_.publish(t);
  }
  ++sequence_;
}

void SimNode::publish_clock(double t_s) {
  rosgraph_msgs::Clock clock;
  clock.clock = ros::Time(t_s);
  clock_pub_.publish(clock);
}

void SimNode::run() {
  if (sync_mode_) {
    run_synchronous();
    return;
  }
  const double period_s = device_->period_s();
  // Under another node's /clock, ROS time is 0 until the first clock message: wait for it rather than
  // "catching up" from 0.
  while (running_ && ros::ok() && !publish_clock_ && ros::Time::now().isZero())
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  const auto wall_start = std::chrono::steady_clock::now();
  // Simulated time starts at the wall clock's epoch time so stamps look like real ones.
  const double sim_start_s = publish_clock_ ? ros::WallTime::now().toSec() : ros::Time::now().toSec();
  double next_sample_s = sim_start_s + period_s;
  std::vector<can::ReceivedFrame> in;
  while (running_ && ros::ok()) {
    double sim_now_s;
    if (publish_clock_) {
      const double wall_elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - wall_start).count();
      sim_now_s = sim_start_s + time_scale_ * wall_elapsed;
    } else {
      sim_now_s = ros::Time::now().toSec();
    }
    // A clock that jumps (restarted clock owner, bag loop) resynchronises instead of replaying the gap.
    if (sim_now_s < next_sample_s - 2 * period_s || sim_now_s > next_sample_s + 5.0) next_sample_s = sim_now_s + period_s;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      while (next_sample_s <= sim_now_s) {
        step_once(next_sample_s);
        next_sample_s += period_s;
      }
    }
    if (publish_clock_) publish_clock(sim_now_s);
    // Wait for commands until the next clock tick or sample, whichever is first (in wall time). Under someone
    // else's /clock the simulated-time gap says nothing about wall time: poll at the clock rate.
    double wait_s;
    if (publish_clock_)
      wait_s = std::min(1.0 / clock_rate_hz_, (next_sample_s - sim_now_s) / time_scale_);
    else if (ros::Time::isSimTime())
      wait_s = 1.0 / clock_rate_hz_;
    else
      wait_s = next_sample_s - sim_now_s;
    wait_s = std::clamp(wait_s, 0.0002, 0.05);
    in.clear();
    if (!port_open()) {
      std::this_thread::sleep_for(std::chrono::duration<double>(wait_s));
      continue;
    }
    try {
      transport_->receive(in, static_cast<int>(std::ceil(wait_s * 1000.0)));
    } catch (const can::TransportError& e) {
      ROS_ERROR_STREAM_THROTTLE(1.0, "mm3e_sim: " << e.what());
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& rf : in) device_->handle(rf.frame);
  }
}

void SimNode::run_synchronous() {
  // Simulated time moves only on the driver's SYNC: one period, one sample, as fast as the host asks. Frames
  // are handled in bus order, so the set points written before a SYNC are in that sample.
  const double period_s = device_->period_s();
  double sim_now_s = ros::WallTime::now().toSec();
  can::SyncPace pace(sync_max_time_scale_, sim_now_s, wall_now_s());
  std::vector<can::ReceivedFrame> in;
  while (running_ && ros::ok()) {
    in.clear();
    if (!port_open()) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      continue;
    }
    try {
      transport_->receive(in, 50);
    } catch (const can::TransportError& e) {
      ROS_ERROR_STREAM_THROTTLE(1.0, "mm3e_sim: " << e.what());
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    std::unique_lock<std::mutex> lock(mutex_);
    if (in.empty()) publish_clock(sim_now_s);  // for nodes that start while nobody asks for samples
    for (const auto& rf : in)
      if (device_->handle(rf.frame) == can::DeviceCore::Handled::kSync) {
        sim_now_s += period_s;
        step_once(sim_now_s);
      }
    lock.unlock();
    const double wait_s = pace.delay_s(sim_now_s, wall_now_s());
    if (wait_s > 0.0) std::this_thread::sleep_for(std::chrono::duration<double>(wait_s));
  }
}

bool SimNode::on_bus_off(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  std::lock_guard<std::mutex> lock(mutex_);
  can::BusError e;
  e.error_class = CAN_ERR_BUSOFF;
  try {
    transport_->send(can::Codec::encode(e));
  } catch (const can::TransportError& err) {
    res.success = false;
    res.message = err.what();
    return true;
  }
  silent_until_wall_s_ = wall_now_s() + fault_silence_s_;
  res.success = true;
  res.message = "bus-off error frame sent; silent for " + std::to_string(fault_silence_s_) + " s";
  ROS_WARN_STREAM("mm3e_sim: " << res.message);
  return true;
}

bool SimNode::on_restart(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  std::lock_guard<std::mutex> lock(mutex_);
  device_->restart();
  res.success = true;
  res.message = "controller restarted: every axis at its power-up voltage, report counter from 0, boot state for " +
                std::to_string(can::DeviceCore::kBootSamples) + " samples";
  ROS_WARN_STREAM("mm3e_sim: " << res.message);
  return true;
}

bool SimNode::on_stuck(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res) {
  std::lock_guard<std::mutex> lock(mutex_);
  for (int i = 0; i < can::kAxisCount; ++i) device_->set_stuck(i, req.data);
  res.success = true;
  res.message = req.data ? "amplifiers stuck: every axis keeps its present output and ignores set points"
                         : "amplifiers released";
  ROS_WARN_STREAM("mm3e_sim: " << res.message);
  return true;
}

// Test hook: the controller stops listening (socket closed, so the driver's sends are refused by the kernel)
// and stops reporting, until called with false. Physics and the sequence counter run on meanwhile.
bool SimNode::on_closed_port(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res) {
  port_closed_ = req.data;
  res.success = true;
  res.message = req.data ? "controller socket closed: frames to it are refused" : "controller socket reopened";
  ROS_WARN_STREAM("mm3e_sim: " << res.message);
  return true;
}

bool SimNode::port_open() {
  std::lock_guard<std::mutex> lock(mutex_);
  try {
    if (port_closed_ && transport_->is_open()) transport_->close();
    if (!port_closed_ && !transport_->is_open()) transport_->open();
  } catch (const can::TransportError& e) {
    ROS_ERROR_STREAM_THROTTLE(1.0, "mm3e_sim: cannot reopen: " << e.what());
  }
  return transport_->is_open();
}

bool SimNode::on_thermal(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res) {
  std::lock_guard<std::mutex> lock(mutex_);
  simulator_->set_thermal_drift(req.data);
  const auto& t = simulator_->config().thermal_drift;
  std::ostringstream os;
  if (req.data)
    os << "thermal drift on: " << t.gain_nm_per_c << " nm/°C through a " << t.lag_s << " s lag, temperature "
       << t.ambient_c << " ± " << t.amplitude_c << " °C over " << t.period_s << " s";
  else
    os << "thermal drift off";
  res.success = true;
  res.message = os.str();
  ROS_WARN_STREAM("mm3e_sim: " << res.message);
  return true;
}

bool SimNode::on_garbage(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  std::lock_guard<std::mutex> lock(mutex_);
  const can::Codec& codec = device_->codec();
  std::vector<can_frame> frames;
  for (int i = 0; i < can::kAxisCount; ++i) {
    can_frame bad_len = codec.encode(can::EncoderReport{i, 1e-6, 0, true});
    bad_len.can_dlc = 3;
    can_frame bad_flags = codec.encode(can::VoltageReport{i, 70.0, 0, false});
    bad_flags.data[7] = 0xF0;
    can_frame rtr = codec.encode(can::EncoderReport{i, 0.0, 0, true});
    rtr.can_id |= CAN_RTR_FLAG;
    frames.insert(frames.end(), {bad_len, bad_flags, rtr});
  }
  can_frame hb = codec.encode(can::Heartbeat{});
  hb.data[0] = 0xEE;
  frames.push_back(hb);
  int sent = 0;
  for (const auto& f : frames) {
    try {
      sent += transport_->send(f) ? 1 : 0;
    } catch (const can::TransportError&) {
    }
  }
  res.success = sent == static_cast<int>(frames.size());
  res.message = std::to_string(sent) + " malformed frames sent";
  return true;
}

}  // namespace piezo::mm3e
