// mm3e_sim with ~transport nanocontrol: the simulated NanoControl (nanocontrol::SimDevice over the node's
// simulator) answering on a pseudo-terminal at ~port, in real time, with the fault injections of
// docs/nanocontrol.md. Publishes <axis>/true_position once per sample as the driver takes it (counter reads closed
// by a `fine16 ?`: the mean true position at those reads, numbered as the driver numbers its samples while no
// reply is lost) and <axis>/device_set_point for every set point the controller took, so a test sees each voltage
// that reached it.
#pragma once

#include <ros/ros.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>

#include <array>
#include <atomic>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "piezo_compensation/nanocontrol/line_protocol.h"
#include "piezo_compensation/nanocontrol/pseudo_terminal.h"
#include "piezo_compensation/nanocontrol/sim_device.h"
#include "piezo_compensation/ros/params.h"
#include "piezo_compensation/sim/manipulator_simulator.h"

namespace piezo::mm3e {

class NanoControlSim {
 public:
  struct Options {
    std::string link_path;
    nanocontrol::SimDeviceConfig device;
    double reply_delay_s = 0.016;
    std::string frame_id;
  };
  // mutex: held around every use of `simulator` (the node's thermal-drift service shares it).
  NanoControlSim(ros::NodeHandle nh, ros::NodeHandle pnh, const params::NodeInterface& iface, const Options& options,
                 sim::ManipulatorSimulator& simulator, std::mutex& mutex);
  ~NanoControlSim();
  std::string describe() const;

 private:
  void run();
  void serve(int fd);
  void publish_sample(const nanocontrol::SimDevice::Answer& a);
  bool inject(nanocontrol::SimFault fault, std_srvs::Trigger::Response& res);
  bool on_port_lost(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res);

  ros::NodeHandle nh_, pnh_;
  Options options_;
  std::mutex& mutex_;  // device_, pty_, lines_
  std::unique_ptr<nanocontrol::PseudoTerminal> pty_;
  std::unique_ptr<nanocontrol::SimDevice> device_;
  nanocontrol::LineBuffer lines_;
  std::array<ros::Publisher, 3> truth_pub_, set_point_pub_;
  ros::Publisher temperature_pub_;
  std::array<std::uint32_t, 3> set_points_{};
  std::uint32_t samples_ = 0;
  ros::ServiceServer error_srv_, breakdown_srv_, lost_srv_, garbled_srv_, partial_srv_, port_srv_;
  std::atomic<bool> running_{true};
  std::thread thread_;
};

}  // namespace piezo::mm3e
