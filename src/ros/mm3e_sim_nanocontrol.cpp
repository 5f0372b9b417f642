#include "piezo_compensation/ros/mm3e_sim_nanocontrol.h"

#include <poll.h>
#include <sensor_msgs/Temperature.h>
#include <unistd.h>

#include <chrono>

#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/EncoderPosition.h"

namespace piezo::mm3e {

namespace {
double nc_sim_mono_s() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}
}  // namespace

NanoControlSim::NanoControlSim(ros::NodeHandle nh, ros::NodeHandle pnh, const params::NodeInterface& iface,
                               const Options& options, sim::ManipulatorSimulator& simulator, std::mutex& mutex)
    : nh_(nh), pnh_(pnh), options_(options), mutex_(mutex) {
  try {
    pty_ = std::make_unique<nanocontrol::PseudoTerminal>(options_.link_path);
  } catch (const std::runtime_error& e) {
    throw std::invalid_argument("parameter " + pnh_.resolveName("port") + ": " + e.what());
  }
  sim::ManipulatorSimulator* s = &simulator;
  device_ = std::make_unique<nanocontrol::SimDevice>(
      options_.device, [s](const std::array<double, 3>& v, double dt) { return s->step(v, dt); });
  using piezo_compensation::AxisVoltage;
  using piezo_compensation::EncoderPosition;
  for (int i = 0; i < 3; ++i) {
    const std::string axis(1, static_cast<char>('a' + i));
    truth_pub_[i] = nh_.advertise<EncoderPosition>(iface.topic_name<EncoderPosition>("<axis>/true_position", axis), 50);
    set_point_pub_[i] = nh_.advertise<AxisVoltage>(iface.topic_name<AxisVoltage>("<axis>/device_set_point", axis), 50);
  }
  temperature_pub_ = nh_.advertise<sensor_msgs::Temperature>(iface.topic_name<sensor_msgs::Temperature>("temperature"), 20);
  using nanocontrol::SimFault;
  const auto trigger = [&](const char* name, SimFault f) {
    return pnh_.advertiseService<std_srvs::Trigger::Request, std_srvs::Trigger::Response>(
        iface.service_name<std_srvs::Trigger>(name),
        [this, f](std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) { return inject(f, res); });
  };
  error_srv_ = trigger("~inject_error_reply", SimFault::kErrorReply);
  breakdown_srv_ = trigger("~inject_breakdown", SimFault::kBreakdown);
  lost_srv_ = trigger("~inject_lost_reply", SimFault::kLostReply);
  garbled_srv_ = trigger("~inject_garbled_reply", SimFault::kGarbled);
  partial_srv_ = trigger("~inject_partial_reply", SimFault::kPartial);
  port_srv_ = pnh_.advertiseService(iface.service_name<std_srvs::SetBool>("~inject_port_lost"),
                                    &NanoControlSim::on_port_lost, this);
  thread_ = std::thread([this] { run(); });
}

NanoControlSim::~NanoControlSim() {
  running_ = false;
  if (thread_.joinable()) thread_.join();
}

std::string NanoControlSim::describe() const {
  return "nanocontrol pseudo-terminal " + options_.link_path + " -> " + pty_->slave_path();
}

void NanoControlSim::publish_sample(const nanocontrol::SimDevice::Answer& a) {
  const ros::Time stamp = ros::Time::now();
  for (int i = 0; i < 3; ++i) {
    piezo_compensation::EncoderPosition msg;
    msg.header.stamp = stamp;
    msg.header.frame_id = options_.frame_id;
    msg.axis = std::string(1, static_cast<char>('a' + i));
    msg.sequence = samples_;
    msg.position = a.sample_truth_nm[i] * 1e-9;
    msg.valid = true;
    truth_pub_[i].publish(msg);
  }
  sensor_msgs::Temperature t;
  t.header.stamp = stamp;
  t.header.frame_id = options_.frame_id;
  t.temperature = device_->last_sample() ? device_->last_sample()->temperature_c : 0.0;
  temperature_pub_.publish(t);
  ++samples_;
}

void NanoControlSim::run() {
  while (running_ && ros::ok()) {
    int fd;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      fd = pty_->present() ? pty_->master_fd() : -1;
    }
    if (fd < 0) {
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
      continue;
    }
    pollfd p{fd, POLLIN, 0};
    if (poll(&p, 1, 20) <= 0 || !(p.revents & POLLIN)) continue;
    serve(fd);
  }
}

void NanoControlSim::serve(int fd) {
  char buf[512];
  std::unique_lock<std::mutex> lock(mutex_);
  if (!pty_->present() || pty_->master_fd() != fd) return;  // vanished meanwhile
  const ssize_t n = ::read(fd, buf, sizeof buf);
  if (n <= 0) return;
  lines_.append(buf, static_cast<std::size_t>(n));
  while (auto line = lines_.next_line()) {
    // the controller's turnaround, outside the lock so a fault service is not kept waiting
    lock.unlock();
    std::this_thread::sleep_for(std::chrono::duration<double>(options_.reply_delay_s));
    lock.lock();
    if (!pty_->present() || pty_->master_fd() != fd) return;
    const nanocontrol::SimDevice::Answer a = device_->handle(*line, nc_sim_mono_s());
    if (a.sample_closed) publish_sample(a);
    if (a.set_point && a.axis >= 0) {
      piezo_compensation::AxisVoltage msg;
      msg.header.stamp = ros::Time::now();
      msg.header.frame_id = options_.frame_id;
      msg.axis = std::string(1, static_cast<char>('a' + a.axis));
      msg.sequence = set_points_[a.axis]++;
      msg.voltage = a.voltage_v;
      set_point_pub_[a.axis].publish(msg);
    }
    if (!a.bytes.empty() && ::write(fd, a.bytes.data(), a.bytes.size()) < 0)
      ROS_ERROR_STREAM_THROTTLE(1.0, "mm3e_sim: cannot write the reply on " << pty_->slave_path());
  }
}

bool NanoControlSim::inject(nanocontrol::SimFault fault, std_srvs::Trigger::Response& res) {
  std::lock_guard<std::mutex> lock(mutex_);
  device_->inject(fault);
  res.success = true;
  res.message = std::string("injected: ") + nanocontrol::to_string(fault);
  ROS_WARN_STREAM("mm3e_sim: " << res.message);
  return true;
}

bool NanoControlSim::on_port_lost(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res) {
  std::lock_guard<std::mutex> lock(mutex_);
  try {
    if (req.data) {
      pty_->vanish();
      lines_.clear();
    } else {
      pty_->reappear();
    }
  } catch (const std::runtime_error& e) {
    res.success = false;
    res.message = e.what();
    return true;
  }
  res.success = true;
  res.message = req.data ? "port vanished: pseudo-terminal closed (the driver sees EIO), " + options_.link_path + " removed"
                         : "port back: " + options_.link_path + " -> " + pty_->slave_path();
  ROS_WARN_STREAM("mm3e_sim: " << res.message);
  return true;
}

}  // namespace piezo::mm3e
