// The mm3e_sim node: a simulated MM3E controller on the same CAN protocol (can::DeviceCore backed by
// sim::ManipulatorSimulator), over SocketCAN or UDP. Publishes <axis>/true_position for evaluation and, with
// ~publish_clock, /clock at ~time_scale × real time so a demo runs faster than real time, or (~sync_mode) one
// period per SYNC frame from the driver, as fast as the host asks (docs/driver.md, docs/recorder.md). With
// ~transport nanocontrol it is a simulated Kleindiek NanoControl on a pseudo-terminal instead (docs/nanocontrol.md).
#pragma once

#include <ros/ros.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>

#include <array>
#include <atomic>
#include <memory>
#include <mutex>
#include <thread>

#include "piezo_compensation/can/device_core.h"
#include "piezo_compensation/can/transport.h"
#include "piezo_compensation/sim/manipulator_simulator.h"

namespace piezo::mm3e {

class NanoControlSim;

class SimNode {
 public:
  // Reads and validates every parameter; throws std::invalid_argument naming the bad one.
  SimNode(ros::NodeHandle nh, ros::NodeHandle pnh);
  ~SimNode();

 private:
  void run();
  void run_synchronous();
  void step_once(double t_s);  // one device sample at simulated time t_s (caller holds mutex_)
  void publish_clock(double t_s);
  bool on_bus_off(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res);
  bool on_garbage(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res);
  bool on_restart(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res);
  bool on_stuck(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res);
  bool on_thermal(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res);
  bool on_closed_port(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res);
  bool port_open();  // applies ~inject_closed_port on the loop thread (the one that receives)
  void send_all(const std::vector<can_frame>& frames);

  ros::NodeHandle nh_, pnh_;
  std::string frame_id_;
  double time_scale_ = 1.0;
  bool publish_clock_ = false;
  bool sync_mode_ = false;  // ~sync_mode: sample on the driver's SYNC frames, not on a clock
  double sync_max_time_scale_ = 0.0;  // ~sync_max_time_scale: ceiling on simulated/wall time in sync mode (0: none)
  std::uint32_t sequence_ = 0;
  double clock_rate_hz_ = 200.0;
  double fault_silence_s_ = 1.0;
  std::unique_ptr<sim::ManipulatorSimulator> simulator_;
  std::unique_ptr<can::DeviceCore> device_;
  std::unique_ptr<can::Transport> transport_;
  std::unique_ptr<NanoControlSim> nano_;  // ~transport nanocontrol: the serial device instead of the CAN one
  std::string transport_name_;
  std::mutex mutex_;  // device_ and transport_ between the loop and the fault services
  std::array<ros::Publisher, can::kAxisCount> truth_pub_;
  ros::Publisher temperature_pub_;  // the simulated temperature [°C] (ambient while thermal drift is off)
  ros::Publisher clock_pub_;
  ros::ServiceServer bus_off_srv_, garbage_srv_, restart_srv_, stuck_srv_, thermal_srv_, closed_port_srv_;
  std::atomic<bool> running_{true};
  std::atomic<double> silent_until_wall_s_{0.0};
  std::atomic<bool> port_closed_{false};  // ~inject_closed_port: the device's socket is closed
  std::thread thread_;
};

}  // namespace piezo::mm3e
