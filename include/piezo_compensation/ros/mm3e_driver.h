// The mm3e_driver node: ROS face of can::DriverCore (docs/driver.md). Per axis it publishes <axis>/voltage and
// <axis>/encoder, takes <axis>/command (queue 1), enforces one commander per axis, reports the bus through
// diagnostic_updater and offers ~halt and ~recover. With ~transport nanocontrol the same core drives a Kleindiek
// NanoControl on a serial port (docs/nanocontrol.md).
#pragma once

#include <diagnostic_updater/diagnostic_updater.h>
#include <ros/ros.h>
#include <std_srvs/Trigger.h>

#include <array>
#include <memory>
#include <mutex>
#include <string>

#include "piezo_compensation/VoltageCommand.h"
#include "piezo_compensation/can/driver_core.h"
#include "piezo_compensation/can/lockstep.h"
#include "piezo_compensation/nanocontrol/transport.h"
#include "piezo_compensation/ros/params.h"

namespace piezo::mm3e {

class DriverNode {
 public:
  // Reads and validates every parameter; throws std::invalid_argument naming the bad one.
  DriverNode(ros::NodeHandle nh, ros::NodeHandle pnh);
  ~DriverNode();

 private:
  // The constructor's parts: sync_mode and what it changes in the limits; the core's report callbacks; topics and
  // services; diagnostics; the tick (or the idle SYNC) and diagnostics timers.
  void read_sync_mode(params::ParamReader& r, can::DriverConfig& config);
  can::DriverCallbacks core_callbacks();
  void advertise(const params::NodeInterface& iface);
  void add_diagnostics(const std::string& hardware_id);
  void start_timers(double output_rate_hz, double diagnostic_period_s);
  void on_command(int axis, const piezo_compensation::VoltageCommand::ConstPtr& msg);
  void on_tick(const ros::TimerEvent&);
  void sync_locked();
  void check_commanders();
  bool on_halt(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res);
  bool on_recover(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res);
  void diagnose_bus(diagnostic_updater::DiagnosticStatusWrapper& stat);
  void diagnose_axis(int axis, diagnostic_updater::DiagnosticStatusWrapper& stat);
  ros::Time stamp_for(int axis, std::uint32_t sequence, double receive_time_s);

  ros::NodeHandle nh_, pnh_;
  std::string frame_id_;
  bool stamp_with_receive_time_ = true;
  std::unique_ptr<can::DriverCore> core_;
  std::shared_ptr<nanocontrol::LinkMonitor> link_monitor_;  // transport nanocontrol only
  nanocontrol::LinkCounters last_link_counters_;            // at the previous diagnostics update
  std::array<ros::Publisher, can::kAxisCount> voltage_pub_, encoder_pub_;
  std::array<ros::Subscriber, can::kAxisCount> command_sub_;
  std::array<bool, can::kAxisCount> multiple_commanders_{};
  ros::ServiceServer halt_srv_, recover_srv_;
  ros::Timer tick_timer_;
  // Synchronous mode (~sync_mode): the controller samples on our SYNC, not on its clock. Bus time advances one
  // encoder period per SYNC and is the limiter's clock, so slew and watchdog count samples, whatever the wall
  // or ROS time does. When a SYNC goes out is can::SyncGate (every commanded axis has its command for the sample,
  // at most ~sync_max_in_flight SYNCs without a reading), or after ~sync_idle_s without one (so an idle device
  // still reports).
  bool sync_mode_ = false;
  double sync_idle_s_ = 0.5;
  std::mutex sync_mutex_;  // sync_gate_, bus_time_s_, last_sync_wall_: the command, reading and idle paths
  double bus_time_s_ = 0.0;
  can::SyncGate sync_gate_;
  ros::WallTime last_sync_wall_;
  ros::WallTimer sync_idle_timer_;
  ros::WallTimer diag_timer_;
  diagnostic_updater::Updater updater_;
  // Counters at the previous diagnostics update, for frame rates.
  ros::WallTime last_diag_;
  std::array<std::uint64_t, can::kAxisCount> last_encoder_frames_{}, last_voltage_frames_{}, last_sent_{};
  double encoder_timeout_s_ = 0.5;
  double sample_period_s_ = 1.0 / 11.0;
  double heartbeat_period_s_ = 1.0;
  // Under sim time: per-axis anchor (sequence, stamp) so stamps advance by exactly one period per sample.
  struct Anchor {
    bool set = false;
    std::uint32_t sequence = 0;
    double stamp_s = 0.0;
  };
  std::mutex anchor_mutex_;
  std::array<Anchor, can::kAxisCount> anchors_{};
};

}  // namespace piezo::mm3e
