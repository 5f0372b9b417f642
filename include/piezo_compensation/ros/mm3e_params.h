// Start-up parameter reading shared by mm3e_driver and mm3e_sim: every read checks type and range and
// throws std::invalid_argument naming the fully resolved parameter, so a bad launch stops with one clear line.
#pragma once

#include <ros/ros.h>

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "piezo_compensation/can/protocol.h"
#include "piezo_compensation/can/transport.h"
#include "piezo_compensation/ros/params.h"

namespace piezo::mm3e {

double param_double(const ros::NodeHandle& nh, const std::string& name, double fallback, double min, double max);
int param_int(const ros::NodeHandle& nh, const std::string& name, int fallback, int min, int max);
bool param_bool(const ros::NodeHandle& nh, const std::string& name, bool fallback);
std::string param_string(const ros::NodeHandle& nh, const std::string& name, const std::string& fallback,
                         const std::vector<std::string>& allowed = {});

// ~protocol/<field> for every field of can::ProtocolConfig (docs/can_protocol.md), then validated.
can::ProtocolConfig read_protocol(params::ParamReader& reader);
can::ProtocolConfig read_protocol(const ros::NodeHandle& pnh);

struct TransportParams {
  std::string kind = "socketcan";  // socketcan | udp
  std::string interface = "can0";
  std::string host = "127.0.0.1";
  int local_port = 0;
  int remote_port = 0;
  std::string describe() const;   // "can0" or "udp 127.0.0.1:47100"
};
// ~transport, ~interface, ~udp_host, ~udp_local_port, ~udp_remote_port.
TransportParams read_transport(params::ParamReader& reader, int default_local_port, int default_remote_port);
TransportParams read_transport(const ros::NodeHandle& pnh, int default_local_port, int default_remote_port);

std::function<std::unique_ptr<can::Transport>()> transport_factory(const TransportParams& params,
                                                                   const std::vector<can_filter>& filters);

}  // namespace piezo::mm3e
